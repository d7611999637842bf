"""Tests of the `gelsim fabrics` command line."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from gelsim.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _run(*args: str) -> subprocess.CompletedProcess:
    """The real entry point in a subprocess, so that exit codes and stderr are what a user sees."""
    return subprocess.run([sys.executable, "-m", "gelsim", "fabrics", *args], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)


def test_list_json(capsys):
    assert main(["fabrics", "list", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["count"] == 100 and len(doc["fabrics"]) == 100
    assert len(doc["version"]) == 12
    first = doc["fabrics"][0]
    for k in ("id", "name", "family", "material", "friction", "thickness_mm", "compressibility", "surface_modulus_mpa",
              "relief_mm", "warp_pitch_mm"):
        assert k in first
    assert [f["id"] for f in doc["fabrics"]] == list(range(1, 101))
    assert all(isinstance(f["name"], str) and f["family"] for f in doc["fabrics"])


def test_list_table(capsys):
    assert main(["fabrics", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:3] == ["id", "name", "family"]
    assert len(out) == 102 and "100 fabrics" in out[-1]


def test_show_writes_png(tmp_path, capsys):
    out = tmp_path / "f.png"
    assert main(["fabrics", "show", "21", "--out", str(out), "--size-mm", "4", "--mm-per-px", "0.02"]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] == 200 and img.shape[0] > 200
    assert img[-150:].std() > 10                      # shaded relief, not a blank image
    assert not list(tmp_path.glob(".*tmp"))           # no temporary file left behind
    assert "raw denim" in capsys.readouterr().out


def test_sheet_writes_png(tmp_path):
    out = tmp_path / "sheet.png"
    assert main(["fabrics", "sheet", "--out", str(out), "--tile-mm", "1", "--mm-per-px", "0.05",
                 "--columns", "20"]) == 0
    img = cv2.imread(str(out))
    assert img is not None
    # 5 rows of 20 tiles of 20 px plus labels and padding
    assert img.shape[1] == 20 * 24 + 4 and img.shape[0] == 5 * (20 + 18 + 4) + 4


@pytest.mark.parametrize("args, pattern", [
    (["show", "101", "--out", "{tmp}/x.png"], "unknown fabric id 101; ids run 1-100"),
    (["show", "5", "--out", "{tmp}/x.png", "--size-mm", "0"], "--size-mm 0.0 must be positive"),
    (["show", "5", "--out", "{tmp}/x.png", "--size-mm", "-3"], "--size-mm -3.0 must be positive"),
    (["show", "5", "--out", "{tmp}/x.png", "--mm-per-px", "0"], "--mm-per-px 0.0 must be positive"),
    (["show", "5", "--out", "{tmp}/missing/dir/x.png", "--size-mm", "1", "--mm-per-px", "0.05"], "does not exist"),
    (["show", "5", "--out", "{tmp}/x.jpg"], "must be a .png file"),
    (["sheet", "--out", "{tmp}/s.png", "--mm-per-px", "-1"], "must be positive"),
    (["list", "--catalog", "{tmp}/nowhere"], "not found"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, args, pattern):
    r = _run(*[a.format(tmp=tmp_path) for a in args])
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gelsim: error: ")
    assert pattern in lines[0]
    assert "Traceback" not in r.stderr


def test_unwritable_output_exits_2(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    # Root writes through permission bits; /proc refuses new files even to root.
    target = ro / "x.png" if not os.access(ro, os.W_OK) else "/proc/gelsim-test.png"
    try:
        assert main(["fabrics", "show", "3", "--out", str(target), "--size-mm", "1", "--mm-per-px", "0.05"]) == 2
    finally:
        ro.chmod(0o700)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ("gelsim-test.png" in err[0] or "x.png" in err[0])
    assert "choose a writable --out" in err[0]


def test_every_option_help_gives_unit_or_default():
    for sub in ("list", "show", "sheet"):
        r = _run(sub, "--help")
        assert r.returncode == 0
        text = " ".join(r.stdout.split())
        for opt in ("--size-mm", "--mm-per-px", "--seed", "--tile-mm", "--columns"):
            if opt in text:
                # each numeric option's help ends with its default, and names its unit
                seg = text.split(opt, 2)[-1][:200]
                assert "(default:" in seg, (sub, opt, seg)
    r = _run("show", "--help")
    assert "mm per pixel" in r.stdout and "side of the square patch shown, mm" in " ".join(r.stdout.split())
