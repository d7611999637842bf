"""The two test scenes, identical for every simulator (numpy only: imported inside each peer's venv).

A scene is the *gap* between the undeformed flat gel and the object, ``gap_mm``
float32 ``(H, W)``: how far the object's surface lies beyond the gel surface
before it is pressed, with 0 at the object's lowest point, together with a
press depth ``press_mm``. Each simulator gets it in its own convention:

* gelsim ``Renderer.render``  the imprint ``max(press - gap, 0)`` mm (>= 0, pushed into the gel);
* taxim ``Taxim.render``      ``gap - press`` mm (<= 0 where the object touches the gel);
* tacto ``render_from_depth`` the imprint in metres, towards the camera;
  tacto's mesh path gets the same surface as a mesh pressed ``press`` into its gel.

The field of view is the GelSight R1.5's (taxim's calibration: 0.0295 mm/px at
640x480, 18.88 x 14.16 mm) at every resolution, so a scene is the same
physical object at 640x480 and 960x720.
"""
from __future__ import annotations

import hashlib

import numpy as np

# taxim's calib/gelsight/params.json: 0.0295 mm/px at 640 px wide
FIELD_W_MM = 640 * 0.0295
FIELD_H_MM = 480 * 0.0295

# a 4 mm ball (diameter, the size of taxim's calibration ball) pressed 0.5 mm: the task's sphere press
SPHERE_RADIUS_MM = 2.0
SPHERE_PRESS_MM = 0.5

# plain weave: 0.5 mm yarn pitch (canvas, 15-25 threads/cm), 0.12 mm relief (a fraction of the yarn
# diameter, REFERENCES 0.02-0.3 mm), pressed 0.09 mm so yarn tops touch and the valleys do not
WEAVE_PITCH_MM = 0.5
WEAVE_RELIEF_MM = 0.12
WEAVE_PRESS_MM = 0.09
# slow pitch wander so the weave is not a perfect lattice (hand-woven look), as a fraction of the pitch
WEAVE_WANDER = 0.08

SCENES = ("sphere", "fabric")


def grid_mm(h: int, w: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Pixel-centre coordinates ``(x, y)`` in mm from the image centre (float64 ``(H, W)``) and mm per px."""
    mm_per_px = FIELD_W_MM / w
    x = (np.arange(w) - (w - 1) / 2.0) * mm_per_px
    y = (np.arange(h) - (h - 1) / 2.0) * mm_per_px
    xx, yy = np.meshgrid(x, y)
    return xx, yy, mm_per_px


def sphere_gap(h: int, w: int) -> np.ndarray:
    """Gap under a ball of radius :data:`SPHERE_RADIUS_MM` centred in the image, mm ``(H, W)``.

    Beyond the ball's footprint the gap is the radius (the ball's equator: never touches)."""
    xx, yy, _ = grid_mm(h, w)
    r2 = xx * xx + yy * yy
    R = SPHERE_RADIUS_MM
    gap = np.full((h, w), R)
    inside = r2 < R * R
    gap[inside] = R - np.sqrt(R * R - r2[inside])
    return gap.astype(np.float32)


def fabric_gap(h: int, w: int) -> np.ndarray:
    """Gap under a plain-weave fabric filling the field, mm ``(H, W)``, 0 at the highest yarn crossings.

    Warp yarns run along x, weft along y; at each crossing the yarn on top alternates (plain weave):
    each yarn's height is its cross-section (cosine bump) times an over-under undulation."""
    xx, yy, _ = grid_mm(h, w)
    p = WEAVE_PITCH_MM
    # wander: a slow sinusoidal warp of the coordinates (periods of 7 and 9 yarns)
    u = xx / p + WEAVE_WANDER * np.sin(2 * np.pi * yy / (7 * p))
    v = yy / p + WEAVE_WANDER * np.sin(2 * np.pi * xx / (9 * p))
    j = np.round(v)  # warp yarn index
    i = np.round(u)  # weft yarn index
    warp_cross = np.cos(np.pi * (v - j))          # 1 on the yarn axis, 0 between yarns
    weft_cross = np.cos(np.pi * (u - i))
    warp = warp_cross * (0.5 + 0.5 * np.cos(np.pi * (u + j)))
    weft = weft_cross * (0.5 + 0.5 * np.cos(np.pi * (v + i + 1)))
    top = np.maximum(warp, weft)
    gap = WEAVE_RELIEF_MM * (1.0 - top / top.max())
    return gap.astype(np.float32)


def scene(name: str, h: int, w: int) -> tuple[np.ndarray, float]:
    """``(gap_mm, press_mm)`` of scene ``name`` (``sphere`` or ``fabric``) at ``h`` x ``w`` px."""
    if name == "sphere":
        return sphere_gap(h, w), SPHERE_PRESS_MM
    if name == "fabric":
        return fabric_gap(h, w), WEAVE_PRESS_MM
    raise ValueError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")


def imprint_mm(gap: np.ndarray, press_mm: float) -> np.ndarray:
    """Depth the gel is pushed in by the rigid object, mm, >= 0 (no gel elasticity)."""
    return np.maximum(np.float32(press_mm) - gap, np.float32(0.0)).astype(np.float32)


def digest(a: np.ndarray) -> str:
    """Short hash of an array's bytes, to show that every simulator got the same scene."""
    return hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()[:12]
