"""Gymnasium environments with GelSight tactile observations (optional: ``make gym`` installs gymnasium).

Importing this package registers every environment of :data:`ENVS` with Gymnasium, so that::

    import gymnasium as gym
    import gelsim.envs  # noqa: F401  (registers the gelsim/ ids)

    env = gym.make("gelsim/Grasp-v0", render_mode="rgb_array")
    envs = gym.make_vec("gelsim/Grasp-v0", num_envs=4)

``gym.make("gelsim.envs:gelsim/Grasp-v0")`` imports it on the way, in a fresh interpreter too: Gymnasium 1.x
reads no entry points (its plugin group was removed in 1.0), so a module-qualified id or this import is
what registers a third-party package's ids. Importing it without gymnasium raises a GelsimError naming the
install command.
"""
from __future__ import annotations

try:
    import gymnasium
except ImportError:  # the optional extra is missing
    from ..errors import GelsimError

    raise GelsimError("gelsim.envs needs gymnasium, an optional extra; install it with `make gym` "
                      "in the clone, or `pip install gymnasium==1.4.0`") from None

from .grasp import GraspEnv  # noqa: E402

#: Every registered environment: id -> keyword arguments of ``gymnasium.register`` (``entry_point`` as
#: "module:attr"; add ``vector_entry_point`` for an environment that steps a batch itself, which
#: ``gym.make_vec`` then uses). Register a new environment by adding a row here.
ENVS: dict[str, dict] = {
    "gelsim/Grasp-v0": {"entry_point": "gelsim.envs.grasp:GraspEnv"},
    # the same task, its sensors batched on a torch device (gelsim.mujoco.batch): gym.make_vec steps all
    # environments' pads in one render per step; gym.make gives the single GraspEnv with the same profile
    "gelsim/GraspBatched-v0": {"entry_point": "gelsim.envs.grasp:GraspEnv", "kwargs": {"profile": "vitac"},
                               "vector_entry_point": "gelsim.envs.vector:GraspVectorEnv"},
}


def register_envs() -> list[str]:
    """Register each of :data:`ENVS` with Gymnasium that is not registered yet; returns the ids."""
    for env_id, kwargs in ENVS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, **kwargs)
    return list(ENVS)


register_envs()

__all__ = ["ENVS", "GraspEnv", "register_envs"]
