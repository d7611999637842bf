"""The reference imprint: frictionless contact with the elastic layer, solved at full resolution.

The object (rigid, or a fabric with its two compliances, :mod:`gelsim.gel.support`) is pressed on
the layer of :mod:`gelsim.gel.layer`; Polonsky-Keer conjugate gradients find the pressure at
every pixel. Exact for the discretised problem at every scale, from the contact patch to the
texture, and the yardstick of the faster models; seconds per frame on a fabric.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .layer import CG_MAXIT, CG_TOL, Operator, effective_modulus_mpa
from .support import FabricSupport
from .twoscale import solve_on_cloth
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


def press_elastic(work: np.ndarray, dx: float, gel, *, force_n: float | None, depth_mm: float | None,
                  support: FabricSupport | None, window: str, guess_mm: float, texture_mm: float | None = None):
    """Press ``work`` (protrusion, mm, (ny, nx) at ``dx`` mm/px). ``guess_mm``: a first estimate of
    the approach for force control (from a faster model), to size the window.

    Returns (depth mm float32 (ny, nx) before the membrane blur, contact mask, approach mm, force N,
    bottomed, ElasticState). ``texture_mm``: the object's texture scale, for the cloth's apparent contact.

    The cloth's secant stiffness is taken at the mean pressure over the *apparent* contact: the touching
    crowns closed over the texture's scale (the cloth spreads a crown's load over about its thickness,
    so it feels the patch's mean pressure, not the crowns'). Its fixed point, and the re-solve at the
    travel of a press that bottoms out, are the two-scale model's (twoscale.solve_on_cloth): a bottomed
    press reports the force the gel carries at the travel, below the request.
    """
    pmax = float(work.max())
    v = (pmax - work).astype(np.float64)
    area = dx * dx
    full = window == "full"
    vmax = gel.max_indentation_mm
    tpx = 0 if texture_mm is None else int(math.ceil(min(texture_mm, gel.thickness_mm) / dx))

    def solve(hh, p, travel):
        return solve_on_cloth(hh, dx, gel, support, force_n, depth_mm, p, vmax=travel, tol=CG_TOL, maxit=CG_MAXIT,
                              close_px=tpx, dtype=np.float64)

    if force_n is not None:
        bound = min(max(2.0 * guess_mm, 1e-4), vmax)  # 0.1 um floor: a first guess only
        while True:
            sl = pen_window(v, bound, 2, "full" if full else "touched")
            hh = -v[sl]
            # A window short of the travel does not bottom out: an approach beyond it grows the window.
            p, delta, bottomed = solve(hh, np.maximum(bound * 0.5 + hh, 0.0) + (hh >= -1e-12),
                                       vmax if bound >= vmax else math.inf)
            if delta <= bound or bound >= vmax:
                break
            bound = min(2.0 * bound, vmax)
    else:
        reach = min(float(depth_mm), vmax)
        sl = pen_window(v, reach, 2, "full" if full else "touched")
        if sl is None:
            return np.zeros(work.shape, np.float32), np.zeros(work.shape, bool), 0.0, 0.0, False, None
        hh = -v[sl]
        p, delta, bottomed = solve(hh, np.maximum(reach + hh, 0.0) * (effective_modulus_mpa(gel) / gel.thickness_mm),
                                   vmax)
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
