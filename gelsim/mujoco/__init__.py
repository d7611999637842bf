"""GelSight sensors inside any MuJoCo scene (issue #14).

* :class:`GelSightSensor`: name a box or cylinder geom of your model as the gel pad; each
  ``render()`` returns a :class:`TactileFrame` (image, markers, forces, contact, shear, twist);
* :func:`attach`: add sensor pads to the fingers of a gripper in your ``mujoco.MjSpec``;
* :mod:`gelsim.mujoco.grasp`: the parallel-gripper scene of ``examples/grasp.py`` and
  :class:`gelsim.envs.GraspEnv`.

Conventions (pad frame, units, which way the gel faces): ``docs/mujoco.md``.
"""
from .attach import attach, pad_size_m
from .sensor import SUPPORTED_PAD_TYPES, GelSightSensor, TactileFrame

__all__ = ["GelSightSensor", "TactileFrame", "attach", "pad_size_m", "SUPPORTED_PAD_TYPES"]
