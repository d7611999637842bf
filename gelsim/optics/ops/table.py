"""The calibrated table's lookup: the colour change at the membrane's normal (:mod:`gelsim.optics.lut`).

Per pixel, the normal's in-plane components ``(nx, ny) = -g / sqrt(1 + |g|^2)`` (``g``: the imprint's
slopes) pick a bilinear sample of the table, whose bins span -1..1: bin coordinate ``half (1 + n)``
with ``half = (nb - 1) / 2``. Two forms (:class:`TableLookup`, built by
:func:`gelsim.optics.lut.table_lookup`): a mosaic of 3-colour tables, one per tile of the frame with the
spatial terms evaluated at its centre (``offx, offy`` move each pixel's coordinates into its tile), or
the exact 9-channel table weighted per pixel by its own ``[1, xn, yn]``.

numpy kernel: OpenCV's remap in bands of rows; torch kernel: the same bilinear taps and weights
(:func:`remap_torch`) over whole frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import torch_module
from .filters import slopes, slopes_torch

_SUM3 = np.ones((1, 3), np.float32)     # cv2.transform matrix: the sum of three channels


@dataclass(frozen=True)
class TableLookup:
    """A table ready to be looked up at a profile's resolution ``(H, W)``. ``half``: ``(nb - 1) / 2`` for
    ``nb`` bins; ``exact``: the 9-channel form (else the mosaic); ``offx, offy``: float32 ``(H, W)`` bin
    offsets of each pixel's tile (``half`` everywhere for the exact form). Mosaic: ``mosaic4`` float32
    ``(Hm, Wm, 4)``, the tiles' 3-colour tables side by side with a zero fourth channel (OpenCV's remap
    interpolates 4-channel float images with vector instructions and 3-channel ones without).
    Exact: ``t9`` float32 ``(nb, nb, 9)`` (channel ``3 colour + basis``), ``xn`` ``(W,)`` and ``yn``
    ``(H,)`` the pixels' positions in -1..1 of the field (clamped to the table's ``position_box``) and
    ``wts`` float32 ``(H, 3 W, 3)`` their basis ``[1, xn, yn]`` per pixel and colour (:func:`basis_weights`)."""
    half: float
    exact: bool
    offx: np.ndarray
    offy: np.ndarray
    mosaic4: np.ndarray | None = None
    t9: np.ndarray | None = None
    xn: np.ndarray | None = None
    yn: np.ndarray | None = None
    wts: np.ndarray | None = None

    def band_weights(self, roi, r0: int, r1: int):
        """The exact form's :attr:`wts` for rows ``r0:r1`` of box ``roi`` (None for the mosaic)."""
        if not self.exact:
            return None
        y0, x0 = roi[0].start or 0, roi[1].start or 0
        x1 = roi[1].stop if roi[1].stop is not None else self.offx.shape[1]
        return self.wts[y0 + r0:y0 + r1, 3 * x0:3 * x1]


def basis_weights(xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    """Per pixel and colour the table's basis ``[1, xn, yn]``: float32 ``(h, 3 w, 3)`` from ``(h, w)`` positions."""
    h, w = xn.shape
    b = np.empty((h, w, 3, 3), np.float32)
    b[..., 0] = 1.0
    b[..., 1] = np.asarray(xn, np.float32)[..., None]
    b[..., 2] = np.asarray(yn, np.float32)[..., None]
    return b.reshape(h, 3 * w, 3)


def lookup_rows(d: np.ndarray, top: int, rows: int, offx: np.ndarray, offy: np.ndarray, out: np.ndarray,
                lut: TableLookup, mm_per_px: float, buffer, wts: np.ndarray | None = None) -> None:
    """The table's colour change of rows ``top:top + rows`` of imprint ``d`` (float32 mm, with the slope
    stencil's extra rows above and below where the frame has them) into ``out`` (float32 ``(rows, w, 3)``
    DN). ``offx, offy``: :attr:`TableLookup.offx` and ``offy`` over those rows; ``wts``: the exact form's
    weights over them (:meth:`TableLookup.band_weights`); ``buffer(name, shape)``: float32 work arrays
    kept between calls (cv2 calls into reused buffers: numpy temporaries were 3x slower)."""
    shape = d.shape
    gx, gy = slopes(d, mm_per_px, buffer("gx", shape), buffer("gy", shape))
    k = buffer("k", shape)
    gx, gy, k = gx[top:top + rows], gy[top:top + rows], k[top:top + rows]
    # map = offset + half - half * g / sqrt(1 + |g|^2): the bin of the normal's (nx, ny) in the pixel's tile
    cv2.multiply(gx, gx, k)
    cv2.accumulateSquare(gy, k)
    cv2.add(k, 1.0, k)
    cv2.pow(k, -0.5, k)                 # one pass; sqrt then divide took 8x longer
    cv2.multiply(gx, k, gx, scale=-lut.half)
    cv2.add(gx, offx, gx)
    cv2.multiply(gy, k, gy, scale=-lut.half)
    cv2.add(gy, offy, gy)
    if wts is None:
        r4 = buffer("r4", (rows, shape[1], 4))
        cv2.remap(lut.mosaic4, gx, gy, cv2.INTER_LINEAR, r4, borderMode=cv2.BORDER_REPLICATE)
        cv2.cvtColor(r4, cv2.COLOR_RGBA2RGB, out)       # drop the zero fourth channel
        return
    r9 = buffer("r9", (rows, shape[1], 9))
    cv2.remap(lut.t9, gx, gy, cv2.INTER_LINEAR, r9, borderMode=cv2.BORDER_REPLICATE)
    r = r9.reshape(rows, 3 * shape[1], 3)
    cv2.multiply(r, wts, r)
    np.copyto(out, cv2.transform(r, _SUM3).reshape(rows, shape[1], 3))


# ---------------------------------------------------------------- torch

@dataclass(frozen=True)
class TableLookupTorch:
    """:class:`TableLookup` on a device (:func:`lookup_to_torch`): ``table`` ``(C, Hm, Wm)`` (the mosaic's 3
    colours, or the exact form's 9 channels), ``offx`` ``(W,)``, ``offy`` ``(H,)``, and for the exact form
    ``xn`` ``(W,)`` and ``yn`` ``(H,)``."""
    half: float
    exact: bool
    table: object
    offx: object
    offy: object
    xn: object = None
    yn: object = None


def lookup_to_torch(lut: TableLookup, device) -> TableLookupTorch:
    """``lut``'s arrays as float32 tensors on ``device`` (the tiles' offsets vary along one axis each)."""
    torch = torch_module()

    def t(a):
        return None if a is None else torch.tensor(np.ascontiguousarray(a, np.float32), device=device)

    table = lut.t9 if lut.exact else lut.mosaic4[..., :3]
    return TableLookupTorch(lut.half, lut.exact, t(table.transpose(2, 0, 1)), t(lut.offx[0]),
                            t(lut.offy[:, 0]), t(lut.xn), t(lut.yn))


def remap_torch(src, mx, my, fixed_point: bool):
    """OpenCV's ``remap`` (INTER_LINEAR, BORDER_REPLICATE) of ``src`` ``(C, Hm, Wm)`` at float pixel coordinates
    ``mx, my`` ``(B, H, W)``: ``(C, B, H, W)``. The four taps' weights as OpenCV 5.0 computes them: from the
    coordinates' fractions for images of 1 to 4 channels, from the coordinates rounded to 1/32 px for
    more channels (``fixed_point``: its fixed-point path, whose weights ``(32 - i)(32 - j) / 1024`` are
    exact); the taps summed in its order. Each output pixel reads its own coordinates only."""
    torch = torch_module()
    if fixed_point:
        qx, qy = torch.round(mx * 32.0).long(), torch.round(my * 32.0).long()
        x0, y0 = qx >> 5, qy >> 5
        fx, fy = (qx & 31).float() * (1.0 / 32.0), (qy & 31).float() * (1.0 / 32.0)
    else:
        x0, y0 = torch.floor(mx), torch.floor(my)
        fx, fy = mx - x0, my - y0
        x0, y0 = x0.long(), y0.long()
    c, hm, wm = src.shape
    flat = src.reshape(c, hm * wm)

    def tap(y, x, weight):
        idx = y.clamp(0, hm - 1) * wm + x.clamp(0, wm - 1)
        return flat[:, idx] * weight

    gx, gy = 1.0 - fx, 1.0 - fy
    return ((tap(y0, x0, gy * gx) + tap(y0, x0 + 1, gy * fx)) + tap(y0 + 1, x0, fy * gx)) + tap(y0 + 1, x0 + 1, fy * fx)


def lookup_torch(d, lut: TableLookupTorch, mm_per_px: float):
    """:func:`lookup_rows` of whole frames: ``(B, 3, H, W)`` DN from imprints ``(B, H, W)`` mm."""
    torch = torch_module()
    gx, gy = slopes_torch(d, mm_per_px)
    k = 1.0 / torch.sqrt(gx * gx + gy * gy + 1.0)
    mx = gx * k * (-lut.half) + lut.offx[None, :]
    my = gy * k * (-lut.half) + lut.offy[:, None]
    out = remap_torch(lut.table, mx, my, lut.exact).transpose(0, 1)
    if not lut.exact:
        return out
    # per colour the three basis values weighted by the pixel's [1, xn, yn], summed in that order
    xn, yn = lut.xn[None, :], lut.yn[:, None]
    return torch.stack([(out[:, 3 * i] + out[:, 3 * i + 1] * xn) + out[:, 3 * i + 2] * yn for i in range(3)], dim=1)
