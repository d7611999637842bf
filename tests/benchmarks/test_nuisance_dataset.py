"""benchmarks/nuisance_dataset.py and nuisance_effects.py on a quick dataset: labels kept byte for byte, the
frames before contact changed by the camera stages, the same bytes for any number of workers."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_nuisance_copy_keeps_labels_and_changes_the_first_frames(tmp_path):
    from gelsim.video import read_video

    src = tmp_path / "none"
    r = subprocess.run([sys.executable, "-m", "gelsim", "generate", "--preset", "quick", "--fabrics", "3",
                        "--out", str(src), "--workers", "1", "--no-previews"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    outs = []
    for workers, name in ((1, "a"), (2, "b")):
        dst = tmp_path / name
        r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "nuisance_dataset.py"), str(src), str(dst),
                            "--level", "handheld", "--workers", str(workers)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        outs.append(json.loads((dst / "manifest.json").read_text()))
    a, b = outs
    assert [s["sha256"] for s in a["sequences"]] == [s["sha256"] for s in b["sequences"]]     # any --workers
    base = json.loads((src / "manifest.json").read_text())
    for s, t in zip(base["sequences"], a["sequences"]):
        assert s["sha256"]["labels"] == t["sha256"]["labels"]
        f0, g0 = read_video(src / s["video"])[0].astype(float), read_video(tmp_path / "a" / t["video"])[0].astype(float)
        assert np.abs(g0 - f0).mean() > 5.0         # frame 0 taken at the start exposure (0.05-0.6 of the settled)
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "nuisance_dataset.py"), str(src),
                        str(tmp_path / "c"), "--level", "camera", "--only", "fibres"], capture_output=True, text=True)
    assert r.returncode == 2 and "not a stage of level 'camera'" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "nuisance_effects.py"), str(src),
                        str(tmp_path / "a"), "--json", str(tmp_path / "e.json")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    eff = json.loads((tmp_path / "e.json").read_text())
    assert eff["a"]["labels_identical"] and eff["none"]["precontact_mean_abs_diff_dn"] == 0.0
