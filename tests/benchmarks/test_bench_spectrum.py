"""benchmarks/bench_spectrum.py: the gel's relief by wavelength, against the fabric's and the reference's."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_spectrum.py"


def _module():
    spec = importlib.util.spec_from_file_location("bench_spectrum", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_transfer_of_a_scaled_copy_is_its_scale_in_every_bin():
    rng = np.random.default_rng(0)
    fabric = rng.standard_normal((180, 240))
    mod = _module()
    rows = mod.transfer_by_bin(0.5 * fabric, 0.25 * fabric, fabric, 0.04)
    assert len(rows) == len(mod.EDGES_MM) - 1
    for r in rows:
        assert r["model_transfer"] == pytest.approx(0.5)
        assert r["reference_transfer"] == pytest.approx(0.25)
        assert r["model_over_reference"] == pytest.approx(2.0)


def test_elastic_contact_passes_a_felts_long_waves_more_than_its_short_ones():
    """Wool felt at 1 N, 320x240: the reference's gel keeps more of the 1-2 mm relief than of the 0.12-0.18 mm
    relief (elastic contact completes sooner for long waves; measured 0.22 against 0.05)."""
    proc = subprocess.run([sys.executable, str(SCRIPT), "--resolution", "320", "--json"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["fabric"] == 78 and doc["resolution"] == [320, 240] and doc["support"] == "cloth"
    by_bin = {tuple(r["wavelength_mm"]): r for r in doc["bins"]}
    long_, short = by_bin[(1.0, 2.0)], by_bin[(0.12, 0.18)]
    assert long_["reference_transfer"] > 2.0 * short["reference_transfer"] > 0
    assert all(0.0 < r["model_transfer"] < 1.5 for r in doc["bins"])
