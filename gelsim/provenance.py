"""What a result depends on besides its arguments: the code and assets that made it.

:func:`source_digest` names that state in one hash. The bench keys its cached reference runs by it, and a
dataset records it in its manifest (``source``) so that a run resumed under other code, which would give
other sequences from the same seed, is refused instead of mixed.
"""
from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import cv2
import numpy as np


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """SHA-256 (hex) of every gelsim module but those that only present results (gelsim/bench/,
    gelsim/cli/), every asset, and the numeric libraries' versions. About 20 ms, once per process."""
    import mujoco

    from .params import ASSETS_DIR

    h = hashlib.sha256()
    pkg = Path(__file__).resolve().parent
    root = pkg.parent
    files = [f for f in sorted(pkg.rglob("*.py")) if not {"bench", "cli"} & set(f.relative_to(pkg).parts)]
    files += sorted(f for f in Path(ASSETS_DIR).rglob("*") if f.is_file())
    for f in files:
        h.update(str(f.relative_to(root) if root in f.parents else f.name).encode())
        h.update(f.read_bytes())
    h.update(f"numpy {np.__version__} cv2 {cv2.__version__} mujoco {mujoco.__version__}".encode())
    return h.hexdigest()
