"""The two-scale imprint's macro contact (:func:`gelsim.gel.twoscale.solve_macro` and
:func:`gelsim.gel.twoscale.solve_on_cloth`, the cloth's support) for a batch of frames in torch: their twin.

Each frame has its own coarse grid (its touched box, its cell size, its grid's shape); the batch's grids share one
array of the largest shape, each frame's in its top-left corner and a ``valid`` mask over it, and the layer's
operator and Polonsky-Keer's solve run them in step (:mod:`gelsim.gel.layer_torch`). The cloth's fixed point, the
re-solve at the pad's travel, the warm start from the previous frame and the refinement of a small patch follow
the numpy path's decisions frame by frame (small host-side bookkeeping between the batched solves). Parity with
the numpy kernels: ``tests/gelsim/test_gel_kernels.py``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import batch_ops as ops
from . import twoscale as ts
from .layer_torch import BatchOperator, cloth_operator, pk_solve


@dataclass(frozen=True)
class DeviceMacroState:
    """A frame's macro solution, as :class:`gelsim.gel.twoscale.MacroState` (which see), its pressure a float32
    device tensor ``(cy, cx)`` MPa (the numpy path's float64 of the same float32 values)."""
    key: tuple
    pressure_mpa: object
    origin: tuple[int, int]
    block: int
    work_shape: tuple[int, int]
    bottomed: bool
    force_n: float
    contact_exponent: float | None

    def to_numpy(self) -> ts.MacroState:
        """The same state for the numpy path (:func:`gelsim.gel.press`'s ``warm``)."""
        return ts.MacroState(self.key, self.pressure_mpa.double().cpu().numpy(), self.origin, self.block,
                             self.work_shape, self.bottomed, self.force_n, self.contact_exponent)


def solve_at(op, hc, valid, area, delta, p, tol=ts.MACRO_TOL, maxit=ts.MACRO_MAXIT):
    """:func:`gelsim.gel.twoscale.solve_at` for every frame: the contact at the approach ``delta`` (float64
    ``(B,)`` mm), warm-started from ``p`` (MPa)."""
    torch = ops.torch_module()
    overlap = ((hc + delta[:, None, None]) > 0) & valid
    p0 = torch.where(overlap, p.clamp(min=0), 0.0)
    none = ~(p0 > 0).any(dim=(1, 2))
    p0 = torch.where(none[:, None, None], overlap.float(), p0)
    return pk_solve(op, hc, valid, area, delta=delta, p0=p0, tol=tol, maxit=maxit)[0]


def _subset(idx: list[int], *arrays):
    torch = ops.torch_module()
    if not arrays:
        return ()
    ix = torch.as_tensor(idx, device=arrays[0].device)
    return tuple(a.index_select(0, ix) for a in arrays)


def _scatter(dst, idx: list[int], src):
    torch = ops.torch_module()
    out = dst.clone()
    out[torch.as_tensor(idx, device=dst.device)] = src
    return out


def solve_on_cloth(hc, valid, cells, dx, gel, supports, force_n, p, *, vmax, at_travel, cells_pred,
                   tol=ts.MACRO_TOL, maxit=ts.MACRO_MAXIT):
    """:func:`gelsim.gel.twoscale.solve_on_cloth` under force control for every frame of the batch.

    hc: float64 ``(B, cy, cx)`` surface below its top (mm) on each frame's grid (``valid``, ``cells[b]`` = its
    (ny, nx), of ``dx[b]`` mm); supports: FabricSupport or None per frame; force_n: float (B,) N; p: the start
    (MPa); at_travel: bool per frame (the previous frame bottomed out); cells_pred: the contact predicted for
    the force per frame, or None. Returns (pressure float32 MPa, approach float (B,) mm, bottomed bool (B,))."""
    torch = ops.torch_module()
    bsz = hc.shape[0]
    dev = hc.device
    shape = tuple(hc.shape[1:])
    area_np = np.asarray([d * d for d in dx], np.float64)
    area = torch.as_tensor(area_np, device=dev)
    force = torch.as_tensor(np.asarray(force_n, np.float64), device=dev)
    delta = np.zeros(bsz)
    bottomed = np.zeros(bsz, bool)
    at_travel = np.asarray(at_travel, bool).copy()
    used = [None] * bsz
    active = np.ones(bsz, bool)
    for pas in range(ts.SUPPORT_PASSES):
        counts = (p > 0).logical_and(valid).sum(dim=(1, 2)).cpu().numpy()
        ks = np.full(bsz, math.inf)
        for b in range(bsz):
            if not active[b] or supports[b] is None:
                continue
            n = cells_pred[b] if (used[b] is None and cells_pred[b] is not None) else int(counts[b])
            pm_kpa = 1e3 * float(force_n[b]) / (area_np[b] * max(n, 1))
            ks[b] = supports[b].secant_stiffness_kpa_per_mm(pm_kpa)
            if used[b] is not None and abs(ks[b] - used[b]) <= ts.SUPPORT_TOL * used[b]:
                active[b] = False
        idx = [b for b in range(bsz) if active[b]]
        if not idx:
            break
        for b in idx:
            used[b] = ks[b]
        op = cloth_operator([cells[b] for b in idx], [dx[b] for b in idx], gel, [supports[b] for b in idx],
                            [ks[b] for b in idx], shape, dev)
        sub_h, sub_v, sub_p, sub_a, sub_f = _subset(idx, hc, valid, p, area, force)
        # (A) after a bottomed pass (or frame): the travel first
        trav = [i for i, b in enumerate(idx) if at_travel[b]]
        if trav:
            o = _sub_op(op, trav)
            tv = torch.full((len(trav),), float(vmax), dtype=torch.float64, device=dev)
            pt = solve_at(o, *_subset(trav, sub_h, sub_v, sub_a), tv, _subset(trav, sub_p)[0], tol, maxit)
            sub_p = _scatter(sub_p, trav, pt)
            carried = (pt.double().sum(dim=(1, 2)) * _subset(trav, sub_a)[0]).cpu().numpy()
            for j, i in enumerate(trav):
                b = idx[i]
                bottomed[b] = carried[j] < float(force_n[b])
                delta[b] = vmax
        # (B) force control where not bottomed
        fc = [i for i, b in enumerate(idx) if not (at_travel[b] and bottomed[b])]
        if fc:
            o = _sub_op(op, fc)
            fh, fv, fa, ff, fp = _subset(fc, sub_h, sub_v, sub_a, sub_f, sub_p)
            pf, df = pk_solve(o, fh, fv, fa, force=ff, p0=fp, tol=tol, maxit=maxit)
            df = df.cpu().numpy()
            over = [j for j in range(len(fc)) if df[j] > vmax]
            if over:
                o2 = _sub_op(o, over)
                tv = torch.full((len(over),), float(vmax), dtype=torch.float64, device=dev)
                po = solve_at(o2, *_subset(over, fh, fv, fa), tv, _subset(over, pf)[0], tol, maxit)
                pf = _scatter(pf, over, po)
            sub_p = _scatter(sub_p, fc, pf)
            for j, i in enumerate(fc):
                b = idx[i]
                bottomed[b] = df[j] > vmax
                delta[b] = vmax if bottomed[b] else float(df[j])
        p = _scatter(p, idx, sub_p)
        for b in idx:
            at_travel[b] = bottomed[b]
            if supports[b] is None or not math.isfinite(ks[b]):
                active[b] = False
    return p, delta, bottomed


def _sub_op(op: BatchOperator, idx: list[int]) -> BatchOperator:
    torch = ops.torch_module()
    return BatchOperator(op.kf.index_select(0, torch.as_tensor(idx, device=op.kf.device)), op.shape, op.m)


# ---------------------------------------------------------------- the coarse grid of each frame

@dataclass
class MacroPlan:
    """One frame's coarse grid: the box (r0, r1, c0, c1) of the work grid it covers, its cell ``f`` (px), its
    shape ``cshape`` (cells) and cell size ``cm`` (mm)."""
    box: tuple[int, int, int, int]
    f: int
    cshape: tuple[int, int]
    cm: float


def plan_grid(box, macro_cells, dx, valley_mm, cells_per_valley) -> MacroPlan:
    """The frame's coarse grid over ``box`` (:func:`gelsim.gel.twoscale.macro_cell_px`)."""
    r0, r1, c0, c1 = (int(v) for v in box)
    f = ts.macro_cell_px((r0, r1, c0, c1), macro_cells, dx, valley_mm, cells_per_valley)
    return MacroPlan((r0, r1, c0, c1), f, (-(-(r1 - r0) // f), -(-(c1 - c0) // f)), dx * f)


def _crown_index(n: int, m: int, f: int) -> np.ndarray:
    """For each of m cells along an axis of n pixels: the f pixels (offsets into the axis, clipped to it) whose
    maximum :func:`gelsim.gel.twoscale._axis_window_max` takes, int64 (m, f)."""
    c = np.minimum(np.floor(np.arange(m) * (1.0 / (m / n))), n - 1).astype(np.int64)
    return np.clip(c[:, None] - f // 2 + np.arange(f)[None, :], 0, n - 1)


def coarse_envelope(own, plans: list[MacroPlan], tex: list[float | None], dx: float, sag, shape):
    """Each frame's envelope on its coarse grid (float64 ``(B, cy, cx)``, the batch's ``shape``; the frame's own
    grid in its corner, the rest replicating its edge): with a texture scale, the crown pool of the object's
    own heights (``own``, float32 ``(B, H, W)``: the protrusion plus the dome's sag) closed over the coarse
    closing, less the sag at each cell's crown window (:func:`gelsim.gel.twoscale.solve_macro`); without, the
    area mean of the protrusion (``own`` less the sag) over each cell."""
    torch = ops.torch_module()
    dev = own.device
    bsz = own.shape[0]
    cy, cx = shape
    fmax = max(p.f for p in plans)
    rows = np.zeros((bsz, cy, fmax), np.int64)
    cols = np.zeros((bsz, cx, fmax), np.int64)
    weight = np.zeros((bsz, fmax), np.float64)      # (area mean: 1 for the frame's own f offsets)
    crown = np.array([t is not None for t in tex])
    for b, pl in enumerate(plans):
        r0, r1, c0, c1 = pl.box
        f = pl.f
        ny, nx = pl.cshape
        if crown[b]:
            ri = _crown_index(r1 - r0, ny, f)
            ci = _crown_index(c1 - c0, nx, f)
        else:   # _pool: blocks of f from the box's corner, the box's last row and column replicated
            ri = np.minimum(f * np.arange(ny)[:, None] + np.arange(f)[None, :], r1 - r0 - 1)
            ci = np.minimum(f * np.arange(nx)[:, None] + np.arange(f)[None, :], c1 - c0 - 1)
        ri = np.concatenate([ri, np.repeat(ri[-1:], cy - ny, 0)])          # cells past the grid: its last
        ci = np.concatenate([ci, np.repeat(ci[-1:], cx - nx, 0)])
        rows[b, :, :f] = r0 + ri
        rows[b, :, f:] = r0 + ri[:, -1:]
        cols[b, :, :f] = c0 + ci
        cols[b, :, f:] = c0 + ci[:, -1:]
        weight[b, :f] = 1.0
    rows_t, cols_t = ops.as_index(rows, dev), ops.as_index(cols, dev)
    height = own if sag is None else own - sag[None]
    w = ops.as_float(weight, dev, torch.float64)
    crown_t = torch.as_tensor(crown, device=dev)
    width = own.shape[2]
    # rows first: (B, cy, W) per offset, then columns
    mx = None
    sm = None
    for a in range(fmax):
        ri = rows_t[:, :, a][:, :, None].expand(bsz, cy, width)
        g_own = torch.gather(own, 1, ri)
        mx = g_own if mx is None else torch.maximum(mx, g_own)
        g_h = torch.gather(height, 1, ri).double() * w[:, a, None, None]
        sm = g_h if sm is None else sm + g_h
    cmx = None
    csm = None
    for e in range(fmax):
        ci = cols_t[:, :, e][:, None, :].expand(bsz, cy, cx)
        g_mx = torch.gather(mx, 2, ci)
        cmx = g_mx if cmx is None else torch.maximum(cmx, g_mx)
        g_sm = torch.gather(sm, 2, ci) * w[:, e, None, None]
        csm = g_sm if csm is None else csm + g_sm
    fs = torch.as_tensor([float(p.f * p.f) for p in plans], dtype=torch.float64, device=dev)
    mean = csm / fs[:, None, None]
    env = cmx
    if crown.any():
        # the coarse closing (per distinct kernel), on each frame's grid continued by replication
        ny_t = ops.as_index([p.cshape[0] for p in plans], dev)
        nx_t = ops.as_index([p.cshape[1] for p in plans], dev)
        ks = [ts.coarse_envelope_kernel_cells(t, dx, p.f) if t is not None else 1 for t, p in zip(tex, plans)]
        for k in sorted(set(ks)):
            if k < 2:
                continue
            sel = torch.as_tensor([kk == k for kk in ks], device=dev)
            x = ops.extend(env, ny_t, nx_t)
            x = ops.window_extreme(ops.window_extreme(x, k, 1, "max"), k, 2, "max")
            x = ops.extend(x, ny_t, nx_t)
            x = ops.window_extreme(ops.window_extreme(x, k, 1, "min"), k, 2, "min")
            env = torch.where(sel[:, None, None], x, env)
        env = env.double()
        if sag is not None:
            si = np.zeros((bsz, cy), np.int64)
            sj = np.zeros((bsz, cx), np.int64)
            for b, pl in enumerate(plans):
                r0, _, c0, _ = pl.box
                ny, nx = pl.cshape
                si[b] = r0 + pl.f * np.minimum(np.arange(cy), ny - 1)
                sj[b] = c0 + pl.f * np.minimum(np.arange(cx), nx - 1)
            s = sag[ops.as_index(si, dev)[:, :, None], ops.as_index(sj, dev)[:, None, :]].double()
            env = env - s
    return torch.where(crown_t[:, None, None], env.double(), mean)


def resample_warm(states: list, plans: list[MacroPlan], shape, device):
    """Each warm state's pressure at the centres of this frame's cells (:func:`gelsim.gel.twoscale.resample_pressure`:
    OpenCV's bilinear remap at float32 coordinates, zero beyond the old grid): float32 ``(B, cy, cx)``
    (zero for a frame whose state is None)."""
    torch = ops.torch_module()
    bsz = len(states)
    cy, cx = shape
    have = [s for s in states if s is not None]
    if not have:
        return torch.zeros((bsz, cy, cx), device=device)
    wy = max(s.pressure_mpa.shape[0] for s in have)
    wx = max(s.pressure_mpa.shape[1] for s in have)
    src = torch.zeros((bsz, wy + 2, wx + 2), device=device)
    sy = np.zeros((bsz, cy), np.float32)
    sx = np.zeros((bsz, cx), np.float32)
    for b, (st, pl) in enumerate(zip(states, plans)):
        if st is None:
            continue
        p = st.pressure_mpa
        src[b, 1:1 + p.shape[0], 1:1 + p.shape[1]] = p
        r0, _, c0, _ = pl.box
        ys = r0 + (np.arange(cy) + 0.5) * pl.f - 0.5
        xs = c0 + (np.arange(cx) + 0.5) * pl.f - 0.5
        blk, (oy, ox) = st.block, st.origin
        sy[b] = ((ys + 0.5) / blk - 0.5 - oy / blk).astype(np.float32)
        sx[b] = ((xs + 0.5) / blk - 0.5 - ox / blk).astype(np.float32)
    # OpenCV's remap (5.x): the float coordinates' whole part and fraction, taps beyond the source read 0
    y0 = np.floor(sy).astype(np.int64)
    x0 = np.floor(sx).astype(np.int64)
    ay = (sy - y0).astype(np.float32)
    ax = (sx - x0).astype(np.float32)
    lim_y = np.array([0 if s is None else s.pressure_mpa.shape[0] for s in states])[:, None]
    lim_x = np.array([0 if s is None else s.pressure_mpa.shape[1] for s in states])[:, None]

    def tap(i, lim, n):   # index into the padded source: 0 (a zero) beyond the old grid
        return np.where((i >= 0) & (i < lim), i + 1, 0)

    ty0, ty1 = tap(y0, lim_y, wy), tap(y0 + 1, lim_y, wy)
    tx0, tx1 = tap(x0, lim_x, wx), tap(x0 + 1, lim_x, wx)
    bi = torch.arange(bsz, device=device)[:, None, None]
    g = [[src[bi, ops.as_index(ty, device)[:, :, None], ops.as_index(tx, device)[:, None, :]] for tx in (tx0, tx1)]
         for ty in (ty0, ty1)]
    ay_t, ax_t = ops.as_float(ay, device)[:, :, None], ops.as_float(ax, device)[:, None, :]
    w00, w01 = (1 - ay_t) * (1 - ax_t), (1 - ay_t) * ax_t
    w10, w11 = ay_t * (1 - ax_t), ay_t * ax_t
    return g[0][0] * w00 + g[0][1] * w01 + g[1][0] * w10 + g[1][1] * w11


@dataclass
class MacroResult:
    """The batch's macro solutions: per frame its plan, pressure (float32 ``(cy, cx)`` view into ``p``), approach
    (mm), bottomed, the contact exponent it measured, and the envelope's top ``emax`` (mm); the batched tensors
    ``p`` (float32), ``hc`` (float64) and ``valid`` over the batch's grid shape."""
    plans: list[MacroPlan]
    p: object
    hc: object
    valid: object
    emax: np.ndarray
    delta: np.ndarray
    bottomed: np.ndarray
    exponent: list


def solve_macro(work, own, sag, plans: list[MacroPlan], dx: float, gel, tex: list, supports: list,
                force_n: np.ndarray, warm: list) -> MacroResult:
    """:func:`gelsim.gel.twoscale.solve_macro` for every frame of the batch (force control): ``work`` float32
    ``(B, H, W)`` the protrusion less the dome's sag, ``own`` the object's own heights (protrusion), ``sag`` the
    dome (``(H, W)`` or None); per frame its plan, texture scale (None: no crown envelope), support, force (N)
    and warm state (:class:`DeviceMacroState` or None)."""
    torch = ops.torch_module()
    dev = work.device
    bsz = len(plans)
    cy = max(p.cshape[0] for p in plans)
    cx = max(p.cshape[1] for p in plans)
    shape = (cy, cx)
    env = coarse_envelope(own, plans, tex, dx, sag, shape)
    yy = torch.arange(cy, device=dev)[None, :, None]
    xx = torch.arange(cx, device=dev)[None, None, :]
    ny_t = ops.as_index([p.cshape[0] for p in plans], dev)[:, None, None]
    nx_t = ops.as_index([p.cshape[1] for p in plans], dev)[:, None, None]
    valid = (yy < ny_t) & (xx < nx_t)
    emax_t = torch.where(valid, env, -math.inf).amax(dim=(1, 2))
    hc = torch.where(valid, env - emax_t[:, None, None], -1e3)
    vmax = float(gel.max_indentation_mm)
    # warm starts (numpy: solve_macro)
    same = [False] * bsz
    resample = [None] * bsz
    start = torch.sqrt(torch.clamp(hc + max(0.05 * vmax, 1e-4), min=0.0)).float()
    p = start.clone()
    for b, (st, pl) in enumerate(zip(warm, plans)):
        if st is None:
            continue
        key = (pl.cshape, pl.f)
        if st.key == key and st.origin == (pl.box[0], pl.box[2]):
            same[b] = True
            ny, nx = pl.cshape
            p[b] = 0.0
            p[b, :ny, :nx] = st.pressure_mpa
        elif tuple(st.work_shape) == tuple(work.shape[1:]):
            resample[b] = st
    if any(r is not None for r in resample):
        rp = torch.where(valid, resample_warm(resample, plans, shape, dev), 0.0)
        has = (rp > 0).any(dim=(1, 2)).cpu().numpy()
        for b in range(bsz):
            if resample[b] is not None and has[b]:
                p[b] = rp[b]
    p = torch.where(valid, p, 0.0)
    n_warm = ((p > 0) & valid).sum(dim=(1, 2)).cpu().numpy()
    at_travel = np.array([w is not None and w.bottomed for w in warm])
    cells_pred = [None] * bsz
    predictable = [False] * bsz
    for b, st in enumerate(warm):
        if same[b] and not st.bottomed and st.force_n > 0 and n_warm[b] > 0:
            predictable[b] = True
            a = ts.CONTACT_EXPONENT if st.contact_exponent is None else st.contact_exponent
            cells_pred[b] = n_warm[b] * (float(force_n[b]) / st.force_n) ** a
    p, delta, bottomed = solve_on_cloth(hc, valid, [pl.cshape for pl in plans], [pl.cm for pl in plans], gel,
                                        supports, force_n, p, vmax=vmax, at_travel=at_travel, cells_pred=cells_pred)
    counts = ((p > 0) & valid).sum(dim=(1, 2)).cpu().numpy()
    exponent = [None] * bsz
    for b, st in enumerate(warm):
        if predictable[b] and not bottomed[b]:
            step = math.log(float(force_n[b]) / st.force_n)
            if abs(step) >= ts.EXPONENT_MIN_STEP and counts[b] > 0:
                exponent[b] = min(max(math.log(counts[b] / n_warm[b]) / step, 0.0), 1.0)
            else:
                exponent[b] = st.contact_exponent
    return MacroResult(plans, p, hc, valid, emax_t.cpu().numpy(), delta, bottomed, exponent)
