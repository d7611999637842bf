"""Accuracy over input resolution: one classifier at several (input size, crop) points of the same sequences.

``--method stam`` (default): each point is the cpu preset (``stam/configs/cpu.toml``) with its input side
and crop changed, run as ``stam experiment`` (pretraining included): the test accuracy of each (model, n).
``--method probe``: a linear classifier on each in-contact frame's texture spectrum (:class:`SpectrumBands`),
minutes at any resolution. Either way: the 95% interval of each accuracy and the paired difference from the
cpu preset's own point (128 px of the central half; ``--base``) on the same test sequences. The millimetres
of gel per input pixel say what the model can resolve: a weave of pitch p needs a few pixels per p.

The full cpu preset's pretraining (16 epochs) costs about 30-60 min per point on 2 cores at 128 px, 4x that at
256 px.
``--per-fabric`` sizes the run: a subset of the dataset's sequences (the first k of each fabric and split, a
manifest beside symlinks to the videos, nothing copied). ``--pretrain-epochs`` defaults to the preset's
(16; docs/stam_results.md's runs used 8): with 4, the backbone stayed at chance (it took off at epochs 2-4 at 128 px
on 1,000 training sequences, at Adam 1e-3; at 64 px and the preset's 3e-4 since, at epochs 4-5).
Usage::

    python benchmarks/bench_resolution.py --data DATASET --out OUT \\
        [--method stam|probe] [--points 64:0.5,128:0.5,128:0.25,256:0.5] [--per-fabric 10,3,5] \\
        [--pretrain-epochs 8] [--models cnn stam] [--frames 2 5] [--json]

Resumable: a stam point whose ``OUT/s<px>-c<crop>.json`` exists is read back (and ``stam experiment``
resumes its own cells and pretraining); the probe's features are cached in ``OUT/probe_features.npz``.
Writes ``OUT/resolution.{json,png}`` (stam) or ``OUT/resolution_probe.{json,png}`` (probe).
"""
from __future__ import annotations

import argparse
import json
import time
import tomllib
from pathlib import Path

import numpy as np

from gelsim.atomic import atomic_open, atomic_write_json, atomic_write_text, write_figure
from gelsim.cli import print_json, run_script
from gelsim.errors import GelsimError
from stam.config import CONFIG_DIR, load_preset
from stam.experiment import run_experiment
from stam.stats import bootstrap_intervals


def parse_points(text: str) -> list[tuple[int, float]]:
    """``"64:0.5,128:0.25"`` -> [(64, 0.5), (128, 0.25)]: input side px and crop fraction."""
    points = []
    for item in text.split(","):
        try:
            px, crop = item.split(":")
            px, crop = int(px), float(crop)
        except ValueError:
            raise GelsimError(f"--points item {item!r} is not PX:CROP; give e.g. 128:0.5") from None
        if px < 8 or not 0.05 <= crop <= 1.0:
            raise GelsimError(f"--points item {item!r}: give at least 8 px and a crop of 0.05-1")
        points.append((px, crop))
    return points


def subset(data: Path, where: Path, per_split: dict[str, int]) -> Path:
    """A dataset at ``where`` holding the first ``per_split[split]`` sequences of each fabric in each split of
    ``data``: its manifest, and symlinks to ``data``'s videos and labels. Rewritten only if it differs."""
    m = json.loads((data / "manifest.json").read_text())
    counts: dict[tuple, int] = {}
    keep = []
    for s in m["sequences"]:
        key = (s["fabric_id"], s["split"])
        if counts.get(key, 0) < per_split[s["split"]]:
            counts[key] = counts.get(key, 0) + 1
            keep.append(s)
    m["sequences"] = keep
    m["splits"] = {k: sum(s["split"] == k for s in keep) for k in per_split}
    where.mkdir(parents=True, exist_ok=True)
    for name in ("videos", "labels"):
        link = where / name
        if not link.exists():
            link.symlink_to((data / name).resolve())
    path = where / "manifest.json"
    if not path.is_file() or json.loads(path.read_text()) != m:
        atomic_write_text(path, json.dumps(m))
    return where


def _toml(cfg: dict) -> str:
    """Tables of scalars and lists as TOML (all a preset holds)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)
    return "\n".join(f"[{name}]\n" + "".join(f"{k} = {value(v)}\n" for k, v in table.items())
                     for name, table in cfg.items())


def point_preset(out: Path, px: int, crop: float, pretrain_epochs: int | None) -> Path:
    """The cpu preset at input side ``px`` and ``crop`` (and ``pretrain_epochs``), written to ``out``."""
    cfg = tomllib.loads((CONFIG_DIR / "cpu.toml").read_text())
    cfg["pretrain"]["image_size"] = cfg["train"]["image_size"] = px
    cfg["train"]["crop"] = crop
    if pretrain_epochs:
        cfg["pretrain"]["epochs"] = pretrain_epochs
    path = out / f"s{px}-c{crop:g}.toml"
    atomic_write_text(path, _toml(cfg))
    return path


# The probe's features: the log power of each colour channel's spectrum in bands of spatial frequency on
# the gel (cycles per mm; pitches from 4 mm down to 0.02 mm) and orientation. Only the bands wholly below
# a point's Nyquist frequency exist there: what a coarser input cannot resolve is absent, not aliased.
PROBE_BANDS_CPMM = np.geomspace(0.25, 50.0, 25)
PROBE_ORIENTATIONS = 6
PROBE_WEIGHT_DECAYS = (1e-4, 1e-3, 1e-2)   # picked per point on the validation split
PROBE_STEPS = 300                          # full-batch Adam steps of the linear classifier
PROBE_LR = 0.01
PROBE_FRAME_STRIDE = 2                     # every 2nd in-contact frame, as the cpu preset's pretraining


class SpectrumBands:
    """The band of each frequency sample of an ``(rows, cols)`` input whose pixels are ``mm_y`` x ``mm_x`` of gel.

    ``features(img)``: float32 ``(F,)`` for a uint8 ``(rows, cols, 3)`` image: per channel, log10 of the mean
    power in each band (the image's mean removed, a Hann window applied), then each channel's mean level
    (the shading). ``F = 3 (bands + 1)``."""

    def __init__(self, rows: int, cols: int, mm_y: float, mm_x: float):
        fy = np.fft.fftfreq(rows, d=mm_y)[:, None]
        fx = np.fft.rfftfreq(cols, d=mm_x)[None, :]
        r = np.hypot(fy, fx)
        theta = np.mod(np.arctan2(fy, fx), np.pi)
        radial = np.digitize(r, PROBE_BANDS_CPMM) - 1              # -1 below the first edge
        nyquist = min(0.5 / mm_y, 0.5 / mm_x)
        n_radial = int(np.searchsorted(PROBE_BANDS_CPMM, nyquist, side="right")) - 1   # bands below Nyquist
        angle = np.minimum((theta / np.pi * PROBE_ORIENTATIONS).astype(int), PROBE_ORIENTATIONS - 1)
        band = np.where((radial >= 0) & (radial < n_radial), radial * PROBE_ORIENTATIONS + angle, -1).ravel()
        nb = max(1, n_radial) * PROBE_ORIENTATIONS
        counts = np.bincount(band[band >= 0], minlength=nb)
        self.keep = np.flatnonzero(counts > 0)                      # bands holding a frequency sample
        # The spectrum's samples in a band, as flat indices into the (rows, cols // 2 + 1, 3) power array,
        # and their band per channel (band + channel * nb): one bincount sums all three channels.
        inside = np.flatnonzero(band >= 0)
        self.samples = (inside[:, None] * 3 + np.arange(3)[None, :]).ravel()
        self.bins = (band[inside][:, None] + nb * np.arange(3)[None, :]).ravel()
        self.nb = nb
        self.mean_power_of = (np.arange(3)[:, None] * nb + self.keep[None, :]).ravel()
        self.norm = np.tile(counts[self.keep], 3).astype(np.float64)
        self.window = (np.hanning(rows)[:, None] * np.hanning(cols)[None, :]).astype(np.float32)[..., None]
        self.size = 3 * (self.keep.size + 1)

    def features(self, img: np.ndarray) -> np.ndarray:
        import scipy.fft

        x = img.astype(np.float32) / np.float32(255.0)
        mean = x.mean(axis=(0, 1))
        z = scipy.fft.rfft2((x - mean) * self.window, axes=(0, 1))       # single precision, all channels
        power = (z.real * z.real + z.imag * z.imag).ravel()
        sums = np.bincount(self.bins, weights=power[self.samples], minlength=3 * self.nb)
        return np.concatenate([np.log10(sums[self.mean_power_of] / self.norm + 1e-12), mean]).astype(np.float32)


def probe_features(data: Path, out: Path, points, shape: tuple[int, int], mm_per_px: float, *, quiet: bool = False):
    """Every sequence's in-contact frames (from the onset detected in the images; every PROBE_FRAME_STRIDE-th,
    as stam's pretraining takes them) as :class:`SpectrumBands` features at each point, decoding each video once; cached in
    ``OUT/probe_features.npz``. Returns (features per point, float32 (frames, F); the frames' sequence
    index; the dataset's sequences, whose id, label and split the classifier reads)."""
    from gelsim.video import read_video
    from stam.data import DEFAULT_ONSET_THRESHOLD, TactileDataset, contact_scores, detect_onset, model_input

    ds = TactileDataset(data)
    seqs = ds.sequences
    names = [f"s{px}-c{crop:g}" for px, crop in points]
    cache = out / "probe_features.npz"
    meta = {"ids": [q.id for q in seqs], "points": names, "bands": PROBE_BANDS_CPMM.tolist(),
            "orientations": PROBE_ORIENTATIONS, "stride": PROBE_FRAME_STRIDE}
    if cache.is_file():
        with np.load(cache) as z:
            if json.loads(str(z["meta"])) == meta:
                return [z[n] for n in names], z["seq"], seqs
    h, w = shape
    bands = []
    for px, crop in points:
        view_y = (crop * min(h, w) if crop < 1 else h) * mm_per_px
        view_x = (crop * min(h, w) if crop < 1 else w) * mm_per_px
        bands.append(SpectrumBands(px, px, view_y / px, view_x / px))
    feats = [[] for _ in points]
    owner = []
    from tqdm import tqdm

    for i, q in enumerate(tqdm(seqs, desc="probe features", disable=quiet)):
        frames = read_video(q.video)
        scores, noise = contact_scores(frames)
        onset = detect_onset(scores, DEFAULT_ONSET_THRESHOLD, noise)
        for f in frames[onset if onset is not None else 0::PROBE_FRAME_STRIDE]:
            owner.append(i)
            for k, (px, crop) in enumerate(points):
                feats[k].append(bands[k].features(model_input(f, px, crop)))
    feats = [np.stack(f) for f in feats]
    owner = np.asarray(owner, np.int32)
    with atomic_open(cache) as fh:
        np.savez(fh, meta=json.dumps(meta), seq=owner, **dict(zip(names, feats)))
    return feats, owner, seqs


def probe_correct(x: np.ndarray, owner: np.ndarray, seqs) -> tuple[dict[str, float], float, float]:
    """A linear classifier (multinomial logistic regression, standardised features, full-batch Adam) trained
    on the training sequences' frames, its weight decay picked on the validation sequences; a sequence's
    prediction is the mean of its frames' log-probabilities. Returns (test id -> 1/0 correct, validation
    accuracy, the weight decay)."""
    import torch

    split = np.array([q.split for q in seqs])[owner]
    labels = torch.as_tensor(np.array([q.label for q in seqs])[owner], dtype=torch.long)
    tr = split == "train"
    mu, sd = x[tr].mean(axis=0), x[tr].std(axis=0) + 1e-6
    xt = torch.as_tensor((x - mu) / sd, dtype=torch.float32)
    n_cls = int(max(q.label for q in seqs)) + 1
    own = torch.as_tensor(owner, dtype=torch.long)

    def fit(wd):
        torch.manual_seed(0)
        model = torch.nn.Linear(xt.shape[1], n_cls)
        opt = torch.optim.Adam(model.parameters(), lr=PROBE_LR, weight_decay=wd)
        idx = torch.as_tensor(np.flatnonzero(tr))
        for _ in range(PROBE_STEPS):
            opt.zero_grad()
            torch.nn.functional.cross_entropy(model(xt[idx]), labels[idx]).backward()
            opt.step()
        return model

    def per_sequence(model, name):
        rows = np.flatnonzero(split == name)
        with torch.no_grad():
            logp = torch.log_softmax(model(xt[rows]), dim=1)
        total = torch.zeros(len(seqs), n_cls).index_add_(0, own[rows], logp)
        pred = total.argmax(dim=1).numpy()
        return {seqs[i].id: float(pred[i] == seqs[i].label) for i in sorted(set(owner[rows].tolist()))}

    best = None
    for wd in PROBE_WEIGHT_DECAYS:
        model = fit(wd)
        val = per_sequence(model, "val")
        acc = float(np.mean(list(val.values())))
        if best is None or acc > best[0]:
            best = (acc, wd, model)
    return per_sequence(best[2], "test"), best[0], best[1]


def _probe_points(data: Path, out: Path, points, rows, shape, mm_per_px: float, *, quiet: bool):
    """The probe at each point; per point, {"probe": test id -> correctness}."""
    feats, owner, seqs = probe_features(data, out, points, shape, mm_per_px, quiet=quiet)
    correct = []
    for x, row in zip(feats, rows):
        test, val_acc, wd = probe_correct(x, owner, seqs)
        row.update(features=int(x.shape[1]), probe_val_acc=round(100 * val_acc, 1), weight_decay=wd)
        correct.append({"probe": test})
    return correct


def seed_correctness(run: Path, model: str, n: int) -> dict[str, float]:
    """Test sequence id -> correctness (seed-averaged) of one cell of a clean-setting run."""
    by_id: dict[str, list[float]] = {}
    for f in sorted((run / "cells" / "clean" / f"n{n}" / model).glob("seed*/result.json")):
        cell = json.loads(f.read_text())
        for i, c in zip(cell["test_ids"], cell["test_correct"]):
            by_id.setdefault(i, []).append(float(c))
    return {i: float(np.mean(v)) for i, v in by_id.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a gelsim dataset (e.g. `gelsim generate --fabrics 100`)")
    ap.add_argument("--out", required=True, help="output directory (resumable)")
    ap.add_argument("--method", choices=["stam", "probe"], default="stam",
                    help="stam: the cpu preset's models (stam experiment); probe: a linear classifier on the "
                         "frames' texture spectra (minutes, any resolution; see probe_features) (default: %(default)s)")
    ap.add_argument("--points", default="64:0.5,128:0.5,128:0.25,256:0.5",
                    help="input side px : crop fraction, comma-separated (default: %(default)s)")
    ap.add_argument("--per-fabric", default="10,3,5",
                    help="train,val,test sequences per fabric kept (default: %(default)s); 'all' keeps the dataset")
    ap.add_argument("--subset-dir", default=None, help="where the subset dataset goes (default: OUT/subset)")
    ap.add_argument("--base", default="128:0.5",
                    help="the point the others are compared with (default: the cpu preset's own, %(default)s)")
    ap.add_argument("--pretrain-epochs", type=int, default=None,
                    help="stam: pretraining epochs per point (default: the cpu preset's)")
    ap.add_argument("--models", nargs="+", default=["cnn", "stam"], help="stam: the models")
    ap.add_argument("--frames", nargs="+", type=int, default=[2, 5], help="stam: window lengths n")
    ap.add_argument("--seeds", type=int, default=1, help="stam: seeds per cell")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Path(args.data)
    if not (data / "manifest.json").is_file():
        raise GelsimError(f"{data} has no manifest.json; pass the --out directory of `gelsim generate`")
    points = parse_points(args.points)
    base_point = parse_points(args.base)[0]
    if args.per_fabric != "all":
        try:
            k = [int(v) for v in args.per_fabric.split(",")]
            per_split = dict(zip(("train", "val", "test"), k, strict=True))
        except ValueError:
            raise GelsimError(f"--per-fabric {args.per_fabric!r}: give three counts, e.g. 10,3,5, or all") from None
        data = subset(data, Path(args.subset_dir) if args.subset_dir else out / "subset", per_split)
    manifest = json.loads((data / "manifest.json").read_text())
    prof = manifest["profile"]      # the frames' size and scale, as generated
    h, w, mm_per_px = prof["height_px"], prof["width_px"], prof["mm_per_px"]

    rows = []
    for px, crop in points:
        view_mm = crop * min(h, w) * mm_per_px
        rows.append({"px": px, "crop": crop, "view_mm": round(view_mm, 2), "mm_per_input_px": round(view_mm / px, 4)})
    if args.method == "stam":
        cols = [f"{m}_n{n}" for m in args.models for n in args.frames]
        correct = _stam_points(data, out, points, rows, args)
        epochs = args.pretrain_epochs or load_preset("cpu").pretrain.epochs
        extra = {"pretrain_epochs": epochs, "seeds": args.seeds}
    else:
        cols = ["probe"]
        correct = _probe_points(data, out, points, rows, (h, w), mm_per_px, quiet=args.json)
        extra = {"probe": {"bands_cycles_per_mm": [float(PROBE_BANDS_CPMM[0]), float(PROBE_BANDS_CPMM[-1])],
                           "band_edges": len(PROBE_BANDS_CPMM), "orientations": PROBE_ORIENTATIONS}}
    _accuracies(rows, correct, cols, base_point)
    summary = {"data": str(data), "method": args.method, "sequences": manifest["splits"], **extra,
               "base_point": list(base_point), "points": rows}
    stem = "resolution" if args.method == "stam" else "resolution_probe"
    atomic_write_json(out / f"{stem}.json", summary)
    _plot(out / f"{stem}.png", rows, cols, args.method)
    if args.json:
        print_json(summary)
    else:
        first = "pretrain val frame acc" if args.method == "stam" else "probe features"
        print("| input px | crop | gel in view (mm) | mm per input px | " + first + " | "
              + " | ".join(f"{c} test % [95% CI]" for c in cols)
              + " | " + " | ".join(f"{c} minus base [95% CI]" for c in cols) + " |")
        print("|---" * (5 + 2 * len(cols)) + "|")
        for r in rows:
            cells = [f"{r[c][0]} [{r[c][1]}, {r[c][2]}]" for c in cols]
            diffs = [(lambda d: f"{d[0]:+.1f} [{d[1]:+.1f}, {d[2]:+.1f}]")(r[c + "_minus_base"])
                     if c + "_minus_base" in r else "(base)" for c in cols]
            lead = (f"{100 * r['pretrain_val_frame_acc']:.1f}%" if args.method == "stam" else str(r["features"]))
            print(f"| {r['px']} | {r['crop']:g} | {r['view_mm']} | {r['mm_per_input_px']} | {lead} | "
                  + " | ".join(cells + diffs) + " |")
        print(f"(written: {out / (stem + '.json')}, {out / (stem + '.png')})")
    return 0


def _stam_points(data: Path, out: Path, points, rows, args) -> list[dict[str, dict[str, float]]]:
    """Run (or read back) ``stam experiment`` at each point; per point, column -> test id -> correctness."""
    correct = []
    for (px, crop), row in zip(points, rows):
        name = f"s{px}-c{crop:g}"
        res_path = out / f"{name}.json"
        if res_path.is_file():
            res = json.loads(res_path.read_text())
        else:
            t0 = time.perf_counter()
            res = run_experiment(str(data), out / f"out-{name}", str(point_preset(out, px, crop, args.pretrain_epochs)),
                                 seeds=args.seeds, models=args.models, frames=args.frames, settings=["clean"],
                                 log=None if args.json else print)
            res["wall_seconds"] = round(time.perf_counter() - t0, 1)
            atomic_write_json(res_path, res)
        row.update(pretrain_val_frame_acc=res["pretrain"]["val_acc"], run=str(out / f"out-{name}"))
        correct.append({f"{m}_n{n}": seed_correctness(out / f"out-{name}", m, n) for m in args.models for n in args.frames})
    return correct


def _accuracies(rows, correct, cols, base_point) -> None:
    """Each row's test accuracy per column, % [95% CI], and its paired difference from the base point's
    (the same test sequences, the same bootstrap resamples)."""
    base = next((i for i, r in enumerate(rows) if (r["px"], r["crop"]) == base_point), None)
    for col in cols:
        ref = correct[base][col] if base is not None else None
        for i, r in enumerate(rows):
            c = correct[i][col]
            ids = sorted(c)
            r[col] = [round(100 * v, 1) for v in bootstrap_intervals(np.array([[c[k]] for k in ids]))[0]]
            if ref is not None and i != base:
                d = bootstrap_intervals(np.array([[c[k] - ref[k]] for k in ids]))[0]
                r[col + "_minus_base"] = [round(100 * v, 1) for v in d]


def _plot(path: Path, rows: list[dict], cols: list[str], method: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for col in cols:
        for crop in sorted({r["crop"] for r in rows}):
            pts = sorted((r["mm_per_input_px"], *r[col]) for r in rows if r["crop"] == crop)
            x, y, lo, hi = (np.array(v) for v in zip(*pts))
            ax.errorbar(x, y, yerr=[y - lo, hi - y], marker="o", capsize=3,
                        label=f"{col.replace('_n', ' n=')}, crop {crop:g}")
    ax.set_xscale("log")
    ticks = sorted({r["mm_per_input_px"] for r in rows})
    ax.set_xticks(ticks, [f"{t:.3g}" for t in ticks], fontsize=7)
    ax.minorticks_off()
    ax.invert_xaxis()
    ax.set_xlabel("mm of gel per input pixel (finer to the right)")
    ax.set_ylabel("test accuracy, % (95% CI)")
    ax.set_title("Accuracy over input resolution: " + ("cpu preset" if method == "stam" else "texture-spectrum probe"))
    ax.legend(fontsize=7)
    fig.tight_layout()
    write_figure(path, fig, dpi=120)


if __name__ == "__main__":
    run_script(main)
