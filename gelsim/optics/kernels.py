"""Fused per-pixel passes of the renderer's compositing (:mod:`gelsim.optics.composite`).

Each kernel does in one pass over memory what a chain of OpenCV calls did in several, with the
same float32 arithmetic in the same order, so that frames stay bit for bit those of the OpenCV
chain (checked against it in tests/gelsim/test_optics_kernels.py):

- :func:`add_noise_u8`: ``uint8(frame + sigma z)``, one ``cv2.addWeighted(..., dtype=CV_8U)``;
- :func:`add_shot_noise_u8`: ``uint8(frame + sqrt(max(gain frame + read_var, 0)) z)``, five
  OpenCV passes (addWeighted, max, sqrt, multiply, add).

Conversion to 8 bits is OpenCV's: round to nearest (ties to even) and saturate at 0 and 255.
Frames are finite (the renderer checks its inputs). The kernels are single-threaded (a dataset's
workers are one process per core) and release the GIL. Numba compiles them on first use (about a
second, cached on disk afterwards).

Contract: a frame is float32 ``(H, W * C)`` (an ``(H, W, C)`` frame's rows, C-contiguous); the
noise is read from a C-contiguous bank float32 ``(H + pad, (W + pad) * C)`` at row ``oy`` and
flat column ``ox`` (``C`` times the pixel column); the output is uint8 ``(H, W * C)``.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

# 8-bit saturation bounds, DN
_LO = np.float32(0.0)
_HI = np.float32(255.0)


@intrinsic
def fma32(typingctx, a, b, c):
    """``a * b + c`` in float32 with one rounding (LLVM's fma): what OpenCV's vector code computes
    for ``addWeighted`` (``v_fma``) on a CPU with FMA instructions."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.FloatType(), [ir.FloatType()] * 3)
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.fma.f32")
        return builder.call(fn, args)

    return sig, codegen


@njit(cache=True, nogil=True)
def _to_u8(v):
    """float32 DN to 8 bits as OpenCV's saturate_cast: nearest (ties to even), clamped to 0-255."""
    return np.uint8(np.int32(np.rint(min(max(v, _LO), _HI))))


@njit(cache=True, nogil=True)
def add_noise_u8(frame, bank, oy, ox, sigma, out):
    """``out = uint8(frame + sigma * z)`` with ``z = bank[oy:oy + H, ox:ox + W C]``.

    ``frame``: float32 ``(H, W C)`` DN; ``bank``: float32 standard normals (see the module's contract);
    ``sigma``: float32 DN (the product ``sigma z`` rounds to float32 before the sum, as
    ``cv2.addWeighted(frame, 1, z, sigma, 0)`` does); ``out``: uint8 ``(H, W C)``, written."""
    h, w = frame.shape
    for y in range(h):
        fr = frame[y]
        zr = bank[oy + y][ox:ox + w]     # a contiguous slice: the loop vectorises (an offset index gathers)
        o = out[y]
        for x in range(w):
            o[x] = _to_u8(fr[x] + zr[x] * sigma)


@njit(cache=True, nogil=True)
def add_shot_noise_u8(frame, bank, oy, ox, gain, read_var, out):
    """``out = uint8(frame + sqrt(max(gain * frame + read_var, 0)) * z)``, ``z`` as in :func:`add_noise_u8`.

    ``gain``: float32 shot-noise variance per DN of signal; ``read_var``: float32 DN^2. The variance
    rounds once (``fma``, as OpenCV's ``addWeighted(frame, gain, frame, 0, read_var)``), then the
    square root, the product with ``z`` and the sum each round to float32, as OpenCV's passes do."""
    h, w = frame.shape
    for y in range(h):
        fr = frame[y]
        zr = bank[oy + y][ox:ox + w]
        o = out[y]
        for x in range(w):
            f = fr[x]
            var = max(fma32(f, gain, read_var), _LO)   # a dark pixel below 0 DN has no shot noise
            o[x] = _to_u8(f + np.sqrt(var) * zr[x])


@njit(cache=True, nogil=True)
def quad_coverage_strip(lo, nx, ny, cc, out):
    """Coverage of convex quadrilaterals, one ``P x P`` patch each, side by side in ``out``.

    ``lo``: int64 ``(N, 2)`` (x, y) px of each patch's top-left pixel; ``nx, ny``: float32 ``(N, 4)`` the
    edges' inward unit normals; ``cc``: float32 ``(N, 4)`` each edge's offset plus half a pixel (so that
    ``nx x + ny y + cc`` is 0.5 plus the signed distance of pixel centre ``(x, y)`` inside the edge);
    ``out``: float32 ``(P, N P)``, written: patch ``i`` in columns ``i P:(i + 1) P``, its row ``r``,
    column ``j`` the pixel ``(lo[i, 0] + j, lo[i, 1] + r)``. Coverage is the product over the edges,
    in their order, of ``clip(nx x + ny y + cc, 0, 1)``, each product and sum rounded to float32 as
    numpy's broadcast expression in :func:`gelsim.optics.composite.coverage_strip` wrote it before."""
    p = out.shape[0]
    n = lo.shape[0]
    one = np.float32(1.0)
    for i in range(n):
        for r in range(p):
            y = np.float32(lo[i, 1] + r)
            o = out[r][i * p:(i + 1) * p]
            for j in range(p):
                x = np.float32(lo[i, 0] + j)
                v = one
                for k in range(4):
                    d = (nx[i, k] * x + ny[i, k] * y) + cc[i, k]
                    v *= min(max(d, _LO), one)
                o[j] = v


@njit(cache=True, nogil=True)
def multiply_patches_rows(rows, lo, factor, y_lo):
    """Multiply a frame's rows ``y_lo:y_lo + n`` (px), ``rows`` float32 ``(n, W, C)`` in place (the whole
    frame: ``y_lo`` 0), by patches of a factor, in patch order.

    ``lo``: int64 ``(N, 2)`` (x, y) px of each patch's top-left pixel; ``factor``: float32 ``(P, N P)``,
    patch ``i`` in columns ``i P:(i + 1) P`` (as :func:`quad_coverage_strip` lays them out), the same
    for every channel. Parts of a patch beyond the rows are skipped. The products are pixel by pixel
    those of a whole frame's pass, so a frame finished band by band (while its rows are in the
    cache) gets the same values."""
    n, w, c = rows.shape
    p = factor.shape[0]
    for i in range(lo.shape[0]):
        x0, y0 = lo[i, 0], lo[i, 1]
        ax, ay = max(x0, 0), max(y0, y_lo)
        bx, by = min(x0 + p, w), min(y0 + p, y_lo + n)
        for y in range(ay, by):
            f = factor[y - y0][i * p + ax - x0:i * p + bx - x0]
            row = rows[y - y_lo]
            for x in range(bx - ax):
                fx = f[x]
                for k in range(c):
                    row[ax + x, k] *= fx
