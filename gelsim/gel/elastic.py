"""The reference imprint: frictionless contact with the elastic layer, solved at full resolution.

The object (rigid, or a fabric with its two compliances, :mod:`gelsim.gel.support`) is pressed on
the layer of :mod:`gelsim.gel.layer`; Polonsky-Keer conjugate gradients find the pressure at
every pixel. Exact for the discretised problem at every scale, from the contact patch to the
texture, and the yardstick of the faster models; seconds per frame on a fabric.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .layer import Operator, effective_modulus_mpa, pk_solve
from .support import FabricSupport
from .util import membrane_blur, pen_window

# The layer's displacement falls below 2% of its peak within 3 thicknesses of the contact
# (bonded base); the half-space's 1/r tail is cut at the frame's edge.
OUT_MARGIN_THICKNESS = 3.0


@dataclass(frozen=True)
class ElasticState:
    """The reference's pressure (MPa) over its solved window of the work grid."""
    pressure_mpa: np.ndarray
    window: tuple[slice, slice]
    work_shape: tuple[int, int]

    def pressure_field(self) -> np.ndarray:
        """The pressure on the whole work grid, MPa (float32, 0 outside the contact)."""
        out = np.zeros(self.work_shape, np.float32)
        out[self.window] = self.pressure_mpa
        return out
# Outer passes for the cloth's secant stiffness at the contact's mean pressure.
SUPPORT_PASSES = 2


def _operator(shape, dx, gel, support: FabricSupport | None, p: np.ndarray | None, force_n: float | None,
              area: float, texture_px: int = 0) -> Operator:
    """The layer with the cloth's secant compliance at the mean pressure over the *apparent* contact
    (the touching crowns closed over the texture's scale: the cloth spreads a crown's load over
    about its thickness, so it feels the patch's mean pressure, not the crowns')."""
    if support is None:
        return Operator(shape, dx, gel)
    if p is not None and np.any(p > 0):
        touch = (p > 0).astype(np.uint8)
        if texture_px >= 2:
            touch = cv2.morphologyEx(touch, cv2.MORPH_CLOSE, np.ones((texture_px, texture_px), np.uint8))
        load = force_n if force_n is not None else float(p.sum() * area)
        pm_kpa = 1e3 * load / (area * max(int(np.count_nonzero(touch)), 1))
    else:
        pm_kpa = 1e3 * (force_n / (area * shape[0] * shape[1]) if force_n else 1.0)
    ks = support.secant_stiffness_kpa_per_mm(pm_kpa)
    cs = 1e3 / ks if math.isfinite(ks) else 0.0
    return Operator(shape, dx, gel, cs, support.shear_length_mm,
                    winkler_compliance=1.0 / support.yarn_stiffness_mpa_per_mm)


def press_elastic(work: np.ndarray, dx: float, gel, *, force_n: float | None, depth_mm: float | None,
                  support: FabricSupport | None, window: str, guess_mm: float, texture_mm: float | None = None):
    """Press ``work`` (protrusion, mm, (ny, nx) at ``dx`` mm/px). ``guess_mm``: a first estimate of
    the approach for force control (from a faster model), to size the window.

    Returns (depth mm float32 (ny, nx) before the membrane blur, contact mask, approach mm, force N,
    bottomed, ElasticState). ``texture_mm``: the object's texture scale, for the apparent contact (see _operator).
    """
    pmax = float(work.max())
    v = (pmax - work).astype(np.float64)
    area = dx * dx
    bottomed = False
    full = window == "full"
    vmax = gel.max_indentation_mm
    p = None
    tpx = 0 if texture_mm is None else int(math.ceil(min(texture_mm, gel.thickness_mm) / dx))
    if force_n is not None:
        bound = min(max(2.0 * guess_mm, 1e-4), vmax)  # 0.1 um floor: a first guess only
        while True:
            sl = pen_window(v, bound, 2, "full" if full else "touched")
            hh = -v[sl]
            p = np.maximum(bound * 0.5 + hh, 0.0) + (hh >= -1e-12)
            for _ in range(SUPPORT_PASSES if support is not None else 1):
                op = _operator(hh.shape, dx, gel, support, p, force_n, area, tpx)
                p, delta, _ = pk_solve(op, hh, area, force=force_n, p0=p)
            if delta <= bound or bound >= vmax:
                break
            bound = min(2.0 * bound, vmax)
        if delta > vmax:
            depth_mm, bottomed = vmax, True
    if depth_mm is not None:
        delta = float(depth_mm)
        if delta > vmax:
            delta, bottomed = vmax, True
        sl = pen_window(v, delta, 2, "full" if full else "touched")
        if sl is None:
            return np.zeros(work.shape, np.float32), np.zeros(work.shape, bool), 0.0, 0.0, False, None
        hh = -v[sl]
        p0 = np.maximum(delta + hh, 0.0) * (effective_modulus_mpa(gel) / gel.thickness_mm)
        for _ in range(SUPPORT_PASSES if support is not None else 1):
            op = _operator(hh.shape, dx, gel, support, p if p is not None and p.shape == hh.shape else p0, None, area,
                           tpx)
            p, _, _ = pk_solve(op, hh, area, delta=delta, p0=p0 if p is None or p.shape != hh.shape else p)
    force = float(p.sum() * area)
    # Displacement over the output window (contact window + margin): one more convolution.
    ny, nx = work.shape
    out_margin = int(math.ceil(OUT_MARGIN_THICKNESS * gel.thickness_mm / dx))
    r0, r1 = sl[0].start, sl[0].stop
    c0, c1 = sl[1].start, sl[1].stop
    if full:
        R0, R1, C0, C1 = 0, ny, 0, nx
    else:
        R0, R1 = max(0, r0 - out_margin), min(ny, r1 + out_margin)
        C0, C1 = max(0, c0 - out_margin), min(nx, c1 + out_margin)
    big = np.zeros((R1 - R0, C1 - C0))
    big[r0 - R0:r1 - R0, c0 - C0:c1 - C0] = p
    u = Operator(big.shape, dx, gel).gel(big)
    depth = np.zeros(work.shape, np.float32)
    mask = np.zeros(work.shape, bool)
    depth[R0:R1, C0:C1] = np.maximum(u, 0.0).astype(np.float32)
    mask[sl] = p > 0
    return depth, mask, delta, force, bottomed, ElasticState(p.astype(np.float32), sl, work.shape)
