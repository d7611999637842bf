"""The ``torch`` optics backend: the fast backend's optics in PyTorch, batched over frames, on any device.

What it renders is the ``fast`` backend's frame, through the same composition
(:mod:`gelsim.optics.composite`): the same shading (the calibrated table of a ``[shading] model =
"lut"`` profile with its soft LED shadows and its depth and halo terms, or Lambert + Phong from the
profile's lights), the same camera blur, markers, supersampling's average, camera noise (drawn from
the same :class:`~gelsim.optics.ops.readout.NoiseBank` with the same per-frame draws) and
quantisation, for ``B`` frames at once as ``(B, ..., H, W)`` tensors on ``cpu`` or ``cuda``. Every
primitive is the torch kernel beside its numpy twin in :mod:`gelsim.optics.ops`; the inputs (light
maps, tables, background, noise bank) are the public ones every backend builds from a profile
(:class:`~gelsim.optics.composite.Optics`, :func:`~gelsim.optics.ops.phong.phong_lights`,
:func:`~gelsim.optics.lut.table_model`), copied to the device once.

Two ways in:

* ``Renderer(profile, "torch", device=...)``: one frame at a time through the
  :class:`~gelsim.optics.shader.Shader` contract (:class:`TorchShader`: its shading on the device,
  the stages by the Renderer's numpy kernels);
* :class:`BatchRenderer` (over such a Renderer): ``B`` frames at once, every stage on the device too
  (its :meth:`~BatchRenderer.stage` takes device tensors as they are); :class:`gelsim.sinks.DeviceFrames`
  feeds it a sequence's frame records, as the dataset does (``gelsim generate --backend torch --device cuda``).

Agreement with ``fast`` (stated tolerance, :data:`TOL_MEAN_DN` and :data:`TOL_MAX_DN`, tested in
``tests/gelsim/test_torch_backend.py``; each primitive's in ``tests/gelsim/test_optics_ops.py``): the
noiseless float frames differ by operation order at float32 rounding, by OpenCV's fixed-point remap
weights, and where the LED shadows are drawn, because the fast backend computes them on a grid of
``f x f``-pixel blocks (:meth:`~gelsim.optics.ops.shadows.ShadowSpec.grid_factor`: 4 at 960x720) aligned with
the imprint's box and this backend on one aligned with the frame (at most 0.23 DN on steep spheres at 960x720).

Same bytes for any batch size, and on any device (see :mod:`gelsim.optics.ops`). Nothing here draws
random numbers: the stages' draws (the noise's offsets) are drawn by the caller's numpy generator in
the order the numpy renderer draws them.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import GelsimError
from .composite import BatchInput, OpticsInput, check_depth, frame_rng, marker_corners
from .ops import torch_module
from .ops.box import MARGIN_PX, box_mask_torch
from .ops.filters import blur_radius_px, gaussian_blur_torch, slopes_torch
from .ops.phong import phong_change_torch, phong_lights
from .ops.resample import upsample_torch
from .ops.table import lookup_to_torch, lookup_torch
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


def resolve_device(name: str | None = None):
    """The ``torch.device`` for ``--device`` ``name`` (``cpu``, ``cuda`` or ``cuda:N``; None: ``cpu``), or a
    one-line GelsimError when this machine has no such device."""
    torch = torch_module()
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


class TorchShader(Shader):
    """The fast backend's shading in torch (see the module docstring).

    ``profile``: sensor profile at the resolution being shaded; ``maps``: its light maps;
    ``device``: where to compute (``--device``; default the CPU). :meth:`shade_parts` is the batched form.
    Its inputs on the device: ``lookup`` (the table's, :class:`~gelsim.optics.ops.table.TableLookupTorch`)
    and ``terms`` (the table's shadows and depth and halo terms), or ``phong`` (the lights').
    """

    name = "torch"

    @classmethod
    def reads_light_maps(cls, profile) -> bool:
        return profile.shading.model != "lut"

    def __init__(self, profile, maps, device=None):
        self.profile = profile
        self.device = resolve_device(device) if not hasattr(device, "type") else device
        self.mm = float(profile.image.mm_per_px)
        self.margin_px = MARGIN_PX
        self.lookup = self.phong = None
        self.terms = ()
        if profile.shading.model == "lut":
            from .lut import table_model

            model = table_model(profile)
            self.lookup = lookup_to_torch(model.lookup, self.device)
            self.terms = model.terms
        else:
            self.phong = phong_lights(profile, maps).to_torch(self.device)

    def shade_parts(self, depth, blur_sigma_px: float, margin_px: int | None = None) -> list:
        """The shading change of ``B`` imprints (float32 ``(B, H, W)`` mm, >= 0, on this shader's device) as
        the fast backend adds it to the background, in its order: the part the camera blurs, blurred by
        ``blur_sigma_px`` (0: not at all) and kept to the box the fast backend shades (the imprint's box
        grown by ``margin_px``, default the blur's reach); then the table's terms (the shadows, blurred
        by the camera too, and the depth and halo terms). Each ``(B, 3, H, W)`` DN."""
        torch = torch_module()
        if margin_px is None:
            margin_px = blur_radius_px(blur_sigma_px)
        pos = depth > 0
        if self.lookup is not None:
            sharp = lookup_torch(depth, self.lookup, self.mm)
        else:
            sharp = phong_change_torch(*slopes_torch(depth, self.mm), self.phong)
            # zero where the slope stencil reaches no imprinted pixel, as outside the fast backend's box
            near = torch.nn.functional.max_pool2d(pos[:, None].float(), 3, 1, 1) > 0
            sharp = torch.where(near, sharp, 0.0)
        sharp = gaussian_blur_torch(sharp, blur_sigma_px)
        out = [sharp * box_mask_torch(pos, self.margin_px + margin_px)]
        return out + [term.part_torch(depth, blur_sigma_px) for term in self.terms]

    def shade(self, depth, blur_sigma_px: float, margin_px: int | None = None):
        """The sum of :meth:`shade_parts`, in their order: ``(B, 3, H, W)`` DN."""
        parts = self.shade_parts(depth, blur_sigma_px, margin_px)
        out = parts[0]
        for p in parts[1:]:
            out = out + p
        return out

    # ------------------------------------------------------------ the Shader contract (one numpy frame)

    def _one(self, depth_mm: np.ndarray, blur_sigma_px: float, margin_px: int) -> np.ndarray | None:
        torch = torch_module()
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


# ---------------------------------------------------------------- whole frames, B at a time

class BatchRenderer:
    """``B`` frames at once through ``renderer`` (a :class:`~gelsim.optics.Renderer` made with backend
    ``"torch"``): its inputs (:attr:`~gelsim.optics.Renderer.optics`), its shader and its stages (the
    composition, the renderer's list of :class:`~gelsim.optics.composite.Stage`), each stage's torch kernel on
    the shader's device.

    Inputs per frame as :meth:`Renderer.render` takes them: the imprint float32 ``(H, W)`` mm or None,
    the markers (an object with ``.corners_px``, an ``(N, 4, 2)`` array, or None) and the noise seed (an
    int or the sequence's numpy Generator, drawn from exactly as the numpy renderer draws); or, for
    :meth:`stage`, tensors already on a device."""

    def __init__(self, renderer):
        torch = torch_module()
        if not isinstance(getattr(renderer, "shader", None), TorchShader):
            raise GelsimError("BatchRenderer needs a Renderer made with backend 'torch'")
        self.renderer = renderer
        self.shader: TorchShader = renderer.shader
        self.device = self.shader.device
        self.optics = renderer.optics
        self.profile = renderer.profile
        self.shape = renderer.profile.shape
        self.s = renderer.supersample
        self.stages = renderer.stages
        self._final = next(i for i, st in enumerate(self.stages) if st.final)
        self._blur = self.optics.blur_sigma_px
        self._margin = blur_radius_px(self._blur)
        self._bg = torch.tensor(self.optics.background_fine.transpose(2, 0, 1), device=self.device)  # (3, H, W)
        self._pinned = self.device.type == "cuda"

    # ------------------------------------------------------------ inputs

    def draw(self, seed, noise: bool = True):
        """This frame's random draws by stage name (the readout's: the noise's offsets ``(bank frame, row,
        column)``), drawn from ``seed`` as the numpy renderer draws them; None where nothing is drawn."""
        rng = frame_rng(seed)
        draws = {}
        for st in self.stages:
            d = st.draw(rng, noise)
            if d is not None:
                draws[st.name] = d
        return draws or None

    def stage(self, depths, markers):
        """A batch's inputs for :meth:`compose`, validated as the numpy renderer validates them: ``(depth,
        corners)``. ``depths``: a list of float32 ``(H, W)`` mm or None (zeros), or a float tensor ``(B, H,
        W)`` mm on any device (kept there: no round trip through the host); ``markers``: a list as
        :meth:`Renderer.render` takes them, or a tensor ``(B, N, 4, 2)`` px. ``depth``: float32 ``(B, H, W)``
        (array or tensor); ``corners``: float32 ``(B, N, 4, 2)`` (a frame without markers gets them far off
        the image, where they draw nothing), or None without markers."""
        torch = torch_module()
        h, w = self.shape
        if torch.is_tensor(depths):
            depth = _check_tensor(depths, (len(depths), h, w), "depth map", lambda d: d.amin() < -1e-3,
                                  "has negative values; the imprint is the depth pushed into the gel, >= 0")
            depth = torch.clamp(depth, min=0.0)
        else:
            depth = np.zeros((len(depths), h, w), np.float32)
            for i, d in enumerate(depths):
                d = check_depth(d, self.shape)
                if d is not None:
                    depth[i] = d
        if not self.profile.markers.enabled or markers is None:
            return depth, None
        if torch.is_tensor(markers):
            return depth, _check_tensor(markers, (len(depth),) + tuple(markers.shape[1:2]) + (4, 2), "marker corners")
        cs = [marker_corners(m) for m in markers]
        n = max((0 if c is None else len(c)) for c in cs)
        if not n:
            return depth, None
        if any(c is not None and len(c) != n for c in cs):
            raise GelsimError("frames of one batch have different numbers of markers; render them apart")
        off = np.float32(-1e6)
        return depth, np.stack([np.full((n, 4, 2), off, np.float32) if c is None else c for c in cs])

    # ------------------------------------------------------------ rendering

    def _to_device(self, a):
        torch = torch_module()
        if torch.is_tensor(a):
            return a.to(self.device, torch.float32)
        t = torch.from_numpy(a)
        if self._pinned:
            t = t.pin_memory()
        return t.to(self.device, non_blocking=self._pinned)

    def compose(self, depth, corners, draws: list | None = None, gains: list | None = None, inputs: list | None = None):
        """The frames before the readout, float32 ``(B, 3, H, W)`` DN on the device, from :meth:`stage`'s
        ``depth`` and ``corners`` (``draws``: each frame's :meth:`draw`, for the stages before the readout;
        ``gains``: each frame's camera gains (3,) or None, as :meth:`Renderer.render` takes them; ``inputs``: the
        frames' :class:`~gelsim.optics.composite.OpticsInput` objects, passed on to the stages)."""
        d = self._to_device(depth)
        s = self.s
        if s > 1:
            d = upsample_torch(d, s, (d.shape[1] * s, d.shape[2] * s))
        frame = self._bg[None]
        for part in self.shader.shade_parts(d, self._blur, self._margin):
            frame = frame + part
        if gains is not None and len(gains) != len(d):
            raise GelsimError(f"{len(gains)} frames' gains for a batch of {len(d)}; give one (or None) per frame")
        batch = BatchInput(d, None if corners is None else self._to_device(corners), gains, draws, inputs)
        for st in self.stages[:self._final]:
            frame = st.apply_torch(frame, batch)
        return frame

    def quantise(self, frame, offsets: list):
        """``frame`` (:meth:`compose`) through the readout: each frame's noise (``offsets``: its :meth:`draw`,
        None for a noiseless frame), rounded half to even and saturated: uint8 ``(B, H, W, 3)`` RGB on the
        device."""
        return self.stages[self._final].apply_torch(frame, BatchInput(None, None, None, offsets))

    def frames(self, depth, corners, draws: list, gains: list | None = None, inputs: list | None = None):
        """uint8 ``(B, H, W, 3)`` RGB on the device from depth float32 ``(B, H, W)`` mm and corners float32
        ``(B, N, 4, 2)`` px (or None) already on a device (:meth:`stage`'s form), each frame's :meth:`draw` and
        camera gains (or None) and its :class:`~gelsim.optics.composite.OpticsInput` (or None)."""
        corners = corners if self.profile.markers.enabled else None
        return self.quantise(self.compose(depth, corners, draws, gains, inputs), draws)

    def render_inputs(self, inputs: list) -> np.ndarray:
        """uint8 ``(B, H, W, 3)`` RGB of frames given as :class:`~gelsim.optics.composite.OpticsInput` objects
        (each frame's draws made from its ``seed``, in order)."""
        draws = [self.draw(i.seed, i.noise) for i in inputs]
        depth, corners = self.stage([i.depth_mm for i in inputs], [i.markers for i in inputs])
        gains = [i.gains for i in inputs]
        gains = None if all(g is None for g in gains) else gains
        return self.quantise(self.compose(depth, corners, draws, gains, list(inputs)), draws).cpu().numpy()

    def render(self, depths: list, markers: list | None = None, seeds: list | None = None, *,
               noise: bool = True, gains: list | None = None) -> np.ndarray:
        """uint8 ``(B, H, W, 3)`` RGB: the frames :meth:`Renderer.render` gives for the same inputs (within
        the stated tolerance); ``seeds`` one per frame (default 0)."""
        n = len(depths)
        if gains is not None and len(gains) != n:
            raise GelsimError(f"{len(gains)} frames' gains for a batch of {n}; give one (or None) per frame")
        markers = markers if markers is not None else [None] * n
        seeds = seeds if seeds is not None else [0] * n
        gains = gains if gains is not None else [None] * n
        return self.render_inputs([OpticsInput(d, m, g, s, noise) for d, m, g, s in zip(depths, markers, gains, seeds)])

    def render_float(self, depths: list, markers: list | None = None, *, gains: list | None = None) -> np.ndarray:
        """Noiseless, unquantised frames: float32 ``(B, H, W, 3)`` DN (as :meth:`Renderer.render_float`)."""
        markers = markers if markers is not None else [None] * len(depths)
        depth, corners = self.stage(depths, markers)
        return np.ascontiguousarray(self.compose(depth, corners, None, gains).permute(0, 2, 3, 1).cpu().numpy())


def _check_tensor(t, shape: tuple, what: str, bad=None, why: str = ""):
    """``t`` if a finite float tensor of ``shape``, else one line naming the problem; ``bad(t)``: a further
    test (a bool tensor) that fails with ``why``."""
    torch = torch_module()
    if tuple(t.shape) != tuple(shape) or not torch.is_floating_point(t):
        raise GelsimError(f"{what} tensor has shape {tuple(t.shape)} and dtype {t.dtype}; give float {tuple(shape)}")
    if not bool(torch.isfinite(t).all()):
        raise GelsimError(f"{what} tensor contains NaN or infinity; check what computed it")
    if bad is not None and bool(bad(t)):
        raise GelsimError(f"{what} tensor {why}")
    return t
