"""Compatibility shims for pyrender 0.1.45 on this stack (numpy 2, PyOpenGL 3.1.10, Mesa).

pyrender 0.1.45 is the last release and no longer matches its dependencies.
Everything gelsim needs to work around lives here, so that the rest of the code
imports pyrender only through :func:`import_pyrender`:

1. **PyOpenGL pin.** pyrender declares ``PyOpenGL==3.1.0``. That release cannot
   create an EGL or OSMesa context on current Mesa (its EGL/OSMesa bindings
   predate the entry points Mesa now exports), so the Makefile installs
   ``PyOpenGL==3.1.10`` with ``--no-deps``; the API pyrender uses is unchanged.
   :func:`check_pyopengl` reports the installed version and raises if it is
   older than :data:`MIN_PYOPENGL` (pip may have "fixed" the pin back to 3.1.0).
2. **``np.infty``** was removed in numpy 2.0; pyrender's ``mesh.py`` still uses
   it when computing bounds. :func:`ensure_numpy_aliases` restores the alias
   before pyrender is imported.
3. **Integer colours.** pyrender's ``format_color_vector`` divides integer
   colours by 255, so a light colour written ``[1, 0, 0]`` (ints, meaning full
   red in 0-1 units) silently becomes ``[1/255, 0, 0]``: nearly black. Always
   pass float colours in 0-1 through :func:`gl_color`.
4. **Platform.** pyrender picks its headless GL from ``PYOPENGL_PLATFORM``,
   which must be set before ``OpenGL`` is first imported and cannot change
   afterwards in the same process. :func:`choose_platform` picks ``egl`` or
   ``osmesa`` from what is installed; :func:`import_pyrender` sets it.
"""
from __future__ import annotations

import ctypes.util
import glob
import importlib.metadata
import os
import sys

import numpy as np

from .errors import GelsimError

#: Debian packages that provide headless GL for pyrender.
GL_PACKAGES = "libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libosmesa6"
#: Oldest PyOpenGL known to create EGL/OSMesa contexts on current Mesa here (3.1.0 fails).
MIN_PYOPENGL = (3, 1, 4)
PLATFORMS = ("egl", "osmesa")


def _version_tuple(text: str) -> tuple[int, ...]:
    """Leading numeric release parts: "3.1.7rc1" -> (3, 1, 7)."""
    import re
    parts = []
    for p in text.split("."):
        m = re.match(r"\d+", p)
        if not m:
            break
        parts.append(int(m.group()))
        if m.end() < len(p):      # a pre/post-release suffix ends the release number
            break
    return tuple(parts)


def check_pyopengl() -> str:
    """Installed PyOpenGL version; GelsimError if missing or older than :data:`MIN_PYOPENGL`."""
    try:
        version = importlib.metadata.version("PyOpenGL")
    except importlib.metadata.PackageNotFoundError:
        raise GelsimError("PyOpenGL is not installed; run: .venv/bin/pip install --no-deps "
                          "PyOpenGL==3.1.10") from None
    if _version_tuple(version) < MIN_PYOPENGL:
        raise GelsimError(f"PyOpenGL {version} is installed (pyrender 0.1.45 pins 3.1.0, which cannot make "
                          "a headless context on current Mesa); run: .venv/bin/pip install --no-deps "
                          "PyOpenGL==3.1.10")
    return version


def ensure_numpy_aliases() -> None:
    """Restore ``np.infty`` (removed in numpy 2.0, still used by pyrender 0.1.45)."""
    if not hasattr(np, "infty"):
        np.infty = np.inf


def gl_color(rgb, alpha: float | None = None) -> np.ndarray:
    """A colour for pyrender: float32 ``(3,)`` (or ``(4,)`` with ``alpha``), each in 0-1.

    pyrender treats integer colours as 0-255 and divides them by 255, so
    ``[1, 0, 0]`` would become almost black; converting to float here keeps the
    meaning "0-1 linear" whatever the caller's number types. Values outside
    0-1 (someone passing 0-255) are a GelsimError rather than a silent clamp.
    """
    c = np.asarray(rgb, dtype=np.float64).reshape(-1)
    if c.shape[0] != 3:
        raise GelsimError(f"a colour needs 3 components (r, g, b), got {c.shape[0]}; give [r, g, b] in 0-1")
    if not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
        raise GelsimError(f"colour {c.tolist()} is outside 0-1; give linear RGB in 0-1 (divide 0-255 values by 255)")
    if alpha is not None:
        c = np.append(c, float(alpha))
    return c.astype(np.float32)


def _has_lib(name: str) -> bool:
    return ctypes.util.find_library(name) is not None


def choose_platform() -> str | None:
    """The headless GL platform to use: ``"egl"``, ``"osmesa"`` or None if neither is installed.

    ``PYOPENGL_PLATFORM`` wins when the user set it. Otherwise EGL when a GPU
    render node exists (hardware EGL is much faster), else OSMesa when its
    library is present (on a CPU-only machine Mesa's OSMesa rendered our
    960x720 gel in 178 ms against 372 ms for EGL, which multisamples), else EGL
    (Mesa's surfaceless software EGL).
    """
    env = os.environ.get("PYOPENGL_PLATFORM")
    if env:
        return env
    has_egl, has_osmesa = _has_lib("EGL"), _has_lib("OSMesa")
    if has_egl and glob.glob("/dev/dri/renderD*"):
        return "egl"
    if has_osmesa:
        return "osmesa"
    if has_egl:
        return "egl"
    return None


def gl_unavailable_message(detail: str = "") -> str:
    """One-line error text for a missing headless GL, naming the packages to install."""
    why = f" ({detail})" if detail else ""
    return (f"no headless OpenGL context could be made for the pyrender backend{why}; "
            f"install: sudo apt-get install -y {GL_PACKAGES} (or set PYOPENGL_PLATFORM=egl|osmesa), "
            "or use --backend fast")


def import_pyrender():
    """Import and return pyrender with every shim above applied; GelsimError if it cannot work."""
    if "pyrender" in sys.modules:
        return sys.modules["pyrender"]
    check_pyopengl()
    if "OpenGL" not in sys.modules:
        platform = choose_platform()
        if platform is None:
            raise GelsimError(gl_unavailable_message("neither libEGL nor libOSMesa was found"))
        os.environ["PYOPENGL_PLATFORM"] = platform
    ensure_numpy_aliases()
    try:
        import pyrender  # noqa: PLC0415 - must follow the environment set-up above
    except Exception as e:  # ImportError, or OpenGL's own errors when a library is broken
        raise GelsimError(gl_unavailable_message(f"{type(e).__name__}: {e}".splitlines()[0])) from None
    return pyrender


def platform_in_use() -> str | None:
    """The platform OpenGL was (or will be) loaded with."""
    return os.environ.get("PYOPENGL_PLATFORM") or choose_platform()
