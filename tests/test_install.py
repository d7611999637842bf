"""The package as a user installs it: a wheel built from this tree, installed (not editable) into a fresh
virtualenv outside the clone, runs ``gelsim --version``, ``gelsim generate --preset quick`` and the README's
MuJoCo snippet from another directory, finding its fabrics, sensors and fidelity levels inside the package.

Marked ``install`` (about 1-2 min: pip installs the dependencies into the new environment, from its cache
when it has them); ``make test`` runs it as its own step after the default suite.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import gelsim

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.install


def readme_mujoco_snippet() -> str:
    """The README's quick start for a GelSight in your own MuJoCo scene: its python block that makes a
    GelSightSensor."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    found = [b for b in blocks if "GelSightSensor(" in b and "import mujoco" in b]
    assert len(found) == 1, "the README should have one python block with the MuJoCo quick start"
    return found[0]


def _clean_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    return env | {"PYTHONNOUSERSITE": "1"}


def _run(cmd, cwd, timeout=600) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_clean_env(), capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
    return r


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    """A wheel built from a copy of the tree, pip-installed into a new virtualenv; returns its paths."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for pkg in ("gelsim", "stam"):
        shutil.copytree(ROOT / pkg, src / pkg, ignore=ignore)
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", dist, src], tmp)
    wheels = sorted(dist.glob("gelsim-*.whl"))
    assert len(wheels) == 1, wheels
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", venv], tmp)
    py = venv / "bin" / "python"
    _run([py, "-m", "pip", "install", "-q", wheels[0]], tmp, timeout=900)
    work = tmp / "work"                     # a directory with no gelsim source in it
    work.mkdir()
    return {"wheel": wheels[0], "venv": venv, "py": py, "bin": venv / "bin", "work": work}


def test_wheel_carries_the_data_files(installed):
    import zipfile

    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    for f in ("gelsim/assets/fidelity.toml", "gelsim/assets/fabrics/woven.toml", "gelsim/assets/sensors/vitac.toml",
              "gelsim/assets/sensors/gelsight-mini-shading.npz", "stam/configs/cpu.toml"):
        assert f in names, f
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(installed["wheel"]).read(meta).decode()
    assert f"Version: {gelsim.__version__}" in text and "License-Expression: MIT" in text
    assert "Provides-Extra: gym" in text and "Classifier: Programming Language :: Python :: 3.11" in text


def test_installed_package_is_the_wheels_not_the_clones(installed):
    # (stam's configs through gelsim.params.package_dir, as stam.config finds them: stam itself needs torch,
    # the `stam` extra, which this environment leaves out)
    r = _run([installed["py"], "-c", "import gelsim; from gelsim.params import ASSETS_DIR, package_dir; "
              "print(gelsim.__file__); print(ASSETS_DIR); print(package_dir('stam', 'configs') / 'cpu.toml')"],
             installed["work"])
    for line in r.stdout.split():
        assert Path(line).is_relative_to(installed["venv"]) and not Path(line).is_relative_to(ROOT), line
    out = _run([installed["bin"] / "gelsim", "--version"], installed["work"]).stdout.strip()
    assert out == f"gelsim {gelsim.__version__}"


def test_installed_wheel_generates_the_quick_dataset(installed):
    work = installed["work"]
    _run([installed["bin"] / "gelsim", "generate", "--preset", "quick", "--workers", "2", "--out", "demo"], work)
    manifest = json.loads((work / "demo" / "manifest.json").read_text())
    assert manifest["complete"] is True and len(manifest["sequences"]) == 40
    assert manifest["splits"] == {"train": 20, "val": 10, "test": 10}   # a test split for `stam evaluate`
    assert (work / "demo" / "previews").is_dir()
    _run([installed["bin"] / "gelsim", "verify", "demo"], work)


def test_installed_wheel_runs_the_readmes_mujoco_snippet(installed):
    work = installed["work"]
    (work / "snippet.py").write_text(readme_mujoco_snippet())
    r = _run([installed["py"], "snippet.py"], work)
    force, touched, *_ = r.stdout.split()
    assert float(force) > 0 and int(touched) > 0, r.stdout
