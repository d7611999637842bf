"""Where a ball was pressed, from its frame alone: the *flat point* detector.

At the ball's lowest point the gel's normal is flat, and a flat normal shows the background: the
colour change ``frame - f0`` vanishes there, and around it each LED's colour rises on the side that
faces it (the point where the three colours meet). Near that point the change is linear in the
surface slope, so the detector fits ``frame - f0 = a + J (p - c)`` (per channel; ``J`` in DN per px)
to the pixels within ``FLAT_SLOPE`` of surface slope of ``c`` and moves ``c`` to where the fit
vanishes (``c -= pinv(J) a``, a Gauss-Newton step), until it stops moving. No shading table and no
other frame enter: the centre depends on the frame, the pack's ``f0``, the ball's size and the
pixel size only.

It needs a sensor whose colour turns steeply at flat and a flat point that looks like the background.
On taxim's GelSight Mini pack both hold: the detected centres agree with the centres registered
against a table of the other presses (:func:`gelsim.calibrate.register_presses`) to 0.37 px RMS, after
a common shift of (6.7, -2.2) px that the registration cannot see (it fixes the presses relative to
each other). On the GelSight R1.5 they do not: its response near flat is a sixth of the Mini's
(about 1.3 DN per px) and its flat tops change colour with their place in the field by up to
+-17 DN, so the point where the change vanishes wanders by 8 px RMS from the annotated centres.
:func:`gelsim.calibrate.choose_centres` therefore uses the detector only where it agrees with the
registration on the fitted frames (docs/realism.md, "Centres").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .errors import GelsimError

# The fit's disk: the pixels within surface slope FLAT_SLOPE of the ball's lowest point, a radius of
# FLAT_SLOPE x (ball radius) / (mm per px): 6.3 px on the Mini at 640x480 (4 mm ball, 0.0317 mm/px).
# The Mini's colour change is linear in the slope up to about 0.1 (its response saturates beyond);
# on the Mini pack a 6.3 px and a 10 px disk give centres within 0.35 px RMS of each other.
FLAT_SLOPE = 0.1
FLAT_BLUR = 0.25        # the change is blurred by a Gaussian of this fraction of the disk's radius
                        # (1.6 px on the Mini) before the fit: the frame's noise, not its shape
FLAT_MIN_DISK_PX = 2.0  # a disk under 2 px holds too few pixels for three planes: refused
FLAT_REACH = 0.75       # the search stays within 0.75 contact radii of the annotated centre (the
                        # Mini's annotations are up to 0.46 radii off; as the registration's reach)
# A flat point is a press's only where the colour turns steeply around it: by at least FLAT_MIN_TURN_DN
# from the point to the disk's edge (slope FLAT_SLOPE; the smaller singular value of J times the disk's
# radius). Measured: the Mini pack's presses turn by 42-49 DN, a synthetic Mini press at 320x240 by
# 27-31 DN; the R1.5 pack's by 2-9 DN (too little to place them against its flat tops' +-17 DN across
# the field); a point found 1.5 contact radii off a synthetic press (outside it) by 2.8 DN.
FLAT_MIN_TURN_DN = 10.0
FLAT_ITERS = 30         # Gauss-Newton steps at most (the Mini's presses converge in 3-6)
FLAT_TOL_PX = 0.01      # converged when a step is below this, px


@dataclass(frozen=True)
class FlatPoint:
    """One frame's detected flat point. ``centre_px`` (x, y); ``gain_dn_per_px``: the smaller singular
    value of ``J`` (how steeply the colour turns at the point, DN per px); ``residual_dn``: RMS of the
    linear fit over the disk; ``offset_dn``: the part of the change at the point that no move can
    remove (the flat colour's distance from the background, DN); ``sigma_px``: the centre's standard
    error from the fit's residual (px); ``steps``: Gauss-Newton steps taken."""
    centre_px: tuple[float, float]
    gain_dn_per_px: float
    residual_dn: float
    offset_dn: float
    sigma_px: float
    steps: int


def disk_radius_px(mm_per_px: float, ball_diameter_mm: float) -> float:
    """The radius of the detector's fit, px (see FLAT_SLOPE)."""
    return FLAT_SLOPE * (ball_diameter_mm / 2.0) / mm_per_px


def colour_change(frame: np.ndarray, f0: np.ndarray, disk_px: float) -> np.ndarray:
    """``frame - f0`` (uint8 or float ``(H, W, 3)``), blurred (FLAT_BLUR x ``disk_px``): float32 ``(H, W, 3)``."""
    d = np.asarray(frame, np.float32) - np.asarray(f0, np.float32)
    return cv2.GaussianBlur(d, (0, 0), FLAT_BLUR * disk_px, borderType=cv2.BORDER_REPLICATE)


def flat_point(delta: np.ndarray, start_px, reach_px: float, disk_px: float) -> FlatPoint | str:
    """The flat point of one press: ``delta`` the blurred colour change (:func:`colour_change`),
    searched within ``reach_px`` of ``start_px`` (x, y). Returns a :class:`FlatPoint`, or a string that
    says why none was found (the fit left the search window, a flat colour change, a colour that turns by
    under FLAT_MIN_TURN_DN around the point, no convergence).

    The first guess is the pixel of the window where the change is smallest against its surroundings
    (``|delta|^2`` over its Gaussian average at ``disk_px``): the dark point where the colours meet."""
    h, w = delta.shape[:2]
    s = np.asarray(start_px, np.float64)
    e = (delta.astype(np.float64) ** 2).sum(axis=-1)
    around = cv2.GaussianBlur(e, (0, 0), disk_px, borderType=cv2.BORDER_REPLICATE)
    x0, x1 = max(0, int(math.floor(s[0] - reach_px))), min(w, int(math.ceil(s[0] + reach_px)) + 1)
    y0, y1 = max(0, int(math.floor(s[1] - reach_px))), min(h, int(math.ceil(s[1] + reach_px)) + 1)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    score = e[y0:y1, x0:x1] / (around[y0:y1, x0:x1] + 1.0)       # + 1 DN^2: a blank window has no dark point
    score[(xx - s[0]) ** 2 + (yy - s[1]) ** 2 > reach_px ** 2] = np.inf
    k = int(np.argmin(score))
    c = np.array([xx.flat[k], yy.flat[k]], np.float64)
    r = int(math.ceil(disk_px))
    for step_no in range(1, FLAT_ITERS + 1):
        cx, cy = int(round(c[0])), int(round(c[1]))
        py, px = np.mgrid[max(0, cy - r):min(h, cy + r + 1), max(0, cx - r):min(w, cx + r + 1)]
        inside = (px - c[0]) ** 2 + (py - c[1]) ** 2 <= disk_px ** 2
        px, py = px[inside], py[inside]
        if px.size < 6:
            return f"the disk at ({c[0]:.1f}, {c[1]:.1f}) px holds {px.size} pixels (the image's edge)"
        design = np.stack([np.ones(px.size), px - c[0], py - c[1]], axis=1)
        coef, *_ = np.linalg.lstsq(design, delta[py, px].astype(np.float64), rcond=None)
        a, jac = coef[0], coef[1:].T                             # (3,), (3 channels, 2)
        sv = np.linalg.svd(jac, compute_uv=False)
        if sv[-1] <= 1e-6 * max(sv[0], 1e-12):
            return "the colour change does not turn around any point (it is flat or one-dimensional)"
        step = -np.linalg.lstsq(jac, a, rcond=None)[0]
        c = c + step
        if (c[0] - s[0]) ** 2 + (c[1] - s[1]) ** 2 > reach_px ** 2:
            return (f"the point where the colour change vanishes lies beyond {reach_px:.1f} px of the "
                    f"annotated centre")
        if float(np.hypot(*step)) < FLAT_TOL_PX:
            turn = float(sv[-1]) * disk_px
            if turn < FLAT_MIN_TURN_DN:
                return (f"the colour turns by only {turn:.1f} DN around the point where it vanishes, at "
                        f"({c[0]:.1f}, {c[1]:.1f}) px (a press's centre turns by {FLAT_MIN_TURN_DN:g} or more)")
            resid = delta[py, px].astype(np.float64) - design @ coef
            rms = float(np.sqrt((resid ** 2).mean()))
            left = a + jac @ step                                 # the change at the final point
            return FlatPoint((float(c[0]), float(c[1])), float(sv[-1]), rms, float(np.linalg.norm(left)),
                             float(rms / (sv[-1] * math.sqrt(px.size))), step_no)
    return f"the fit did not settle in {FLAT_ITERS} steps"


def detect_centres(pack, mm_per_px: float, ball_diameter_mm: float) -> dict:
    """The flat point of every frame of ``pack`` (:class:`gelsim.realism.DataPack`), each searched
    within FLAT_REACH contact radii of its annotated centre.

    Returns ``{"centres_px": float (N, 2) (NaN where none was found), "points": [FlatPoint | None],
    "failures": {frame: reason}, "disk_px"}``. Raises GelsimError when the disk is too small to fit
    (a pixel size too coarse for the ball)."""
    disk = disk_radius_px(mm_per_px, ball_diameter_mm)
    if disk < FLAT_MIN_DISK_PX:
        raise GelsimError(f"the flat-point detector's disk is {disk:.1f} px (slope {FLAT_SLOPE:g} on a "
                          f"{ball_diameter_mm:g} mm ball at {mm_per_px:g} mm/px), under {FLAT_MIN_DISK_PX:g} px; "
                          f"give frames of a finer pixel size or --centres annotated")
    n = len(pack.imgs)
    cents = np.full((n, 2), np.nan)
    points: list[FlatPoint | None] = [None] * n
    failures: dict[int, str] = {}
    for i in range(n):
        delta = colour_change(pack.imgs[i], pack.f0, disk)
        got = flat_point(delta, pack.centers_px[i], FLAT_REACH * float(pack.radii_px[i]), disk)
        if isinstance(got, str):
            failures[i] = got
        else:
            points[i] = got
            cents[i] = got.centre_px
    return {"centres_px": cents, "points": points, "failures": failures, "disk_px": disk}
