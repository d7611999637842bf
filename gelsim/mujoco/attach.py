"""Put gel pads on a user's model: :func:`attach` edits a ``mujoco.MjSpec`` before it is compiled.

Each call adds, under one finger body, a body ``<name>_body`` whose origin is the gel's surface
centre and whose +z is the gel's normal (pointing away from the finger, towards what it grasps),
holding a box geom ``<name>`` of the sensor's field of view (``profile.field_mm``) and
:data:`gelsim.contact.PAD_BOX_MM` thick, its +z face on the body's origin. That geom is what
:class:`gelsim.mujoco.GelSightSensor` takes as ``pad=<name>``. For a two-finger gripper call it
once per finger, with the two facings opposite (``docs/mujoco.md`` has the equivalent MJCF).
"""
from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from ..contact import PAD_BOX_MM
from ..errors import GelsimError
from ..scene import DEFAULT_FRICTION
from ..sensor import SensorProfile, load_profile
from .rays import MM

# A translucent grey, like the silicone of a GelSight pad (display only).
PAD_RGBA = (0.75, 0.75, 0.8, 0.9)
# MuJoCo's default torsional and rolling friction for the pad's geom (mujoco's geom defaults).
_SPIN_ROLL = (0.005, 0.0001)


def pad_size_m(profile: str | Path | SensorProfile) -> tuple[float, float, float]:
    """Half-sizes (x, y, z) of the pad box for ``profile``, m: its field of view and PAD_BOX_MM thick."""
    prof = profile if isinstance(profile, SensorProfile) else load_profile(profile)
    fw, fh = prof.field_mm
    return fw / 2 * MM, fh / 2 * MM, PAD_BOX_MM / 2 * MM


def _unit(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    n = float(np.linalg.norm(a)) if a.size == 3 and np.all(np.isfinite(a)) else 0.0
    if n == 0.0:
        raise GelsimError(f"{what} {v!r} is not a direction; give three numbers, not all zero")
    return a / n


def attach(spec: mujoco.MjSpec, finger: str, name: str, *, facing=(0.0, 0.0, 1.0), x_axis=None,
           pos_m=(0.0, 0.0, 0.0), profile: str | Path | SensorProfile = "gelsight-mini",
           friction: float = DEFAULT_FRICTION, condim: int = 4) -> mujoco.MjsGeom:
    """Add a gel pad named ``name`` to body ``finger`` of ``spec`` and return its geom.

    ``facing``: the gel's normal in the finger's frame (towards the grasped object); ``x_axis``: the
    image's column direction in the finger's frame (default: any direction normal to ``facing``,
    MuJoCo's ``zaxis`` convention); ``pos_m``: the gel surface's centre in the finger's frame, m;
    ``profile``: sets the pad's size (its field of view); ``friction``: Coulomb's coefficient of
    the gel (default: silicone, gelsim.scene.DEFAULT_FRICTION); ``condim``: MuJoCo's contact
    dimensionality for the pad (4: with torsional friction, which keeps a pinched object from
    spinning about the grasp axis).
    """
    body = spec.body(finger) if isinstance(finger, str) else None
    if body is None:
        names = [b.name for b in spec.bodies if b.name]
        raise GelsimError(f"no body named {finger!r} in the spec; attach the pad to one of: "
                          + (", ".join(names[:12]) or "(no named bodies)"))
    if spec.geom(name) is not None or spec.body(f"{name}_body") is not None:
        raise GelsimError(f"the spec already has a geom {name!r} or a body {name + '_body'!r}; give the pad another name")
    if not (isinstance(friction, (int, float)) and 0 < friction <= 5):
        raise GelsimError(f"friction {friction!r} is out of range; give Coulomb's coefficient in (0, 5]")
    z = _unit(facing, "facing")
    if x_axis is None:
        frame = dict(zaxis=z.tolist())
    else:
        x = _unit(x_axis, "x_axis")
        x = x - (x @ z) * z
        if np.linalg.norm(x) < 1e-9:
            raise GelsimError(f"x_axis {x_axis!r} is parallel to facing {facing!r}; give a direction across the gel")
        x /= np.linalg.norm(x)
        frame = dict(xyaxes=[*x.tolist(), *np.cross(z, x).tolist()])
    hx, hy, hz = pad_size_m(profile)
    pad_body = body.add_body(name=f"{name}_body", pos=list(map(float, pos_m)), **frame)
    return pad_body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz], pos=[0.0, 0.0, -hz],
                             rgba=list(PAD_RGBA), friction=[float(friction), *_SPIN_ROLL], condim=int(condim))
