"""What the nuisance stages do to a dataset's frames, and to the image-based contact-onset detector.

For a stage-free dataset NONE and copies of it made with the same options and ``--nuisance LEVEL``
(``gelsim generate``), per dataset:

* the labels are byte-identical to NONE's (every sequence's labels sha256);
* the contact frames among each sequence's first two (what Table II's STAM row says keep their content):
  each frame's mean |difference| from NONE's, DN, and its median over those frames (issue 48's bar: 3 DN);
* frames that are black (mean under 1 DN), over all frames;
* how far the frames before contact (the manifest's ``contact_onset``) move from NONE's: mean |difference|
  in DN (mean and median over the frames), the share of them whose largest pixel change exceeds 1 DN, and the share of those frames whose change from NONE's (stam's onset statistic: the 99.9th
  percentile of the RGB distance on 160-px-wide thumbnails) exceeds the onset detector's bar
  (``stam.data.DEFAULT_ONSET_THRESHOLD``, 5 DN: above the H.264 steps of still frames and 6x the camera
  noise measured on lossless video, docs/stam.md), so more than the camera noise;
* the onset detector's agreement with the true onset (``stam.data.detect_onset`` with its defaults):
  exact and within one frame, with 95% Wilson intervals, and its errors (detected - true, frames).

``--figure PNG``: the first four frames of one sequence (the hairiest fabric's first sequence that starts
before contact) in every dataset, and each copy's difference from NONE's (x4).

    .venv/bin/python benchmarks/nuisance_effects.py NONE COPY [COPY ...] [--json OUT.json] [--figure OUT.png]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _load(d: Path) -> dict:
    return json.loads((d / "manifest.json").read_text())


def main(argv=None) -> int:
    from gelsim.video import read_video
    from stam.data import DEFAULT_ONSET_THRESHOLD, change_score, contact_scores, detect_onset, thumbnails
    from stam.stats import wilson_interval

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("none")
    p.add_argument("copies", nargs="+")
    p.add_argument("--json")
    p.add_argument("--figure")
    a = p.parse_args(argv)
    base = Path(a.none)
    mb = _load(base)
    seqs = {s["id"]: s for s in mb["sequences"]}
    dirs = [base] + [Path(c) for c in a.copies]
    results = {}
    cache: dict[str, np.ndarray] = {}
    for d in dirs:
        m = _load(d)
        other = {k for k in set(m["options"]) | set(mb["options"])
                 if k not in ("nuisance", "nuisance_severity") and m["options"].get(k) != mb["options"].get(k)}
        if other:
            raise SystemExit(f"gelsim: error: {d} was made with other options than {base} ({', '.join(sorted(other))}); "
                             "give copies made with the same options and --nuisance")
        lab_same = all(s["sha256"]["labels"] == seqs[s["id"]]["sha256"]["labels"] for s in m["sequences"])
        diffs, over, n_pre, exact, within, n = [], 0, 0, 0, 0, 0
        early, pre_frames, black, n_frames, over_1dn = [], [], 0, 0, 0
        errors: dict[str, int] = {}
        for s in m["sequences"]:
            fr = read_video(d / s["video"])
            onset = int(s["contact_onset"])
            if d == base:
                cache[s["id"]] = fr
            ref = cache.get(s["id"])
            if ref is None:
                ref = cache[s["id"]] = read_video(base / s["video"])
            black += int((fr.reshape(len(fr), -1).mean(axis=1) < 1.0).sum())
            n_frames += len(fr)
            for i in range(max(onset, 0), min(2, len(fr))):
                early.append(float(np.abs(fr[i].astype(np.float32) - ref[i].astype(np.float32)).mean()))
            if onset > 0:
                pre, pre_ref = fr[:onset].astype(np.float32), ref[:onset].astype(np.float32)
                diffs.append(float(np.abs(pre - pre_ref).mean()))
                pre_frames += [float(v) for v in np.abs(pre - pre_ref).mean(axis=(1, 2, 3))]
                over_1dn += int((np.abs(pre - pre_ref).max(axis=(1, 2, 3)) > 1.0).sum())
                if d != base:
                    sc = change_score(thumbnails(fr[:onset]), thumbnails(ref[:onset]))
                    over += int((sc > DEFAULT_ONSET_THRESHOLD).sum())
                    n_pre += onset
            scores, noise = contact_scores(fr)
            det = detect_onset(scores, noise_dn=noise)
            if onset >= 0:
                n += 1
                exact += int(det == onset)
                key = "none" if det is None else str(det - onset)
                errors[key] = errors.get(key, 0) + 1
                within += int(det is not None and abs(det - onset) <= 1)
        name = "none" if d == base else d.name
        res = {"dir": str(d), "level": m["options"].get("nuisance", "none"),
               "severity": m["options"].get("nuisance_severity"), "labels_identical": lab_same,
               "precontact_mean_abs_diff_dn": float(np.mean(diffs)) if diffs else 0.0,
               "precontact_frame_diff_dn": {"mean": float(np.mean(pre_frames)) if pre_frames else 0.0,
                                            "median": float(np.median(pre_frames)) if pre_frames else 0.0,
                                            "frames": len(pre_frames), "largest_pixel_over_1dn": over_1dn},
               "early_contact_frame_diff_dn": {"median": float(np.median(early)) if early else 0.0,
                                               "mean": float(np.mean(early)) if early else 0.0,
                                               "p90": float(np.percentile(early, 90)) if early else 0.0,
                                               "frames": len(early)},
               "black_frames": black, "frames": n_frames,
               "onset_exact": exact, "onset_within_1": within, "sequences": n,
               "onset_exact_ci": wilson_interval(exact, n), "onset_within_1_ci": wilson_interval(within, n),
               "onset_errors": dict(sorted(errors.items(), key=lambda kv: (kv[0] == "none", int(kv[0]) if kv[0] != "none" else 0)))}
        if d != base:
            res["precontact_frames_over_bar"] = over
            res["precontact_frames"] = n_pre
        results[name] = res
        e = res["early_contact_frame_diff_dn"]
        print(f"{name}: level {res['level']} severity {res['severity']}; labels identical {lab_same}; "
              f"contact frames in frames 0-1: |diff| median {e['median']:.2f} DN (mean {e['mean']:.2f}, 90th pct "
              f"{e['p90']:.2f}, {e['frames']} frames); black frames {black}/{n_frames}; pre-contact |diff| "
              f"{res['precontact_mean_abs_diff_dn']:.2f} DN (per frame: mean {res['precontact_frame_diff_dn']['mean']:.2f}, "
              f"median {res['precontact_frame_diff_dn']['median']:.2f}; {over_1dn}/{len(pre_frames)} with a pixel "
              f"changed by more than 1 DN)"
              + (f", {over}/{n_pre} pre-contact frames change by more than the {DEFAULT_ONSET_THRESHOLD:g} DN bar"
                 if d != base else "")
              + f"; onset exact {exact}/{n} ({100 * exact / n:.1f}%), within 1 {within}/{n} ({100 * within / n:.1f}%, "
              f"95% CI {100 * res['onset_within_1_ci'][0]:.1f}-{100 * res['onset_within_1_ci'][1]:.1f})", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    if a.figure:
        _figure(dirs, mb, Path(a.figure))
    return 0


def _figure(dirs: list[Path], mb: dict, out: Path) -> None:
    """Frames 0-3 of one sequence per dataset, and each copy's |difference| from the first dataset's (x4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from gelsim.fabrics import load_catalog
    from gelsim.video import read_video

    cat = load_catalog()
    seqs = [s for s in mb["sequences"] if s["contact_onset"] >= 1]
    s = max(seqs, key=lambda r: (cat[r["fabric_id"]].hairiness, -int(r["id"].split("s")[-1])))
    frames = [read_video(d / s["video"])[:4] for d in dirs]
    rows = len(dirs) + len(dirs) - 1
    fig, ax = plt.subplots(rows, 4, figsize=(10, 2.0 * rows), squeeze=False)
    names = ["none"] + [_load(d)["options"].get("nuisance", d.name) for d in dirs[1:]]
    for r, (name, fr) in enumerate(zip(names, frames)):
        for c in range(4):
            ax[r, c].imshow(fr[c])
            ax[r, c].set_title(f"{name}, frame {c}" + (" (contact)" if c >= s["contact_onset"] else ""), fontsize=8)
    for k, (name, fr) in enumerate(zip(names[1:], frames[1:])):
        for c in range(4):
            d = np.abs(fr[c].astype(np.int16) - frames[0][c].astype(np.int16)).sum(axis=2)
            ax[len(dirs) + k, c].imshow(np.clip(d * 4, 0, 255), cmap="magma", vmin=0, vmax=255)
            ax[len(dirs) + k, c].set_title(f"|{name} - none| x4, frame {c}", fontsize=8)
    for a_ in ax.ravel():
        a_.axis("off")
    fig.suptitle(f"{s['id']} ({cat[s['fabric_id']].name}, hairiness {cat[s['fabric_id']].hairiness}); "
                 f"contact from frame {s['contact_onset']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=80)


if __name__ == "__main__":
    sys.exit(main())
