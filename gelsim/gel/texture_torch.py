"""The two-scale imprint's texture stage (:func:`gelsim.gel.twoscale.texture_depth` and the passes of
:mod:`gelsim.gel.texture_kernels`) for a batch of frames in torch.

The frames of one call share the texture's scale (one fabric's, or fabrics of the same scale) and so the
statistics grid's cell ``fs``, the band's blur and the smoothing's width; each has its own contact window
(its own size, its cells tiling it from its corner), its own local pressure and its own support. Every frame's
window sits in the top-left corner of the batch's arrays and is continued beyond its padded size by replicating
its edge, which is what every filter of the numpy path reads past that edge (:mod:`gelsim.batch_ops`); the
slopes' mirrored edge and the cell sums are taken at each frame's own edge.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import batch_ops as ops
from ..optics.ops.resample import area_mean_torch
from . import texture_kernels as tk
from . import twoscale as ts
from .johnson import segment_arrays
from .layer import effective_modulus_mpa

CONTACT, KEPT, LAM = tk.CONTACT, tk.KEPT, tk.LAM


@dataclass(frozen=True)
class TextureScale:
    """What the frames of one texture call share: the texture's scale ``tex`` (mm) at ``dx`` mm per pixel, and
    what follows from it (see :func:`gelsim.gel.twoscale.texture_depth`)."""
    tex: float
    dx: float

    @property
    def fs(self) -> int:
        fs = max(1, int(self.tex / (4.0 * self.dx)))
        return fs - fs % 2 if self.half_from(fs) else fs

    def half_from(self, fs: int) -> bool:
        return fs >= 2

    @property
    def half(self) -> bool:
        return self.half_from(max(1, int(self.tex / (4.0 * self.dx))))

    @property
    def unit(self) -> int:
        return 2 * self.fs if self.half else self.fs

    @property
    def sigma(self) -> float:
        return self.tex / (ts.STATS_BLUR_PER_TEXTURE * self.dx)

    @property
    def blurred(self) -> bool:
        return self.sigma >= 0.5

    @property
    def k(self) -> int:
        return max(1, int(round(self.tex / (self.dx * self.fs))))


def _tables(device):
    torch = ops.torch_module()
    lo, hi, per_step, v0, slope = segment_arrays()
    return (float(lo), float(hi), float(per_step), torch.as_tensor(v0, device=device),
            torch.as_tensor(slope, device=device))


def read_table(s, a, key: int, tables):
    """:func:`gelsim.gel.texture_kernels._read_table`: column ``key`` at p / p* = ``s``, blended from the 2-D
    wave (``a`` 0) to the 1-D wave (1); 1 at s >= 1."""
    torch = ops.torch_module()
    lo, hi, per_step, v0, slope = tables
    last = v0.shape[2] - 1
    u = (torch.clamp(s, lo, hi) - lo) * per_step
    i = torch.clamp(u.long(), max=last)
    f = u - i.float()
    v = v0[1, key][i] + slope[1, key][i] * f
    v = v + a * (v0[0, key][i] + slope[0, key][i] * f - v)
    return torch.where(s >= 1.0, 1.0, v)


def _asin_over_x(x):
    torch = ops.torch_module()
    safe = torch.where(x > 0, x, 1.0)
    return torch.where(x > 0, torch.asin(safe) / safe, 1.0)


def _sinc_factor(qdx2, d: float):
    torch = ops.torch_module()
    r = _asin_over_x(torch.clamp(torch.sqrt(qdx2) * d, max=1.0))
    return r * r


def _share(q, e_half: float, yarn_comp, has_cloth, cloth_k, ell):
    """:func:`gelsim.gel.texture_kernels._share`; the support's terms per frame ``(B, 1, 1)``."""
    torch = ops.torch_module()
    comp = yarn_comp + torch.where(has_cloth, 1.0 / (cloth_k * (1.0 + (q * ell) * (q * ell))), 0.0)
    return 1.0 / (1.0 + e_half * q * comp)


def _slopes(b, h: float, rows, cols):
    """Central-difference slopes (gx, gy) of ``(B, H, W)`` ``b`` times ``h``, zero across each frame's own edge
    (rows ``rows[b]``, columns ``cols[b]``: the mirrored neighbour of :func:`gelsim.gel.texture_kernels._slopes`)."""
    torch = ops.torch_module()
    bsz, hh, ww = b.shape
    gx = torch.zeros_like(b)
    gy = torch.zeros_like(b)
    if ww > 2:
        gx[:, :, 1:-1] = (b[:, :, 2:] - b[:, :, :-2]) * h
    if hh > 2:
        gy[:, 1:-1] = (b[:, 2:] - b[:, :-2]) * h
    yy = torch.arange(hh, device=b.device)[None, :, None]
    xx = torch.arange(ww, device=b.device)[None, None, :]
    gx = torch.where((xx == 0) | (xx >= cols[:, None, None] - 1), 0.0, gx)
    gy = torch.where((yy == 0) | (yy >= rows[:, None, None] - 1), 0.0, gy)
    return gx, gy


def cell_sums(x, fs: int):
    """Sums over ``fs`` x ``fs`` cells of ``(B, H, W)`` ``x`` (H, W multiples of fs), float64 ``(B, H/fs, W/fs)``."""
    b, h, w = x.shape
    if fs == 1:
        return x.double()
    return x.double().reshape(b, h // fs, fs, w // fs, fs).sum(dim=(2, 4))


@dataclass
class TextureBatch:
    """The texture's part of each frame's gel surface over its window (:class:`gelsim.gel.twoscale.TextureDepth`):
    ``g`` (mm) and ``touch`` ``(B, NY, NX)``, its local mean on the cells ``mean`` ``(B, rows, cols)``, and the
    cells' read at every pixel ``mean_px`` ``(B, NY, NX)``."""
    g: object
    mean: object
    touch: object
    mean_px: object
    fs: int


def texture_depth(surface, env, ny, nx, pressure_cells, scale: TextureScale, gel, supports, cloth_mpa_per_mm):
    """:func:`gelsim.gel.twoscale.texture_depth` for a batch of windows.

    surface, env: float32 ``(B, NY, NX)`` each frame's window of the object (less the dome) and of its crown
    envelope at the top-left, continued by replication (:func:`gelsim.batch_ops.crop`); ny, nx: int64 ``(B,)``
    the windows' sizes; ``pressure_cells(rows, cols, NYb, NXb)``: the local mean pressure averaged over each
    frame's cells (MPa, float32 ``(B, R, C)``, see :func:`gelsim.gel.twoscale_torch`); supports: per frame;
    cloth_mpa_per_mm: float (B,), the cloth's secant stiffness (inf: rigid)."""
    torch = ops.torch_module()
    dev = surface.device
    bsz = surface.shape[0]
    dx = scale.dx
    fs, half, unit, sigma, blurred, k = scale.fs, scale.half, scale.unit, scale.sigma, scale.blurred, scale.k
    NYb = ny + (-ny) % unit                     # each frame's padded size, whole cells
    NXb = nx + (-nx) % unit
    NY, NX = int(NYb.max()), int(NXb.max())
    t = surface[:, :NY, :NX] - env[:, :NY, :NX]
    rows, cols = NYb // fs, NXb // fs
    C = NX // fs
    if blurred:
        from ..optics.ops.filters import smooth_torch

        tq = smooth_torch(t, sigma, border="replicate")
    else:
        tq = t

    def ext(cells):
        if cells.dim() == 4:
            return torch.stack([ops.extend(cells[:, i], rows, cols) for i in range(cells.shape[1])], dim=1)
        return ops.extend(cells, rows, cols)

    def smooth(cells):
        # (each frame's own cells, continued by replication, as each box filter's border reads them)
        return ops.box_filter(ext(ops.box_filter(ext(cells), k)), k)

    q_lo = 2.0 * math.pi / (k * fs * dx)
    e_star = effective_modulus_mpa(gel)
    yarn = np.zeros(bsz, np.float32)
    has_cloth = np.zeros(bsz, bool)
    cloth_k = np.ones(bsz, np.float32)
    ell = np.zeros(bsz, np.float32)
    for b, sup in enumerate(supports):
        if sup is not None:
            yarn[b] = 1.0 / sup.yarn_stiffness_mpa_per_mm
            if math.isfinite(cloth_mpa_per_mm[b]):
                has_cloth[b], cloth_k[b], ell[b] = True, cloth_mpa_per_mm[b], sup.shear_length_mm
    sh_args = (e_star / 2.0, ops.as_float(yarn, dev)[:, None, None],
               torch.as_tensor(has_cloth, device=dev)[:, None, None], ops.as_float(cloth_k, dev)[:, None, None],
               ops.as_float(ell, dev)[:, None, None])
    tables = _tables(dev)

    # The band's statistics from the cells' moments (kernels.moment_sums, band_cells)
    d_band = 2.0 * dx if half else dx
    if half:
        b = area_mean_torch(tq, 2)            # cv2.resize's INTER_AREA, as the numpy path's
        brow, bcol = NYb // 2, NXb // 2
    else:
        b, brow, bcol = tq, NYb, NXb
    f = b.shape[2] // C
    gx, gy = _slopes(b, 0.5 / d_band, brow, bcol)
    if f == 1:
        mom = torch.stack([b, b * b, gx * gx, gy * gy, gx * gy], dim=1)
    else:
        mom = torch.stack([cell_sums(v, f) for v in (b, b * b, gx * gx, gy * gy, gx * gy)], dim=1).float()
        mom = mom / float(np.float32(f * f))
    mom = smooth(mom)
    m, b2, bxx, byy, bxy = (mom[:, i] for i in range(5))
    var = torch.clamp(b2 - m * m, min=tk.VAR_FLOOR_MM2)
    gxx = torch.clamp(bxx, min=0.0)
    gyy = torch.clamp(byy, min=0.0)
    cx_ = _sinc_factor(gxx / var, d_band)
    cy_ = _sinc_factor(gyy / var, d_band)
    gxx = gxx * cx_
    gyy = gyy * cy_
    gxy = bxy * torch.sqrt(cx_ * cy_)
    s2 = gxx + gyy
    q = torch.clamp(torch.sqrt(s2 / var), q_lo, math.pi / d_band)
    spread = torch.sqrt((gxx - gyy) * (gxx - gyy) + 4.0 * gxy * gxy)
    aniso = torch.clamp(spread / torch.clamp(s2, min=tk.VAR_FLOOR_MM2), max=1.0)
    m_tq = m

    # Johnson's map per cell (kernels.map_cells)
    p_small = pressure_cells(rows, cols, NYb, NXb)
    gain = torch.exp(-0.5 * torch.square(q * (sigma * dx if blurred else 0.0)))
    inv = 1.0 / gain
    share = _share(q, *sh_args)
    depth = torch.sqrt(var) * inv * (4.0 - (4.0 - 2.0 * math.sqrt(2.0)) * aniso)
    d_eff = torch.clamp(depth * share, min=tk.DEPTH_FLOOR_MM)
    s = torch.clamp(p_small / ((e_star / 4.0) * q * d_eff), max=ts.S_MAX)
    span = 1.0 - read_table(s, aniso, LAM, tables)
    phi = read_table(s, aniso, CONTACT, tables)

    fsv = torch.full_like(rows, fs)

    def px(cells):
        return ops.upsample_cells(ops.extend(cells, rows, cols), fsv, rows, cols, (NY, NX))

    if blurred:
        mp = px(m_tq)
        band = mp + (tq - mp) * px(inv)
        tf = t - band
        te = band * px(share)
        tf2 = cell_sums(tf * tf, fs)
        tgx, tgy = _slopes(tf, 0.5 / dx, NYb, NXb)
        tg2 = cell_sums(tgx * tgx + tgy * tgy, fs)
    else:
        te, tf = t * px(share), None

    cut = bearing_cut(te, ny, nx, d_eff, fs, phi)
    if tf is not None:
        cell_px = float(fs * fs)
        var_f = smooth((tf2 / cell_px).float())
        g2 = smooth((tg2 / cell_px).float())
        v = torch.clamp(var_f, min=tk.VAR_FLOOR_MM2)
        gg = torch.clamp(g2, min=0.0)
        gg = gg * _sinc_factor(0.5 * gg / v, dx)
        qf = torch.clamp(torch.sqrt(gg / v), q_lo, math.pi / dx)
        shf = _share(qf, *sh_args)
        crown_p = p_small / torch.clamp(phi, min=tk.PHI_FLOOR)
        depth_f = torch.clamp(4.0 * torch.sqrt(v) * shf, min=tk.DEPTH_FLOOR_MM)
        ps = torch.clamp(crown_p / ((e_star / 4.0) * qf * depth_f), max=ts.S_MAX)
        kept_f = read_table(ps, torch.zeros_like(ps), KEPT, tables) * shf
    # kernels.press_texture
    below = torch.clamp(te + px(cut), max=0.0)
    inside = below >= 0.0
    g = te - px(span) * below
    if tf is not None:
        g = g + torch.where(inside, tf * px(kept_f), 0.0)
    g_sum = cell_sums(g, fs)
    mean = smooth((g_sum / float(fs * fs)).float())
    return TextureBatch(g, mean, inside, px(mean), fs)


def bearing_cut(te, ny, nx, d_eff, fs: int, phi):
    """:func:`gelsim.gel.twoscale._bearing_cut` per frame: ``d_eff`` times the window's bearing curve of
    ``-te / d_eff`` (about BEARING_SAMPLES samples of its first ny[b] rows and nx[b] columns) read at ``phi``."""
    torch = ops.torch_module()
    dev = te.device
    bsz = te.shape[0]
    nyh, nxh = ny.cpu().numpy(), nx.cpu().numpy()
    strides = [max(1, int(math.sqrt(int(a) * int(c) / ts.BEARING_SAMPLES))) for a, c in zip(nyh, nxh)]
    counts = [(-(-int(a) // s)) * (-(-int(c) // s)) for a, c, s in zip(nyh, nxh, strides)]
    n = max(counts)
    ri = np.zeros((bsz, n), np.int64)
    ci = np.zeros((bsz, n), np.int64)
    pad = np.zeros((bsz, n), bool)
    for b in range(bsz):
        s = strides[b]
        rr = np.arange(0, int(nyh[b]), s)
        cc = np.arange(0, int(nxh[b]), s)
        k = counts[b]
        ri[b, :k] = np.repeat(rr, cc.size)
        ci[b, :k] = np.tile(cc, rr.size)
        pad[b, k:] = True
    ri_t, ci_t = ops.as_index(ri, dev), ops.as_index(ci, dev)
    bi = torch.arange(bsz, device=dev)[:, None]
    rows_c = torch.clamp(ri_t // fs, max=d_eff.shape[1] - 1)
    cols_c = torch.clamp(ci_t // fs, max=d_eff.shape[2] - 1)
    z = -te[bi, ri_t, ci_t] / d_eff[bi, rows_c, cols_c]
    z = torch.where(torch.as_tensor(pad, device=dev), math.inf, z)
    z, _ = torch.sort(z, dim=1)
    cnt = torch.as_tensor(counts, device=dev)
    nf = cnt.float()[:, None, None]
    x = torch.clamp(phi * nf - 0.5, min=0.0)
    x = torch.minimum(x, nf - 1)
    i = torch.minimum(x.long(), torch.clamp(cnt - 2, min=0)[:, None, None])
    flat = z.reshape(bsz, -1)
    z0 = torch.gather(flat, 1, i.reshape(bsz, -1)).reshape(i.shape)
    z1 = torch.gather(flat, 1, torch.minimum(i + 1, (cnt - 1)[:, None, None]).reshape(bsz, -1)).reshape(i.shape)
    v = z0.double() + (x.double() - i.double()) * (z1 - z0).double()
    one = (cnt == 1)[:, None, None]
    v = torch.where(one, z[:, :1, None].double().expand_as(v), v)
    return (v * d_eff.double()).float()
