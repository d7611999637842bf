"""The camera's readout: noise, then 8-bit quantisation.

Noise: ``frame + sqrt(read_sigma^2 + shot_gain * frame) z`` with ``z`` a standard-normal field picked
from a bank drawn once (:class:`NoiseBank`: the same draws for both backends); quantisation: round to
nearest, ties to even, and saturate at 0 and 255 (OpenCV's conversion to 8 bits; no wrap-around).

numpy kernels: numba loops doing in one pass over memory what a chain of OpenCV calls did in several,
with the same float32 arithmetic in the same order, so that frames stay bit for bit those of the
OpenCV chain (checked against it in ``tests/gelsim/test_optics_kernels.py``): :func:`add_noise_u8` for
a constant sigma (one ``cv2.addWeighted(..., dtype=CV_8U)``), :func:`add_shot_noise_u8` with shot noise
(five OpenCV passes: addWeighted, max, sqrt, multiply, add). They are single-threaded (a dataset's
workers are one process per core), release the GIL, and take a frame as float32 ``(H, W * C)`` (an
``(H, W, C)`` frame's rows, C-contiguous), the bank as float32 ``(H + pad, (W + pad) * C)`` read at row
``oy`` and flat column ``ox`` (``C`` times the pixel column), and write uint8 ``(H, W * C)``. Numba
compiles them on first use (about a second, cached on disk afterwards). torch kernel: ``B`` frames.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from ...errors import GelsimError
from . import torch_module

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


def to_uint8_rows(rows: np.ndarray, out: np.ndarray, y0: int) -> None:
    """:func:`to_uint8` of a band of a frame: ``rows`` float32 ``(n, W, 3)`` DN, the frame's rows ``y0:y0 + n``,
    into the same rows of ``out`` (uint8 ``(H, W, 3)``)."""
    cv2.add(rows, (0.0, 0.0, 0.0, 0.0), out[y0:y0 + rows.shape[0]], dtype=cv2.CV_8U)


def to_uint8(frame: np.ndarray) -> np.ndarray:
    """Round and saturate float32 DN to uint8 (no wrap-around)."""
    if frame.ndim == 3 and frame.shape[2] <= 4:
        # cv2 rounds to nearest and saturates when converting to 8 bits
        return cv2.add(frame, (0.0, 0.0, 0.0, 0.0), dtype=cv2.CV_8U)
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


class NoiseBank:
    """Camera noise from a bank of pre-drawn standard-normal frames.

    Drawing 960x720x3 normals costs about 6 ms per frame; instead ``frames``
    frames are drawn once from the renderer's seed, each ``pad_px`` larger than
    the image, and a frame's noise is one of them at an offset chosen by the
    frame's seed (``frames * (pad_px + 1)^2`` distinct patterns). The standard
    normal is scaled per pixel by ``sqrt(read_sigma^2 + shot_gain * signal)``.
    """

    def __init__(self, shape: tuple[int, int], read_sigma_dn: float, shot_gain: float, seed: int,
                 frames: int = 4, pad_px: int = 48):
        h, w = shape
        self.shape = shape
        self.read_var = float(read_sigma_dn) ** 2
        self.shot_gain = float(shot_gain)
        self.pad = pad_px
        rng = np.random.default_rng([seed, 0x401])
        self.bank = [rng.standard_normal((h + pad_px, w + pad_px, 3), dtype=np.float32) for _ in range(frames)]

    @property
    def active(self) -> bool:
        return self.read_var > 0 or self.shot_gain > 0

    def offsets(self, seed: int | np.random.Generator) -> tuple[int, int, int]:
        """The draw for ``seed``: (bank frame, row offset, column offset) of its noise field (a Generator
        advances by this draw, as a frame of a sequence does)."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        k = int(rng.integers(len(self.bank)))
        oy, ox = (int(v) for v in rng.integers(self.pad + 1, size=2))
        return k, oy, ox

    def pick(self, seed: int | np.random.Generator) -> np.ndarray:
        """The standard-normal field for ``seed``: float32 ``(H, W, 3)`` view."""
        k, oy, ox = self.offsets(seed)
        h, w = self.shape
        return self.bank[k][oy:oy + h, ox:ox + w]

    def apply(self, frame: np.ndarray, seed: int | np.random.Generator) -> np.ndarray:
        """``frame`` (float32 ``(H, W, 3)`` DN, not modified) plus noise, as a new uint8 array.

        One fused pass reads the frame and the noise once: the same values as OpenCV's ``addWeighted``
        into 8 bits (constant sigma) or its five passes (shot noise), in a third (constant sigma) to a
        fifth (shot noise) of their time."""
        h, w = self.shape
        frame = np.ascontiguousarray(frame, dtype=np.float32)
        if frame.shape != (h, w, 3):
            raise GelsimError(f"frame has shape {frame.shape}; the noise bank is for {(h, w, 3)}")
        out = np.empty((h, w, 3), np.uint8)
        self.apply_rows(frame, self.offsets(seed), out, 0)
        return out

    def apply_rows(self, rows: np.ndarray, offsets: tuple[int, int, int], out: np.ndarray, y0: int) -> None:
        """:meth:`apply` on a band of a frame with the draw ``offsets`` (:meth:`offsets`): ``rows`` float32
        C-contiguous ``(n, W, 3)`` DN, the frame's rows ``y0:y0 + n``; ``out`` uint8 C-contiguous
        ``(H, W, 3)``, those rows written. Each pixel's value depends on that pixel alone, so a frame
        finished band by band, while its rows are in the cache, equals the whole frame's :meth:`apply`."""
        k, oy, ox = offsets
        h, w = self.shape
        n = rows.shape[0]
        bank = self.bank[k]
        flat, bank2 = rows.reshape(n, w * 3), bank.reshape(bank.shape[0], -1)
        dst = out.reshape(h, w * 3)[y0:y0 + n]
        if self.shot_gain == 0:
            # the scalars are float32, as OpenCV's vector code uses them
            add_noise_u8(flat, bank2, oy + y0, 3 * ox, np.float32(math.sqrt(self.read_var)), dst)
        else:
            add_shot_noise_u8(flat, bank2, oy + y0, 3 * ox, np.float32(self.shot_gain), np.float32(self.read_var), dst)

    def to_torch(self, device):
        """The bank as one float32 tensor ``(frames, 3, H + pad, W + pad)`` on ``device``."""
        torch = torch_module()
        return torch.tensor(np.stack(self.bank).transpose(0, 3, 1, 2), device=device)


# ---------------------------------------------------------------- torch

def readout_torch(frame, bank, noise: NoiseBank, offsets: list):
    """:meth:`NoiseBank.apply` (or :func:`to_uint8` for a frame whose offsets are None) of ``B`` frames
    ``(B, 3, H, W)`` DN: uint8 ``(B, H, W, 3)`` on their device. ``bank``: :meth:`NoiseBank.to_torch` (None
    when the noise is off); ``offsets``: each frame's :meth:`NoiseBank.offsets`, or None."""
    torch = torch_module()
    if bank is not None and any(o is not None for o in offsets):
        h, w = noise.shape
        # a noiseless frame in the batch reads any field and keeps its own value (torch.where below)
        z = torch.stack([bank[k, :, oy:oy + h, ox:ox + w] for k, oy, ox in
                         (o if o is not None else (0, 0, 0) for o in offsets)])
        has = torch.tensor([o is not None for o in offsets], device=frame.device)[:, None, None, None]
        if noise.shot_gain == 0:
            sigma = z * math.sqrt(noise.read_var)
        else:
            var = torch.clamp(frame * noise.shot_gain + noise.read_var, min=0.0)   # below 0 DN: no shot noise
            sigma = torch.sqrt(var) * z
        frame = torch.where(has, frame + sigma, frame)
    out = torch.clamp(torch.round(frame), 0.0, 255.0).to(torch.uint8)
    return out.permute(0, 2, 3, 1).contiguous()
