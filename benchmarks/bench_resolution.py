"""Accuracy over input resolution: the cpu preset's models at several (input size, crop) points.

Each point is the cpu preset (``stam/configs/cpu.toml``) with its input side and crop changed, run
as ``stam experiment`` on the same dataset (pretraining included): the test accuracy of each
(model, n) with its 95% interval, and the paired difference from the cpu preset's own point
(128 px of the central half; ``--base``), on the same test sequences. The millimetres of gel per input pixel
say what the model can resolve: a weave of pitch p needs a few pixels per p.

The full cpu preset costs 36 min of pretraining per point on 2 cores at 128 px, 4x that at 256 px.
``--per-fabric`` and ``--pretrain-epochs`` size the run: a subset of the dataset's sequences (the first
k of each fabric and split, a manifest beside symlinks to the videos, nothing copied) and fewer
pretraining epochs, the same for every point, so the points stay comparable with each other (not with
a full cpu-preset run). Usage::

    python benchmarks/bench_resolution.py --data DATASET --out OUT \\
        [--points 64:0.5,128:0.5,128:0.25,256:0.5] [--per-fabric 10,3,5] [--pretrain-epochs 4] \\
        [--models cnn stam] [--frames 2 5] [--json]

Resumable: a point whose ``OUT/s<px>-c<crop>.json`` exists is read back, and ``stam experiment``
resumes its own cells and pretraining. Writes ``OUT/resolution.json`` and ``OUT/resolution.png``.
"""
from __future__ import annotations

import argparse
import json
import time
import tomllib
from pathlib import Path

import numpy as np

from gelsim.atomic import atomic_write_json, atomic_write_text, write_figure
from gelsim.cli import print_json, run_script
from gelsim.errors import GelsimError
from stam.config import CONFIG_DIR
from stam.experiment import run_experiment
from stam.stats import bootstrap_intervals



def parse_points(text: str) -> list[tuple[int, float]]:
    """``"64:0.5,128:0.25"`` -> [(64, 0.5), (128, 0.25)]: input side px and crop fraction."""
    points = []
    for item in text.split(","):
        try:
            px, crop = item.split(":")
            points.append((int(px), float(crop)))
        except ValueError:
            raise GelsimError(f"--points item {item!r} is not PX:CROP; give e.g. 128:0.5") from None
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


def _correct(run: Path, model: str, n: int) -> dict[str, float]:
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
    ap.add_argument("--points", default="64:0.5,128:0.5,128:0.25,256:0.5",
                    help="input side px : crop fraction, comma-separated (default: %(default)s)")
    ap.add_argument("--per-fabric", default="10,3,5",
                    help="train,val,test sequences per fabric kept (default: %(default)s); 'all' keeps the dataset")
    ap.add_argument("--subset-dir", default=None, help="where the subset dataset goes (default: OUT/subset)")
    ap.add_argument("--base", default="128:0.5",
                    help="the point the others are compared with (default: the cpu preset's own, %(default)s)")
    ap.add_argument("--pretrain-epochs", type=int, default=4, help="pretraining epochs per point (default: %(default)s)")
    ap.add_argument("--models", nargs="+", default=["cnn", "stam"])
    ap.add_argument("--frames", nargs="+", type=int, default=[2, 5])
    ap.add_argument("--seeds", type=int, default=1)
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
        view_mm = crop * min(h, w) * mm_per_px
        rows.append({"px": px, "crop": crop, "view_mm": round(view_mm, 2), "mm_per_input_px": round(view_mm / px, 4),
                     "pretrain_val_frame_acc": res["pretrain"]["val_acc"], "run": str(out / f"out-{name}")})

    # Test accuracy per (model, n) and the paired difference from the base point, on the same sequences.
    base = next((r for r in rows if (r["px"], r["crop"]) == base_point), None)
    for m in args.models:
        for n in args.frames:
            col = f"{m}_n{n}"
            ref = _correct(Path(base["run"]), m, n) if base else None
            for r in rows:
                c = _correct(Path(r["run"]), m, n)
                ids = sorted(c)
                acc = bootstrap_intervals(np.array([[c[i]] for i in ids]))[0]
                r[col] = [round(100 * v, 1) for v in acc]
                if ref is not None and r is not base:
                    d = bootstrap_intervals(np.array([[c[i] - ref[i]] for i in ids]))[0]
                    r[col + "_minus_base"] = [round(100 * v, 1) for v in d]
    summary = {"data": str(data), "sequences": manifest["splits"], "pretrain_epochs": args.pretrain_epochs,
               "seeds": args.seeds, "base_point": list(base_point), "points": rows}
    atomic_write_json(out / "resolution.json", summary)
    _plot(out / "resolution.png", rows, args.models, args.frames)
    if args.json:
        print_json(summary)
    else:
        cols = [f"{m}_n{n}" for m in args.models for n in args.frames]
        print("| input px | crop | gel in view (mm) | mm per input px | pretrain val frame acc | "
              + " | ".join(f"{c} test % [95% CI]" for c in cols) + " |")
        print("|---" * (5 + len(cols)) + "|")
        for r in rows:
            cells = [f"{r[c][0]} [{r[c][1]}, {r[c][2]}]" for c in cols]
            print(f"| {r['px']} | {r['crop']:g} | {r['view_mm']} | {r['mm_per_input_px']} | "
                  f"{100 * r['pretrain_val_frame_acc']:.1f}% | " + " | ".join(cells) + " |")
        print(f"(written: {out / 'resolution.json'}, {out / 'resolution.png'})")
    return 0


def _plot(path: Path, rows: list[dict], models: list[str], frames: list[int]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for m in models:
        for n in frames:
            col = f"{m}_n{n}"
            for crop in sorted({r["crop"] for r in rows}):
                pts = sorted((r["mm_per_input_px"], *r[col]) for r in rows if r["crop"] == crop)
                x, y, lo, hi = (np.array(v) for v in zip(*pts))
                ax.errorbar(x, y, yerr=[y - lo, hi - y], marker="o", capsize=3,
                            label=f"{m} n={n}, crop {crop:g}")
    ax.set_xscale("log")
    ax.invert_xaxis()
    ax.set_xlabel("mm of gel per input pixel (finer to the right)")
    ax.set_ylabel("test accuracy, % (95% CI)")
    ax.set_title("Accuracy over input resolution (cpu preset)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    write_figure(path, fig, dpi=120)


if __name__ == "__main__":
    run_script(main)
