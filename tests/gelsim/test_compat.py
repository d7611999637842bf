"""Tests of gelsim.compat: the pyrender 0.1.45 shims."""
from __future__ import annotations

import importlib.metadata
import subprocess
import sys

import numpy as np
import pytest

from gelsim import compat
from gelsim.errors import GelsimError


def test_gl_color_keeps_unit_floats_and_converts_ints():
    c = compat.gl_color([1, 0, 0])
    assert c.dtype == np.float32 and c.tolist() == [1.0, 0.0, 0.0]
    c4 = compat.gl_color((0.5, 0.25, 1.0), alpha=1.0)
    assert c4.shape == (4,) and c4.dtype == np.float32
    np.testing.assert_allclose(c4, [0.5, 0.25, 1.0, 1.0])


@pytest.mark.parametrize("bad", [[255, 0, 0], [0.5, -0.1, 0.0], [0.1, 0.2], [np.nan, 0, 0]])
def test_gl_color_refuses_out_of_range(bad):
    with pytest.raises(GelsimError):
        compat.gl_color(bad)


def test_numpy_alias_restored():
    compat.ensure_numpy_aliases()
    assert np.infty == np.inf


def test_pyopengl_version_checked(monkeypatch):
    installed = importlib.metadata.version("PyOpenGL")
    assert compat.check_pyopengl() == installed
    assert compat._version_tuple(installed) >= compat.MIN_PYOPENGL
    monkeypatch.setattr(importlib.metadata, "version", lambda name: "3.1.0")
    with pytest.raises(GelsimError, match="3.1.10"):
        compat.check_pyopengl()
    assert compat._version_tuple("3.1.10") > compat._version_tuple("3.1.9") > compat._version_tuple("3.1.0")
    assert compat._version_tuple("3.1.7rc1") == (3, 1, 7)


def test_platform_choice(monkeypatch):
    monkeypatch.setenv("PYOPENGL_PLATFORM", "osmesa")
    assert compat.choose_platform() == "osmesa"
    monkeypatch.delenv("PYOPENGL_PLATFORM")
    monkeypatch.setattr(compat, "_has_lib", lambda name: False)
    assert compat.choose_platform() is None
    monkeypatch.setattr(compat, "_has_lib", lambda name: name == "EGL")
    assert compat.choose_platform() == "egl"
    monkeypatch.setattr(compat, "_has_lib", lambda name: True)
    monkeypatch.setattr(compat.glob, "glob", lambda pattern: [])
    assert compat.choose_platform() == "osmesa"          # no GPU: software OSMesa is faster
    monkeypatch.setattr(compat.glob, "glob", lambda pattern: ["/dev/dri/renderD128"])
    assert compat.choose_platform() == "egl"


def test_error_message_names_packages():
    msg = compat.gl_unavailable_message("x")
    assert compat.GL_PACKAGES in msg and "\n" not in msg


def _run(code: str, env_platform: str | None = None) -> subprocess.CompletedProcess:
    import os
    env = dict(os.environ)
    env.pop("PYOPENGL_PLATFORM", None)
    if env_platform:
        env["PYOPENGL_PLATFORM"] = env_platform
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_no_gl_libraries_is_one_clear_error():
    """In a fresh process where no GL library can be found, importing pyrender is a GelsimError naming the packages."""
    code = ("from gelsim import compat\n"
            "compat._has_lib = lambda name: False\n"
            "try:\n    compat.import_pyrender()\nexcept compat.GelsimError as e:\n    print('ERR', e)\n")
    out = _run(code)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ERR") and "libosmesa6" in out.stdout


@pytest.mark.gl
def test_import_pyrender_applies_shims_and_colours_stay_bright():
    """pyrender imports under numpy 2 and reads our colours as given (raw ints would turn 1 into 1/255)."""
    code = ("import numpy as np\n"
            "from gelsim import compat\n"
            "pr = compat.import_pyrender()\n"
            "import os\n"
            "from pyrender.utils import format_color_vector\n"
            "print(os.environ['PYOPENGL_PLATFORM'])\n"
            "print(format_color_vector(np.array([1, 0, 0]), 3)[0], format_color_vector(compat.gl_color([1, 0, 0]), 3)[0])\n"
            "r = pr.OffscreenRenderer(16, 16); r.delete(); print('ctx ok')\n")
    out = _run(code)
    if "ctx ok" not in out.stdout:
        pytest.skip(f"no headless GL context here: {out.stderr.strip().splitlines()[-1:]}")
    lines = out.stdout.split()
    assert lines[0] in compat.PLATFORMS
    assert float(lines[1]) == pytest.approx(1 / 255) and float(lines[2]) == 1.0


def test_broken_gl_platform_gives_fast_only_and_one_line_error():
    """With an unusable GL platform, pyrender is not offered (fast is, and torch where PyTorch is installed)
    and fails with one clear line."""
    code = ("from gelsim.optics import Renderer, available_backends\n"
            "from gelsim.sensor import load_profile\n"
            "from gelsim.errors import GelsimError\n"
            "print(available_backends())\n"
            "try:\n    Renderer(load_profile('vitac').with_resolution(64), 'pyrender')\n"
            "except GelsimError as e:\n    print('ERR', e)\n")
    out = _run(code, env_platform="bogus")
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    import ast
    import importlib.util

    assert ast.literal_eval(lines[0]) == ["fast"] + (["torch"] if importlib.util.find_spec("torch") else [])
    assert lines[1].startswith("ERR no headless OpenGL") and "libegl1" in lines[1] and len(lines) == 2
