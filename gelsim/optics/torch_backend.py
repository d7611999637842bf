"""The ``torch`` optics backend: the fast backend's optics in PyTorch, batched over frames, on any device.

What it renders is the ``fast`` backend's frame: the same shading (the calibrated table of a
``[shading] model = "lut"`` profile with its soft LED shadows and its depth and halo terms, or
Lambert + Phong from the profile's lights), the same camera blur, the same anti-aliased markers, the
same camera noise (drawn from the same :class:`~gelsim.optics.composite.NoiseBank` with the same
per-frame draws) and the same quantisation, for ``B`` frames at once as ``(B, H, W)`` tensors on
``cpu`` or ``cuda``. The tables, light maps, background and noise bank are built once by the numpy
code (:class:`~gelsim.optics.lut.LutShader`, :class:`~gelsim.optics.fast.FastShader`,
:class:`~gelsim.optics.Renderer`) and copied to the device; only the per-frame work runs here.

Two ways in:

* ``Renderer(profile, "torch", device=...)``: one frame at a time through the
  :class:`~gelsim.optics.shader.Shader` contract (:class:`TorchShader`: its shading on the device,
  markers and noise by the Renderer's numpy compositing);
* :class:`BatchRenderer` (over such a Renderer): ``B`` frames at once, markers and noise on the
  device too; :class:`gelsim.sinks.DeviceFrames` feeds it a sequence's frame records, as the
  dataset does (``gelsim generate --backend torch --device cuda``).

Agreement with ``fast`` (stated tolerance, :data:`TOL_MEAN_DN` and :data:`TOL_MAX_DN`, tested in
``tests/gelsim/test_torch_backend.py``): the noiseless float frames differ by operation order at
float32 rounding, and where the LED shadows are drawn, because the fast backend computes them on a
half-resolution grid aligned with the imprint's box and this backend on one aligned with the frame.

Same bytes for any batch size, and on any device: a frame's pixels come from element-wise IEEE
operations (add, multiply, divide, square root, min/max: correctly rounded everywhere), exact copies
(gathers, padding, slicing) and order-free reductions (max) only, each over one frame. Filters are
written as sums of shifted slices in a fixed order rather than convolutions, whose algorithm (and
summation order) a library may choose by the batch's shape; powers (Phong's highlight) are taken in
float64 and rounded to float32. Nothing here draws random numbers: the noise offsets are drawn by
the caller's numpy generator in the order the numpy renderer draws them.
"""
from __future__ import annotations

import math
import os

import cv2
import numpy as np

from ..errors import GelsimError
from .composite import blur_radius_px, marker_corners
from .fast import FastShader
from .lut import COARSE_SKIP_DN, SHADOW_SCALE, LutShader, _grid_factor, coarse_factor
from .shader import Shader

#: Stated agreement of this backend with ``fast``, noiseless float frames, DN (0-255): mean and largest
#: absolute difference per pixel and channel. Measured (with markers, on the CPU) at 320x240 and 960x720 on
#: a sphere, a steep sphere with shadows, a weave and two catalog fabrics pressed at 3 N, with the
#: calibrated table and with Phong shading: mean at most 0.0003 DN; largest 0.32 DN where a sphere's
#: shadows fall at 320x240 (the two grids above), 0.001 DN elsewhere. The margin keeps the test meaningful
#: under float32-level changes of either backend; 1 DN is one 8-bit step.
TOL_MEAN_DN = 0.02
TOL_MAX_DN = 1.0
#: The same for uint8 frames with the same noise: a float difference can move a pixel across one more
#: rounding step (measured: at most 1 DN, at 0.03% of the pixels).
TOL_MAX_UINT8_DN = 2

#: Frames rendered at once by default (``--batch``): at 960x720 a batch of 16 is about 0.6 GB of work
#: arrays on the device; the result does not depend on it.
DEFAULT_BATCH = 16


def _torch():
    """The torch module, or one line saying how to get it."""
    try:
        import torch
    except ImportError:  # torch is installed by `make install`; a bare `pip install gelsim` lacks it
        raise GelsimError("the torch backend needs PyTorch; install it (make install, or pip install torch)") from None
    return torch


def resolve_device(name: str | None = None):
    """The ``torch.device`` for ``--device`` ``name`` (``cpu``, ``cuda`` or ``cuda:N``; None: ``cpu``), or a
    one-line GelsimError when this machine has no such device."""
    torch = _torch()
    text = "cpu" if name is None else str(name)
    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise GelsimError(f"--device {text!r} is not a device; give cpu or cuda (or cuda:N)") from None
    if dev.type == "cpu":
        return dev
    if dev.type != "cuda":
        raise GelsimError(f"--device {text!r} is not supported; give cpu or cuda (or cuda:N)")
    # Ask NVML rather than the CUDA driver, which would be initialised in this process by the question:
    # `gelsim generate` forks its workers from it, and a forked child cannot use a parent's CUDA.
    os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
    if not torch.cuda.is_available():
        build = "built without CUDA" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no GPU visible"
        raise GelsimError(f"--device {text}: no CUDA device on this machine (torch {torch.__version__}, {build}); "
                          "use --device cpu")
    if dev.index is not None and dev.index >= torch.cuda.device_count():
        raise GelsimError(f"--device {text}: this machine has {torch.cuda.device_count()} CUDA device(s); "
                          "give cuda:0 or another index below that")
    return dev


# ---------------------------------------------------------------- filters (fixed order, element-wise)

def cv_gaussian_taps(sigma_px: float, ksize: int | None = None) -> list[float]:
    """The float32 taps OpenCV's GaussianBlur uses for ``sigma_px`` on float images (``ksize`` None: its
    own choice for a zero size, ``round(8 sigma + 1) | 1``)."""
    if ksize is None:
        ksize = int(round(sigma_px * 8 + 1)) | 1
    return [float(v) for v in cv2.getGaussianKernel(ksize, sigma_px, cv2.CV_32F).ravel()]


def _shifted_sum(x, taps: list[float], dim: int, border: str):
    """``sum_i taps[i] x[.. j + i - r ..]`` along ``dim`` (-2: down the rows, -1: along them, of an
    ``(..., H, W)`` tensor), the border ``"replicate"`` or ``"constant"`` (zero). A multiply and an add
    per tap, in tap order, as separate operations (no fused multiply-add)."""
    torch = _torch()
    r = (len(taps) - 1) // 2
    if r == 0:
        return x * taps[0]
    n = x.shape[dim]
    h, w = x.shape[-2:]
    pad = (r, r, 0, 0) if dim in (-1, x.dim() - 1) else (0, 0, r, r)
    xp = torch.nn.functional.pad(x.reshape(-1, 1, h, w), pad, mode=border)   # exact copies
    xp = xp.reshape(*x.shape[:-2], *xp.shape[-2:])
    out = xp.narrow(dim, 0, n) * taps[0]
    tmp = torch.empty_like(out)
    for i in range(1, len(taps)):
        if taps[i] == 0.0:
            continue                      # (a Sobel's middle tap: adding 0 x would change nothing)
        out += torch.mul(xp.narrow(dim, i, n), taps[i], out=tmp)
    return out


def gaussian(x, sigma_px: float, ksize: int | None = None, border: str = "replicate"):
    """Separable Gaussian blur of an ``(..., H, W)`` tensor, along the rows first (OpenCV's order)."""
    if sigma_px <= 0:
        return x
    taps = cv_gaussian_taps(sigma_px, ksize)
    return _shifted_sum(_shifted_sum(x, taps, -1, border), taps, -2, border)


def camera_blur(x, sigma_px: float):
    """The camera blur of :func:`gelsim.optics.composite.gaussian_blur` (kernel +-3 sigma, replicated
    borders) on an ``(..., H, W)`` tensor."""
    if sigma_px <= 0:
        return x
    return gaussian(x, sigma_px, 2 * blur_radius_px(sigma_px) + 1)


def sobel(d, scale: float):
    """3x3 Sobel slopes ``(gx, gy)`` of ``(..., H, W)`` ``d`` times ``scale``, replicated borders (cv2.Sobel)."""
    dx = _shifted_sum(_shifted_sum(d, [-1.0, 0.0, 1.0], -1, "replicate"), [1.0, 2.0, 1.0], -2, "replicate")
    dy = _shifted_sum(_shifted_sum(d, [1.0, 2.0, 1.0], -1, "replicate"), [-1.0, 0.0, 1.0], -2, "replicate")
    return dx * scale, dy * scale


def block_mean(x, f: int):
    """Mean over ``f`` x ``f`` blocks of ``(..., H, W)`` ``x``, zero-padded at the bottom and right to a
    multiple of ``f`` (:func:`gelsim.optics.lut._grid_heights`; OpenCV's INTER_AREA by a whole factor)."""
    if f == 1:
        return x
    torch = _torch()
    h, w = x.shape[-2:]
    hs, ws = -(-h // f), -(-w // f)
    if (hs * f, ws * f) != (h, w):
        x = torch.nn.functional.pad(x, (0, ws * f - w, 0, hs * f - h))
    acc = None
    for i in range(f):
        for j in range(f):
            s = x[..., i::f, j::f]
            acc = s if acc is None else acc + s
    return acc * (1.0 / (f * f))


def upsample(x, f: int, shape: tuple[int, int]):
    """Bilinear from a grid of ``f``-pixel blocks to ``shape`` (H, W) (cv2.resize INTER_LINEAR by ``f``, then
    cropped): ``(..., h, w)`` -> ``(..., H, W)``."""
    if f == 1:
        return x[..., :shape[0], :shape[1]]
    for dim, n in ((-1, shape[1]), (-2, shape[0])):     # along the rows first, as OpenCV
        x = _linear_axis(x, f, n, dim)
    return x


def _linear_axis(x, f: int, n: int, dim: int):
    """One axis of :func:`upsample`: fine pixel ``i`` reads coarse ``(i + 1/2) / f - 1/2``, clamped to the
    first and last coarse pixel (which are then read alone, with weight 1). Computed per phase ``i mod
    f``, whose two neighbours and weights are the same all along the axis."""
    torch = _torch()
    m = x.shape[dim]
    h, w = x.shape[-2:]
    pad = (1, 1, 0, 0) if dim in (-1, x.dim() - 1) else (0, 0, 1, 1)
    xp = torch.nn.functional.pad(x.reshape(-1, 1, h, w), pad, mode="replicate")
    xp = xp.reshape(*x.shape[:-2], *xp.shape[-2:])          # xp[j + 1] = x[j], replicated at both ends
    shape = list(x.shape)
    shape[dim] = m * f
    out = x.new_empty(shape)
    for r in range(f):
        t = (r + 0.5) / f - 0.5                              # the phase's offset from its coarse pixel
        lo, w1 = (1, t) if t >= 0 else (0, 1.0 + t)          # read pixels j and j + 1, or j - 1 and j
        w0 = float(np.float32(1.0 - w1))
        w1 = float(np.float32(w1))
        dst = out.narrow(dim, r, m * f - r)[(slice(None),) * (dim % x.dim()) + (slice(None, None, f),)]
        dst.copy_(xp.narrow(dim, lo, m) * w0 + xp.narrow(dim, lo + 1, m) * w1)
    first = int(math.ceil((f - 1) / 2.0))                    # fine pixels left of coarse pixel 0's centre
    if first:
        out.narrow(dim, 0, first).copy_(x.narrow(dim, 0, 1).expand_as(out.narrow(dim, 0, first)))
    last = int(math.ceil((m - 0.5) * f - 0.5))               # from here on, right of the last one's centre
    if last < m * f:
        tail = out.narrow(dim, last, m * f - last)
        tail.copy_(x.narrow(dim, m - 1, 1).expand_as(tail))
    return out.narrow(dim, 0, n)


def box_mask(pos, margin: int):
    """``(B, 1, H, W)`` bool: each frame's bounding box of ``pos`` (bool ``(B, H, W)``) grown by ``margin`` px
    (empty for a frame without any true pixel): where the fast backend shades."""
    torch = _torch()
    out = []
    for dim in (2, 1):                       # rows (any over columns), then columns (any over rows)
        hit = pos.any(dim=dim)               # (B, n)
        n = hit.shape[1]
        ar = torch.arange(n, device=pos.device)
        big = torch.full_like(ar, n)
        first = torch.where(hit, ar, big).amin(dim=1, keepdim=True)
        last = torch.where(hit, ar, -big).amax(dim=1, keepdim=True)
        out.append((ar >= first - margin) & (ar <= last + margin))
    rows, cols = out
    return (rows[:, :, None] & cols[:, None, :])[:, None]


def mix_channels(maps: list, matrix: np.ndarray):
    """Per-pixel colour mix ``out[:, c] = sum_k maps[k] * matrix[k, c]``, summed in ``k`` order: ``(B, C, h, w)``
    from ``K`` maps ``(B, h, w)`` and a ``(K, C)`` matrix (cv2.transform's, written out)."""
    torch = _torch()
    out = []
    for c in range(matrix.shape[1]):
        acc = maps[0] * float(matrix[0, c])
        for k in range(1, len(maps)):
            acc = acc + maps[k] * float(matrix[k, c])
        out.append(acc)
    return torch.stack(out, dim=1)


# ---------------------------------------------------------------- the shader

class TorchShader(Shader):
    """The fast backend's shading in torch (see the module docstring).

    ``profile``: sensor profile at the resolution being shaded; ``maps``: its light maps;
    ``device``: where to compute (``--device``; default the CPU). :meth:`shade` is the batched form.
    """

    name = "torch"

    def __init__(self, profile, maps, device=None):
        torch = _torch()
        self.profile = profile
        self.device = resolve_device(device) if not hasattr(device, "type") else device
        self.mm = float(profile.image.mm_per_px)
        h, w = profile.shape

        def t(a):
            return torch.tensor(np.asarray(a, np.float32), device=self.device)

        self.lut = profile.shading.model == "lut"
        if self.lut:
            cpu = LutShader(profile)          # the table as the fast backend reads and adjusts it
            self.margin_px = cpu.margin_px
            self._mosaic = t(cpu._mosaic.transpose(2, 0, 1))[None]      # (1, 3, Hm, Wm)
            self._mosaic_hw = cpu._mosaic.shape[:2]
            self._offx = t(cpu._offx[0])
            self._offy = t(cpu._offy[:, 0])
            self._half = (cpu.nb - 1) / 2.0
            self.shadow = cpu.shadow
            self._shadow_rgb = None if cpu.shadow is None else cpu.shadow["shadow_rgb"].astype(np.float32)
            self.depth_term, self.halo = cpu.depth_term, cpu.halo
            self._coarse_mix = cpu._coarse_mix
            if self.depth_term:
                f = coarse_factor(self.mm)
                hs, ws = -(-h // f), -(-w // f)
                fw, fh = profile.field_mm
                # grid pixel x' is centred on full-resolution f (x' + 1/2) - 1/2 (lut.coarse_grid)
                self._xn = t(((f * (np.arange(ws) + 0.5) - 0.5 - (w - 1) / 2.0) * self.mm / (fw / 2.0))[None, :])
                self._yn = t(((f * (np.arange(hs) + 0.5) - 0.5 - (h - 1) / 2.0) * self.mm / (fh / 2.0))[:, None])
        else:
            cpu = FastShader(profile, maps)
            self.margin_px = cpu.margin_px
            sh = profile.shading
            self._spec = sh.specular > 0
            self._shininess = float(sh.shininess)
            self._lights = [(t(m.lx), t(m.ly), t(m.lz), t(kd), t(ks), t(flat))
                            for m, kd, ks, flat in zip(maps, cpu._kd, cpu._ks, cpu._flat)]
            self._color = cpu.color_matrix.astype(np.float32)          # (3 colours, lights)

    # ------------------------------------------------------------ batched

    def shade(self, depth, blur_sigma_px: float, margin_px: int | None = None):
        """The shading change of ``B`` imprints: float32 ``(B, 3, H, W)`` DN from ``depth`` float32
        ``(B, H, W)`` mm (>= 0) on this shader's device (the sum of :meth:`shade_parts`)."""
        parts = self.shade_parts(depth, blur_sigma_px, margin_px)
        out = parts[0]
        for p in parts[1:]:
            out = out + p
        return out

    def shade_parts(self, depth, blur_sigma_px: float, margin_px: int | None = None) -> list:
        """The change as the fast backend adds it to the background, in its order: the part the camera
        blurs, blurred by ``blur_sigma_px`` (0: not at all) and kept to the box the fast backend shades
        (the imprint's box grown by ``margin_px``, default the blur's reach); then, with a table, the
        shadows (blurred by the camera too) and the depth and halo terms. Each ``(B, 3, H, W)`` DN."""
        if margin_px is None:
            margin_px = blur_radius_px(blur_sigma_px)
        pos = depth > 0
        sharp = self._lut_change(depth) if self.lut else self._phong_change(depth, pos)
        sharp = camera_blur(sharp, blur_sigma_px)
        keep = box_mask(pos, self.margin_px + margin_px)
        out = [sharp * keep]
        if self.lut and self.shadow is not None:
            out.append(self._shadows(depth, blur_sigma_px))
        if self.lut and self._coarse_mix is not None:
            out.append(self._coarse(depth))
        return out

    def _lut_change(self, d):
        """The table's change (:meth:`LutShader._shade_band`): bilinear in the tile mosaic at the normal's bin."""
        torch = _torch()
        gx, gy = sobel(d, 1.0 / (8.0 * self.mm))
        k = 1.0 / torch.sqrt(gx * gx + gy * gy + 1.0)
        mx = gx * k * (-self._half) + self._offx[None, :]
        my = gy * k * (-self._half) + self._offy[:, None]
        return self._bilinear(mx, my)

    def _bilinear(self, mx, my):
        """cv2.remap INTER_LINEAR of the mosaic at float pixel coordinates ``mx, my`` (``(B, H, W)``),
        replicated borders: ``(B, 3, H, W)``. The frames are looked up as one tall image (one output pixel
        depends on its own coordinates only, whatever the batch)."""
        torch = _torch()
        hm, wm = self._mosaic_hw
        b, h, w = mx.shape
        grid = torch.stack([mx * (2.0 / (wm - 1)) - 1.0, my * (2.0 / (hm - 1)) - 1.0], dim=-1)
        out = torch.nn.functional.grid_sample(self._mosaic, grid.reshape(1, b * h, w, 2), mode="bilinear",
                                              padding_mode="border", align_corners=True)
        return out.reshape(3, b, h, w).transpose(0, 1)

    def _phong_change(self, d, pos):
        """Lambert + Phong under the lights less the flat gel's (:meth:`FastShader.delta`), where the
        slope stencil reaches an imprinted pixel (zero elsewhere, as outside the fast backend's box)."""
        torch = _torch()
        gx, gy = sobel(d, 1.0 / (8.0 * self.mm))
        nz = 1.0 / torch.sqrt(gx * gx + gy * gy + 1.0)
        near = torch.nn.functional.max_pool2d(pos[:, None].float(), 3, 1, 1)[:, 0] > 0
        dls = []
        for lx, ly, lz, kd, ks, flat in self._lights:
            ndl = (lz - gx * lx - gy * ly) * nz
            dl = torch.clamp(ndl, min=0.0) * kd
            if self._spec:
                r = torch.clamp(ndl * (nz * 2.0) - lz, min=0.0)
                # float64 power rounded to float32: the same value whichever kernel computes it
                dl = dl + (r.double() ** self._shininess).float() * ks
            dls.append(torch.where(near, dl - flat, 0.0))
        return mix_channels(dls, self._color.T)

    def _shadows(self, d, blur_sigma_px: float):
        """The LED shadows (:meth:`LutShader._shadows`), blurred by their penumbra and the camera:
        ``(B, 3, H, W)`` DN, computed on the frame's half-resolution grid."""
        torch = _torch()
        s = self.shadow
        factor = _grid_factor(SHADOW_SCALE)
        hg = block_mean(d, factor)                                   # (B, hs, ws)
        hi = float(hg.amax())
        lo = min(float(hg.amin()), 0.0)
        sat = float(s["shadow_sat_mm"])
        # largest step between neighbours per frame (lut.grid_slopes): a direction along which no frame
        # climbs as steeply as the grazing ray casts no shadow (exactly zero; lut.occlusion_grid)
        sx = (hg[:, :, 1:] - hg[:, :, :-1]).abs().amax(dim=(1, 2))
        sy = (hg[:, 1:] - hg[:, :-1]).abs().amax(dim=(1, 2))
        chans = []
        for phi, tan_e in zip(s["shadow_dirs_deg"], s["shadow_tan"]):
            rise = float(tan_e) * self.mm * factor
            ux, uy = abs(math.cos(math.radians(phi))), abs(math.sin(math.radians(phi)))
            casts = (sx * ux + sy * uy) >= rise                       # per frame, as the fast backend decides
            if not bool(casts.any()):
                chans.append(torch.zeros_like(hg))
                continue
            occ = _occlusion(hg, float(phi), rise, hi - lo)
            chans.append(torch.where(casts[:, None, None], occ / (occ + sat), 0.0))
        small = mix_channels(chans, self._shadow_rgb)                # (B, 3, hs, ws)
        sigma = math.hypot(s["shadow_soft_mm"] / self.mm, blur_sigma_px) / factor
        if sigma > 0.3:     # as the fast backend: below a third of a grid pixel a blur changes nothing visible
            small = gaussian(small, sigma, border="constant")
        return upsample(small, factor, tuple(d.shape[1:]))

    def _coarse(self, d):
        """The depth and halo terms (:func:`gelsim.optics.lut.coarse_grid`), skipped per frame where no
        pixel changes by COARSE_SKIP_DN: ``(B, 3, H, W)`` DN."""
        torch = _torch()
        f = coarse_factor(self.mm)
        hg = block_mean(d, f)
        gmm = self.mm * f
        feats = []
        if self.depth_term:
            feats += [hg, hg * self._xn, hg * self._yn]
        if self.halo is not None:
            halo = self.halo
            b = gaussian(hg, halo["halo_sigma_mm"] / gmm)
            b0 = gaussian(hg, halo["halo_base_mm"] / gmm)
            sp = torch.clamp(b - b0, min=0.0)
            gate = torch.clamp(sp * (1.0 / halo["halo_gate_mm"]), max=1.0)
            gx, gy = sobel(b, 1.0 / (8.0 * gmm))
            feats += [gx * gate, gy * gate, sp]
        small = mix_channels(feats, self._coarse_mix)                 # (B, 3, hs, ws)
        seen = small.abs().amax(dim=(1, 2, 3)) >= COARSE_SKIP_DN      # per frame
        small = small * seen[:, None, None, None]
        return upsample(small, f, tuple(d.shape[1:]))

    # ------------------------------------------------------------ the Shader contract (one numpy frame)

    def _one(self, depth_mm: np.ndarray, blur_sigma_px: float, margin_px: int) -> np.ndarray | None:
        torch = _torch()
        if not np.any(depth_mm > 0):
            return None
        d = torch.as_tensor(np.ascontiguousarray(depth_mm, np.float32), device=self.device)[None]
        return np.ascontiguousarray(self.shade(d, blur_sigma_px, margin_px)[0].permute(1, 2, 0).cpu().numpy())

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, change)``: the whole frame and its float32 ``(H, W, 3)`` DN change, not blurred by the
        camera (shadows by their penumbra only); None for a flat gel."""
        change = self._one(depth_mm, 0.0, margin_px)
        if change is None:
            return None
        h, w = depth_mm.shape
        return (slice(0, h), slice(0, w)), change

    def parts(self, depth_mm: np.ndarray, margin_px: int, blur_sigma_px: float):
        """One part, the whole frame's change with the camera blur applied (so the Renderer adds it as it
        is); None for a flat gel."""
        change = self._one(depth_mm, blur_sigma_px, margin_px)
        if change is None:
            return None
        h, w = depth_mm.shape
        return [((slice(0, h), slice(0, w)), change, True)]


def _occlusion(hg, dir_deg: float, rise: float, span_mm: float):
    """:func:`gelsim.optics.lut.occlusion_grid` for a batch ``(B, h, w)`` of grids: the surface towards the
    light above the grazing ray, mm. ``span_mm``: the batch's largest height range (max - min(min, 0));
    frames of a smaller range run passes past their own reach, which cannot raise their result (every
    window they add lies below the surface it is compared with, by at least one ``rise``)."""
    torch = _torch()
    b, h, w = hg.shape
    reach = min(span_mm / rise if rise > 0 else math.hypot(h, w), math.hypot(h, w))
    if reach < 1.0:
        return torch.zeros_like(hg)
    ux, uy = math.cos(math.radians(dir_deg)), math.sin(math.radians(dir_deg))
    pad = int(math.ceil(reach)) + 2
    buf = hg.new_zeros((b, h + 2 * pad, w + 2 * pad))

    def shifted(src, vx, vy, minus):
        """``src(p + v) - minus`` bilinearly (:func:`gelsim.optics.lut._bilinear_shift`)."""
        ix, iy = math.floor(vx), math.floor(vy)
        fx, fy = vx - ix, vy - iy
        y0, x0 = pad + iy, pad + ix

        def view(dy, dx):
            return src[:, y0 + dy:y0 + dy + h, x0 + dx:x0 + dx + w]

        a = view(0, 0) * ((1 - fx) * (1 - fy)) + view(0, 1) * (fx * (1 - fy)) - minus
        if fy > 0:
            a = a + (view(1, 0) * ((1 - fx) * fy) + view(1, 1) * (fx * fy))
        return a

    buf[:, pad:pad + h, pad:pad + w] = hg
    m = shifted(buf, ux, uy, rise)                                   # window s = 1
    cover = 1
    while cover < reach:
        buf[:, pad:pad + h, pad:pad + w] = m                         # the border stays 0
        m = torch.maximum(m, shifted(buf, cover * ux, cover * uy, cover * rise))
        cover *= 2
    return torch.clamp(m - hg, min=0.0)


# ---------------------------------------------------------------- whole frames, B at a time

class BatchRenderer:
    """``B`` frames at once through ``renderer`` (a :class:`~gelsim.optics.Renderer` made with backend
    ``"torch"``): its background, shader and noise bank, with the markers, the supersampling's
    average, the noise and the quantisation on the shader's device.

    Inputs per frame as :meth:`Renderer.render` takes them: the imprint float32 ``(H, W)`` mm or None,
    the markers (an object with ``.corners_px``, an ``(N, 4, 2)`` array, or None) and the noise seed (an
    int or the sequence's numpy Generator, drawn from exactly as the numpy renderer draws)."""

    def __init__(self, renderer):
        torch = _torch()
        if not isinstance(getattr(renderer, "_shader", None), TorchShader):
            raise GelsimError("BatchRenderer needs a Renderer made with backend 'torch'")
        self.renderer = renderer
        self.shader: TorchShader = renderer._shader
        self.device = self.shader.device
        self.profile = renderer.profile
        self.shape = renderer.profile.shape
        self.s = renderer.supersample
        self._blur = renderer._blur_fine
        self._margin = blur_radius_px(self._blur)
        self._bg = torch.tensor(renderer._bg_fine.transpose(2, 0, 1), device=self.device)   # (3, H, W)
        mk = renderer.profile.markers
        self._markers = mk.enabled
        self._darkness = float(mk.darkness)
        noise = renderer._noise
        self._noise = noise
        self._bank = torch.tensor(np.stack(noise.bank).transpose(0, 3, 1, 2), device=self.device) \
            if noise.active else None                                 # (frames, 3, H + pad, W + pad)
        self._pinned = self.device.type == "cuda"

    # ------------------------------------------------------------ inputs

    def draw(self, seed, noise: bool = True):
        """This frame's noise offsets ``(bank frame, row, column)`` drawn from ``seed`` as the numpy
        renderer draws them (None without noise)."""
        if not (noise and self._noise.active):
            return None
        return self._noise.offsets(seed)

    def stage(self, depths: list, markers: list):
        """Host arrays of a batch: depth float32 ``(B, H, W)`` (zeros for None) and corners float32
        ``(B, N, 4, 2)`` (None without markers), validated as the numpy renderer validates them."""
        from . import check_depth

        h, w = self.shape
        depth = np.zeros((len(depths), h, w), np.float32)
        for i, d in enumerate(depths):
            d = check_depth(d, self.shape)
            if d is not None:
                depth[i] = d
        corners = None
        if self._markers:
            cs = [marker_corners(m) for m in markers]
            n = max((0 if c is None else len(c)) for c in cs)
            if n:
                # a frame without markers gets them far off the image, where they draw nothing
                off = np.float32(-1e6)
                corners = np.stack([np.full((n, 4, 2), off, np.float32) if c is None else c for c in cs])
                if any(c is not None and len(c) != n for c in cs):
                    raise GelsimError("frames of one batch have different numbers of markers; render them apart")
        return depth, corners

    # ------------------------------------------------------------ rendering

    def _to_device(self, a):
        torch = _torch()
        t = torch.from_numpy(a)
        if self._pinned:
            t = t.pin_memory()
        return t.to(self.device, non_blocking=self._pinned)

    def compose(self, depth: np.ndarray, corners: np.ndarray | None):
        """The noiseless float frames ``(B, 3, H, W)`` DN on the device, from :meth:`stage`'s arrays."""
        d = self._to_device(depth)
        s = self.s
        if s > 1:
            d = upsample(d, s, (d.shape[1] * s, d.shape[2] * s))
        frame = self._bg[None]
        for part in self.shader.shade_parts(d, self._blur, self._margin):
            frame = frame + part
        if corners is not None:
            c = self._to_device(corners)
            if s > 1:
                c = (c + 0.5) * s - 0.5                # pixel centres at integers at both resolutions
            frame = frame * marker_factor(c, tuple(frame.shape[-2:]), self._darkness, self._blur)[:, None]
        if s > 1:
            frame = block_mean(frame, s)
        return frame

    def quantise(self, frame, offsets: list):
        """``frame`` (:meth:`compose`) plus each frame's noise (``offsets``: :meth:`draw`'s, None for a
        noiseless frame), rounded half to even and saturated: uint8 ``(B, H, W, 3)`` RGB on the device."""
        torch = _torch()
        if self._bank is not None and any(o is not None for o in offsets):
            h, w = self.shape
            # a noiseless frame in the batch reads any field and keeps its own value (torch.where below)
            z = torch.stack([self._bank[k, :, oy:oy + h, ox:ox + w] for k, oy, ox in
                             (o if o is not None else (0, 0, 0) for o in offsets)])
            has = torch.tensor([o is not None for o in offsets], device=self.device)[:, None, None, None]
            read_var, gain = self._noise.read_var, self._noise.shot_gain
            if gain == 0:
                sigma = z * math.sqrt(read_var)
            else:
                var = torch.clamp(frame * gain + read_var, min=0.0)   # a pixel below 0 DN has no shot noise
                sigma = torch.sqrt(var) * z
            frame = torch.where(has, frame + sigma, frame)
        out = torch.clamp(torch.round(frame), 0.0, 255.0).to(torch.uint8)
        return out.permute(0, 2, 3, 1).contiguous()

    def render(self, depths: list, markers: list | None = None, seeds: list | None = None, *,
               noise: bool = True) -> np.ndarray:
        """uint8 ``(B, H, W, 3)`` RGB: the frames :meth:`Renderer.render` gives for the same inputs (within
        the stated tolerance); ``seeds`` one per frame (default 0)."""
        n = len(depths)
        markers = markers if markers is not None else [None] * n
        seeds = seeds if seeds is not None else [0] * n
        offsets = [self.draw(s, noise) for s in seeds]
        depth, corners = self.stage(depths, markers)
        return self.quantise(self.compose(depth, corners), offsets).cpu().numpy()

    def render_float(self, depths: list, markers: list | None = None) -> np.ndarray:
        """Noiseless, unquantised frames: float32 ``(B, H, W, 3)`` DN (as :meth:`Renderer.render_float`)."""
        markers = markers if markers is not None else [None] * len(depths)
        return np.ascontiguousarray(self.compose(*self.stage(depths, markers)).permute(0, 2, 3, 1).cpu().numpy())


def marker_factor(corners, shape: tuple[int, int], darkness: float, blur_sigma_px: float):
    """``1 - darkness * blur(coverage)`` of the markers (:func:`gelsim.optics.composite.darken_markers`) as
    a ``(B, H, W)`` factor, from corners float32 ``(B, N, 4, 2)`` (x, y) px. Each marker's coverage is
    computed on its own patch (:func:`gelsim.optics.composite.coverage_strip`), blurred there, and
    multiplied into the frame's factor; patches beyond the frame draw nothing."""
    torch = _torch()
    b, n = corners.shape[:2]
    h, w = shape
    radius = blur_radius_px(blur_sigma_px)
    pad = radius + 1
    cmin = corners.amin(dim=2)                                        # (B, N, 2)
    cmax = corners.amax(dim=2)
    lo = torch.floor(cmin).long() - pad                               # (B, N, 2) patch origin
    # the same patch size for every marker of the batch: a larger patch only adds zero coverage
    size = int(torch.ceil(cmax - cmin).amax()) + 2 * pad + 2
    grid = torch.arange(size, device=corners.device)
    xs = (lo[..., 0:1] + grid).float()[:, :, None, :]                 # (B, N, 1, P)
    ys = (lo[..., 1:2] + grid).float()[:, :, :, None]                 # (B, N, P, 1)
    v0 = corners
    v1 = torch.roll(corners, -1, dims=2)
    ex, ey = v1[..., 0] - v0[..., 0], v1[..., 1] - v0[..., 1]         # (B, N, 4)
    prod = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    area2 = ((prod[..., 0] + prod[..., 1]) + prod[..., 2]) + prod[..., 3]
    sign = torch.where(area2 >= 0, 1.0, -1.0)[..., None]
    length = torch.clamp(torch.sqrt(ex * ex + ey * ey), min=1e-6)
    nx, ny = -ey * sign / length, ex * sign / length
    c = -(nx * v0[..., 0] + ny * v0[..., 1])
    cov = None
    for k in range(4):
        d = nx[..., k, None, None] * xs + ny[..., k, None, None] * ys
        d = torch.clamp(d + (c[..., k] + 0.5)[..., None, None], 0.0, 1.0)
        cov = d if cov is None else cov * d
    cov = cov.reshape(b * n, size, size)
    if radius:
        cov = camera_blur(cov, blur_sigma_px)
    fac = (cov * (-darkness) + 1.0).reshape(b, n, size, size)
    # scatter the patches into the frame's factor by product: a pixel outside a marker's blurred
    # square multiplies by exactly 1, so overlapping zero borders leave it as it is
    py = lo[..., 1, None, None] + grid[:, None]                       # (B, N, P, 1)
    px = lo[..., 0, None, None] + grid[None, :]                       # (B, N, 1, P)
    inside = (py >= 0) & (py < h) & (px >= 0) & (px < w)
    frame_of = torch.arange(b, device=corners.device)[:, None, None, None]
    idx = torch.where(inside, (frame_of * h + py) * w + px, b * h * w)  # b*h*w: a slot that is thrown away
    out = torch.ones(b * h * w + 1, device=corners.device)
    out.scatter_reduce_(0, idx.reshape(-1), fac.reshape(-1), reduce="prod")
    return out[:-1].reshape(b, h, w)
