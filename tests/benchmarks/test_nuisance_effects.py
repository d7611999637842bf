"""benchmarks/nuisance_effects.py on two tiny datasets (none, handheld): labels kept, the frames before
contact changed by more than the detector's bar, onset agreement counted, copies made otherwise refused."""
import json
import subprocess
import sys
from pathlib import Path

from gelsim.dataset import GenerateConfig, generate

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "nuisance_effects.py"


def test_nuisance_effects_on_tiny_datasets(tmp_path):
    base = dict(fabrics=2, sequences_per_fabric=2, frames=(8, 8), precontact=(2, 2), resolution=(96, 72),
                fidelity="fast")
    generate(GenerateConfig(**base), tmp_path / "none", workers=1, previews=False)
    generate(GenerateConfig(**base, nuisance="handheld"), tmp_path / "handheld", workers=1, previews=False)
    generate(GenerateConfig(**base, nuisance="webcam-restart"), tmp_path / "webcam-restart", workers=1, previews=False)
    r = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "none"), str(tmp_path / "handheld"),
                        str(tmp_path / "webcam-restart"),
                        "--json", str(tmp_path / "e.json"), "--figure", str(tmp_path / "f.png")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    eff = json.loads((tmp_path / "e.json").read_text())
    none, hand, restart = eff["none"], eff["handheld"], eff["webcam-restart"]
    assert none["precontact_mean_abs_diff_dn"] == 0.0 and none["sequences"] == 4
    assert hand["level"] == "handheld" and hand["labels_identical"] and restart["labels_identical"]
    assert restart["precontact_mean_abs_diff_dn"] > 5.0               # the start exposure: 0.05-0.6 of settled
    assert restart["precontact_frames"] == 8 and restart["precontact_frames_over_bar"] >= 4
    assert restart["black_frames"] == 0 and restart["frames"] == 32
    assert hand["precontact_frame_diff_dn"]["frames"] == 8
    assert none["early_contact_frame_diff_dn"]["frames"] == 0          # contact from frame 2 here
    assert 0 <= hand["onset_within_1"] <= hand["sequences"] == 4 == sum(hand["onset_errors"].values())
    assert (tmp_path / "f.png").stat().st_size > 1000
    generate(GenerateConfig(**{**base, "frames": (9, 9)}), tmp_path / "other", workers=1, previews=False)
    r = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "none"), str(tmp_path / "other")],
                       capture_output=True, text=True)
    assert r.returncode != 0 and "other options" in r.stderr and "Traceback" not in r.stderr
