"""What the nuisance stages do to a dataset's frames, and to the image-based contact-onset detector.

For a stage-free dataset NONE and copies of it made with the same options and ``--nuisance LEVEL``
(``gelsim generate``), per dataset:

* the labels are byte-identical to NONE's (every sequence's labels sha256);
* how far the frames before contact (the manifest's ``contact_onset``) move from NONE's: mean |difference|
  in DN, and the share of those frames whose change from NONE's (stam's onset statistic: the 99.9th
  percentile of the RGB distance on 160-px-wide thumbnails) exceeds the onset detector's bar
  (``stam.data.DEFAULT_ONSET_THRESHOLD``, 5 DN: above the H.264 steps of still frames and 6x the camera
  noise measured on lossless video, docs/stam.md), so more than the camera noise;
* the onset detector's agreement with the true onset (``stam.data.detect_onset`` with its defaults):
  exact and within one frame, with 95% Wilson intervals.

    .venv/bin/python benchmarks/nuisance_effects.py NONE COPY [COPY ...] [--json OUT.json]
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
        for s in m["sequences"]:
            fr = read_video(d / s["video"])
            onset = int(s["contact_onset"])
            if d == base:
                cache[s["id"]] = fr
            ref = cache.get(s["id"])
            if ref is None:
                ref = cache[s["id"]] = read_video(base / s["video"])
            if onset > 0:
                pre, pre_ref = fr[:onset].astype(np.float32), ref[:onset].astype(np.float32)
                diffs.append(float(np.abs(pre - pre_ref).mean()))
                if d != base:
                    sc = change_score(thumbnails(fr[:onset]), thumbnails(ref[:onset]))
                    over += int((sc > DEFAULT_ONSET_THRESHOLD).sum())
                    n_pre += onset
            scores, noise = contact_scores(fr)
            det = detect_onset(scores, noise_dn=noise)
            if onset >= 0:
                n += 1
                exact += int(det == onset)
                within += int(det is not None and abs(det - onset) <= 1)
        name = "none" if d == base else d.name
        res = {"dir": str(d), "level": m["options"].get("nuisance", "none"),
               "severity": m["options"].get("nuisance_severity"), "labels_identical": lab_same,
               "precontact_mean_abs_diff_dn": float(np.mean(diffs)) if diffs else 0.0,
               "onset_exact": exact, "onset_within_1": within, "sequences": n,
               "onset_exact_ci": wilson_interval(exact, n), "onset_within_1_ci": wilson_interval(within, n)}
        if d != base:
            res["precontact_frames_over_bar"] = over
            res["precontact_frames"] = n_pre
        results[name] = res
        print(f"{name}: level {res['level']} severity {res['severity']}; labels identical {lab_same}; pre-contact |diff| "
              f"{res['precontact_mean_abs_diff_dn']:.2f} DN"
              + (f", {over}/{n_pre} pre-contact frames change by more than the {DEFAULT_ONSET_THRESHOLD:g} DN bar"
                 if d != base else "")
              + f"; onset exact {exact}/{n} ({100 * exact / n:.1f}%), within 1 {within}/{n} ({100 * within / n:.1f}%, "
              f"95% CI {100 * res['onset_within_1_ci'][0]:.1f}-{100 * res['onset_within_1_ci'][1]:.1f})", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
