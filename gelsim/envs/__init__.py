"""Gymnasium environments with GelSight tactile observations (optional: ``make gym`` installs gymnasium).

:class:`GraspEnv` is importable only when gymnasium is installed; importing this package without it
raises a GelsimError naming the install command.
"""
from __future__ import annotations

try:
    import gymnasium  # noqa: F401
except ImportError:  # the optional extra is missing
    from ..errors import GelsimError

    raise GelsimError("gelsim.envs needs gymnasium, an optional extra; install it with `make gym` "
                      "(or .venv/bin/pip install -e '.[gym]')") from None

from .grasp import GraspEnv  # noqa: E402

__all__ = ["GraspEnv"]
