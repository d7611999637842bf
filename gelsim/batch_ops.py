"""Small batched tensor operations the device imprint and markers share: per-frame index arithmetic that the numpy
path does with OpenCV (bounding boxes, window gathers with replicated edges, bilinear reads of coarse grids,
separable window maxima and box filters), each on ``(B, H, W)`` tensors whose frames have their own sizes.

Frames of a batch differ in their windows and grids; every array here is the batch's largest, each frame's data
in its top-left corner. Where an operation reads past a frame's own edge the numpy path replicates that edge
(OpenCV's BORDER_REPLICATE); :func:`extend` makes a frame's corner array hold those replicas out to the batch's
size, so that one batched filter with a replicated border reads, inside each frame, what the frame's own filter
reads.
"""
from __future__ import annotations

import numpy as np

from .optics.ops import pad_hw, torch_module  # noqa: F401 (torch_module: the torch kernels' way to torch)
from .optics.ops.box import extent_torch


def as_index(values, device):
    """int64 tensor of ``values`` (a sequence or array) on ``device``."""
    torch = torch_module()
    return torch.as_tensor(np.asarray(values, np.int64), device=device)


def as_float(values, device, dtype=None):
    """float32 (or ``dtype``) tensor of ``values`` on ``device``."""
    torch = torch_module()
    return torch.as_tensor(np.asarray(values, np.float64), device=device).to(dtype or torch.float32)


def bbox(mask):
    """Bounding boxes of the true pixels of each frame of bool ``(B, H, W)`` ``mask``: int64 ``(B, 4)``
    (r0, r1, c0, c1), ends exclusive; (0, 0, 0, 0) for a frame without any."""
    torch = torch_module()
    out = []
    for first, last in extent_torch(mask):
        empty = last < first
        out += [torch.where(empty, 0, first), torch.where(empty, 0, last + 1)]
    return torch.stack(out, dim=1)


def extend(x, rows, cols):
    """``x`` ``(B, H, W)`` with frame b's rows from ``rows[b]`` on and columns from ``cols[b]`` on replaced by
    its last row and column (int64 ``(B,)`` tensors, each >= 1): the frame's own array continued by
    replication out to the batch's size."""
    torch = torch_module()
    b, h, w = x.shape
    ri = torch.minimum(torch.arange(h, device=x.device)[None, :], rows[:, None] - 1)      # (B, H)
    ci = torch.minimum(torch.arange(w, device=x.device)[None, :], cols[:, None] - 1)      # (B, W)
    x = torch.gather(x, 1, ri[:, :, None].expand(b, h, w))
    return torch.gather(x, 2, ci[:, None, :].expand(b, h, w))


def crop(x, r0, c0, shape, rows, cols):
    """Each frame's window of ``x`` ``(B, H, W)``: rows ``r0[b]`` + (0 .. rows[b]) and columns ``c0[b]`` +
    (0 .. cols[b]) at the top-left of a ``shape`` (h, w) array, continued by replication beyond (see
    :func:`extend`); int64 ``(B,)`` tensors."""
    torch = torch_module()
    b = x.shape[0]
    h, w = shape
    ri = r0[:, None] + torch.minimum(torch.arange(h, device=x.device)[None, :], rows[:, None] - 1)
    ci = c0[:, None] + torch.minimum(torch.arange(w, device=x.device)[None, :], cols[:, None] - 1)
    y = torch.gather(x, 1, ri[:, :, None].expand(b, h, x.shape[2]))
    return torch.gather(y, 2, ci[:, None, :].expand(b, h, w))


def uncrop(win, r0, c0, rows, cols, shape, fill=0.0):
    """The inverse of :func:`crop`: a ``(B, H, W)`` frame (``shape``) holding frame b's window ``win[b, :rows,
    :cols]`` at (r0, c0) and ``fill`` elsewhere."""
    torch = torch_module()
    b, hw, ww = win.shape
    h, w = shape
    yy = torch.arange(h, device=win.device)[None, :] - r0[:, None]                      # (B, H)
    xx = torch.arange(w, device=win.device)[None, :] - c0[:, None]                      # (B, W)
    iny = (yy >= 0) & (yy < rows[:, None])
    inx = (xx >= 0) & (xx < cols[:, None])
    y = torch.gather(win, 1, yy.clamp(0, hw - 1)[:, :, None].expand(b, h, ww))
    y = torch.gather(y, 2, xx.clamp(0, ww - 1)[:, None, :].expand(b, h, w))
    inside = iny[:, :, None] & inx[:, None, :]
    return torch.where(inside, y, torch.as_tensor(fill, dtype=win.dtype, device=win.device))


def axis_weights(n_out: int, f, n_cells, origin=None, device=None):
    """The bilinear read of a coarse axis at fine pixels, as OpenCV's linear resize by the whole factor ``f``
    reads it (cell c's centre at fine pixel ``f c + (f - 1) / 2``, held beyond the first and last centres):
    for fine pixels ``origin + 0 .. n_out`` (``origin`` int64 (B,) or None for 0) of frames whose grids have
    ``n_cells[b]`` cells of ``f[b]`` pixels: (i0, i1, w) int64, int64, float32 ``(B, n_out)``."""
    torch = torch_module()
    x = torch.arange(n_out, device=device, dtype=torch.float64)[None, :]
    if origin is not None:
        x = x + origin[:, None].double()
    u = (x + 0.5) / f[:, None].double() - 0.5
    k = torch.minimum(torch.floor(u).clamp(min=0), (n_cells[:, None] - 1).double())
    i0 = k.long()
    i1 = torch.minimum(i0 + 1, n_cells[:, None] - 1)
    w = torch.where(i1 > i0, (u - k).clamp(0.0, 1.0), 0.0)
    return i0, i1, w.float()


def read_rows(field, i0, i1, w):
    """``field`` ``(B, R, W)`` blended along its rows: ``(B, n, W)`` from (i0, i1, w) ``(B, n)``
    (:func:`axis_weights`), as ``(1 - w) a + w b``."""
    torch = torch_module()
    b, _, cols = field.shape
    n = i0.shape[1]
    a = torch.gather(field, 1, i0[:, :, None].expand(b, n, cols))
    c = torch.gather(field, 1, i1[:, :, None].expand(b, n, cols))
    w = w[:, :, None]
    return a * (1.0 - w) + c * w


def read_cols(field, i0, i1, w):
    """``field`` ``(B, H, C)`` blended along its columns: ``(B, H, n)`` (as :func:`read_rows`)."""
    torch = torch_module()
    b, rows, _ = field.shape
    n = i0.shape[1]
    a = torch.gather(field, 2, i0[:, None, :].expand(b, rows, n))
    c = torch.gather(field, 2, i1[:, None, :].expand(b, rows, n))
    w = w[:, None, :]
    return a * (1.0 - w) + c * w


def upsample_cells(field, f, rows, cols, shape):
    """A coarse field ``(B, r, c)`` of ``f``-pixel cells read at every fine pixel of a ``shape`` (H, W) array as
    OpenCV's linear resize reads it (along the rows first; :mod:`gelsim.gel.texture_kernels`' contract); ``f``,
    ``rows``, ``cols`` int64 ``(B,)``: each frame's factor and grid."""
    h, w = shape
    xi0, xi1, wx = axis_weights(w, f, cols, device=field.device)
    yi0, yi1, wy = axis_weights(h, f, rows, device=field.device)
    return read_rows(read_cols(field, xi0, xi1, wx), yi0, yi1, wy)


def _pad_window(x, k: int, dim: int):
    """``(B, H, W)`` ``x`` with ``k // 2`` replicas of its first and ``k - 1 - k // 2`` of its last sample along
    ``dim`` (1: rows, 2: columns): what a window of ``k`` anchored at ``k // 2`` reads, OpenCV's replicated border."""
    a, b = k // 2, k - 1 - k // 2
    return pad_hw(x, (a, b, 0, 0) if dim == 2 else (0, 0, a, b), "replicate")


def window_extreme(x, k: int, dim: int, op: str):
    """Maximum (``op`` "max") or minimum ("min") over ``k`` samples along ``dim`` (1: rows, 2: columns) of
    ``(B, H, W)`` ``x``, anchored at ``k // 2`` as OpenCV's morphology and box filters are, the border
    replicated: sample i reads [i - k // 2, i - k // 2 + k). By window doubling (log2(k) + 1 passes)."""
    torch = torch_module()
    if k <= 1:
        return x
    n = x.shape[dim]
    m = _pad_window(x, k, dim)
    fn = torch.maximum if op == "max" else torch.minimum
    w, size = 1, n + k - 1
    while 2 * w <= k:
        size -= w
        m = fn(m.narrow(dim, 0, size), m.narrow(dim, w, size))
        w *= 2
    return fn(m.narrow(dim, 0, n), m.narrow(dim, k - w, n))


def closing(x, k: int):
    """Grey closing of each frame of ``(B, H, W)`` ``x`` by a k x k square, the border replicated: a dilation then an
    erosion (:func:`window_extreme` along the rows and the columns), what ``cv2.morphologyEx(MORPH_CLOSE)`` with
    BORDER_REPLICATE gives (:func:`gelsim.gel.twoscale.crown_envelope`'s closing): maxima and minima, exact."""
    if k < 2:
        return x
    d = window_extreme(window_extreme(x, k, 1, "max"), k, 2, "max")
    return window_extreme(window_extreme(d, k, 1, "min"), k, 2, "min")


def box_filter(x, k: int):
    """cv2.blur of each frame of ``(B, H, W)`` (or ``(B, C, H, W)`` channel by channel) ``x`` with a k x k box,
    anchor k // 2, border replicated: the mean over rows [i - k // 2, i - k // 2 + k) and likewise columns
    (rows first). Running sums in float64, rounded to float32."""
    torch = torch_module()
    if k <= 1:
        return x
    shape = x.shape
    y = x.reshape(-1, shape[-2], shape[-1]).double()
    for dim in (2, 1):
        n = y.shape[dim]
        c = torch.cumsum(_pad_window(y, k, dim), dim=dim)
        zero = torch.zeros_like(c.narrow(dim, 0, 1))
        c = torch.cat([zero, c], dim=dim)
        y = (c.narrow(dim, k, n) - c.narrow(dim, 0, n)) * (1.0 / k)
    return y.float().reshape(shape)
