"""The optics of one frame, in order, written once for every backend.

A frame is composed in this order, in float32 DN until the readout:

1. **shading** (the backend's :class:`~gelsim.optics.shader.Shader`): the flat gel's background (built
   once: LED tint, illumination field, vignetting, camera blur) plus the membrane's shading change
   blurred by the camera within the imprint's box (a calibrated table, or Lambert + Phong from the
   LEDs), then, with a table, its terms in :class:`~gelsim.optics.lut.TableModel`'s order: the LEDs'
   soft shadows and the depth and halo terms;
2. the **stages** of the renderer's list (default :data:`OPTICS_STAGES`), in order: :class:`MarkerShading`
   (``x (1 - darkness * blur(coverage))``),
   :class:`CameraGains` (the webcam's exposure and white balance, a per-channel gain per frame; only with
   a nuisance level, :mod:`gelsim.nuisance`), :class:`AreaAverage` (supersampling's average back down), :class:`Readout` (camera noise, then
   8-bit quantisation; always last).

A stage carries its numpy kernel and its torch kernel (both calling the primitives of
:mod:`gelsim.optics.ops`, where each primitive's two kernels stand side by side), so both backends run
this one list: :class:`gelsim.optics.Renderer` one frame at a time in numpy, band by band while the
rows are in the cache where every stage allows it, and
:class:`gelsim.optics.torch_backend.BatchRenderer` ``B`` frames at once on a device. Adding a stage
(a nuisance of the image, say) is writing a :class:`Stage` subclass with both kernels and inserting
it into the list (:data:`OPTICS_STAGES`, or a renderer's ``stages=`` argument); both backends then run it
in its place, and its random draws (if any) come from each frame's seed in the list's order.

A frame's inputs travel in one object, :class:`OpticsInput` (the depth to render, the markers, the camera's
gains, where its random draws come from), from whoever makes the frame to the renderer, which hands each
stage what it reads in the prepared form (:class:`FrameInput` for a numpy frame, :class:`BatchInput` for a
torch batch, each with the frame's draws by stage name).

The inputs every backend reads are public and built once per renderer (:class:`Optics`: the
resolutions, light maps, background, camera blur, noise bank), so that no backend reads another's
state.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Mapping

import cv2
import numpy as np

from ..errors import GelsimError
from .field import LightMaps, background_float, light_maps
from .ops.filters import gaussian_blur
from .ops.markers import apply_marker_factors, fine_px, marker_corners, marker_factor_torch, marker_factors
from .ops.readout import NoiseBank, readout_torch, to_uint8_rows
from .ops.resample import area_mean, area_mean_torch

__all__ = ["Optics", "OpticsInput", "FrameInput", "BatchInput", "Stage", "MarkerShading", "CameraGains", "AreaAverage",
           "Readout", "OPTICS_STAGES", "check_depth", "frame_rng", "marker_corners"]


@dataclass(frozen=True)
class Optics:
    """The optics' inputs for one profile, built once per renderer (:meth:`build`), read by every backend.

    ``profile``: the sensor profile (output resolution ``(H, W)``); ``supersample``: ``s``, the shading
    is done at ``s`` times the resolution (``fine``: the profile there) and averaged back down;
    ``maps``: the LEDs' :func:`~gelsim.optics.field.light_maps` at the fine resolution (made on first use
    and then kept: 41 MB at 960x720 with three LEDs, which a calibrated table's shading never reads);
    ``blur_sigma_px``: the camera blur's sigma in fine pixels; ``background_fine`` and ``background``:
    the flat gel without markers or noise, float32 ``(sH, sW, 3)`` and ``(H, W, 3)`` DN (camera blur
    applied); ``noise``: the camera noise's bank (:class:`~gelsim.optics.ops.readout.NoiseBank`)."""
    profile: object
    fine: object
    supersample: int
    blur_sigma_px: float
    background_fine: np.ndarray
    background: np.ndarray
    noise: NoiseBank

    @classmethod
    def build(cls, profile, supersample: int = 1, seed: int = 0) -> "Optics":
        """The inputs of ``profile`` at supersampling ``supersample``; ``seed`` fixes the background's random
        illumination field and the noise bank."""
        h, w = profile.shape
        s = int(supersample)
        fine = profile if s == 1 else profile.with_resolution(w * s, h * s)
        maps = light_maps(fine)
        blur = profile.camera.blur_sigma_px * s
        bg = gaussian_blur(background_float(fine, maps, seed), blur)
        out = bg if s == 1 else cv2.resize(bg, (w, h), interpolation=cv2.INTER_AREA)
        n = profile.noise
        return cls(profile, fine, s, blur, bg, out, NoiseBank(profile.shape, n.read_sigma_dn, n.shot_gain, seed))

    @cached_property
    def maps(self) -> list[LightMaps]:
        """The LEDs' light maps at the fine resolution (see the class docstring)."""
        return light_maps(self.fine)


def check_depth(depth_mm, shape: tuple[int, int]) -> np.ndarray | None:
    """Validate an imprint: float32 C-contiguous ``(H, W)`` mm, finite, >= 0 (tiny negatives clipped)."""
    if depth_mm is None:
        return None
    d = np.asarray(depth_mm)
    if d.shape != tuple(shape):
        raise GelsimError(f"depth map has shape {d.shape} but the profile's image is {tuple(shape)} (H, W); "
                          "compute the imprint at the profile's resolution or use profile.with_resolution")
    if not np.issubdtype(d.dtype, np.number):
        raise GelsimError(f"depth map has dtype {d.dtype}; give float32 millimetres")
    d = np.ascontiguousarray(d, dtype=np.float32)
    lo, hi = float(d.min()), float(d.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise GelsimError("depth map contains NaN or infinity; check the imprint computation")
    # float error of an imprint model may leave -1e-7 mm; a real negative depth is a sign error
    if lo < -1e-3:
        raise GelsimError(f"depth map has negative values (min {lo:.4g} mm); the imprint is the depth "
                          "pushed into the gel, >= 0")
    if lo < 0:
        d = np.maximum(d, 0.0)
    return d


def frame_rng(seed: int | np.random.Generator):
    """A frame's random generator for the stages' draws, made on first use: a callable returning the
    Generator (``seed`` itself if it is one, else ``np.random.default_rng(seed)``). A fresh Generator
    costs about 30 us, as much as a tenth of a small flat frame: a frame whose stages draw nothing
    makes none."""
    made = [seed] if isinstance(seed, np.random.Generator) else []

    def rng() -> np.random.Generator:
        if not made:
            made.append(np.random.default_rng(seed))
        return made[0]

    return rng


@dataclass(frozen=True)
class OpticsInput:
    """One frame's inputs to the optics, in one object from whoever makes the frame to the renderer.

    ``depth_mm``: the depth the optics render, float32 ``(H, W)`` mm >= 0 (the imprint plus the nuisance's
    dents: the engine's ``render_depth``, :mod:`gelsim.engines`), or None for the flat gel (a tensor on a device for the torch
    batch renderer's :meth:`~gelsim.optics.torch_backend.BatchRenderer.frames`); ``markers``: an object with
    ``.corners_px`` float32 ``(N, 4, 2)`` px, such an array, or None; ``gains``: the camera's per-channel gains
    ``(3,)`` (:class:`CameraGains`) or None (all 1); ``seed``: where the frame's random draws come from (an
    int, or the sequence's Generator, drawn from in frame order); ``noise``: False for a noiseless frame;
    ``extent``: the box where ``depth_mm > 0`` (:func:`~gelsim.optics.ops.box.imprint_extent`) where its maker has
    it (the imprint's :attr:`~gelsim.gel.Imprint.depth_extent`, read by the markers too), None where not given (the
    shader finds it)."""
    depth_mm: Any = None
    markers: Any = None
    gains: Any = None
    seed: int | np.random.Generator = 0
    noise: bool = True
    extent: tuple[int, int, int, int] | None = None


@dataclass
class FrameInput:
    """One frame's inputs as the numpy stages read them: ``depth`` the depth to render at the fine
    resolution (float32 mm, validated) or None; ``markers`` as :class:`OpticsInput`'s (output pixels);
    ``shape`` the fine frame's ``(sH, sW, 3)``; ``gains`` the camera's per-channel gains ``(3,)`` or None (all
    1); ``draws`` the frame's random draws by stage name (:meth:`Stage.draw`'s; empty for an unquantised
    frame, which draws nothing); ``inputs`` the frame's :class:`OpticsInput` itself (a stage reading an input
    added to it finds it there: the renderers pass it on unchanged)."""
    depth: np.ndarray | None
    markers: object
    shape: tuple[int, int, int]
    gains: np.ndarray | None = None
    draws: Mapping[str, object] = field(default_factory=dict)
    inputs: OpticsInput | None = None


@dataclass
class BatchInput:
    """``B`` frames' inputs as the torch stages read them: ``depth`` ``(B, sH, sW)`` mm at the fine resolution
    and ``corners`` ``(B, N, 4, 2)`` output pixels (None without markers), tensors on the device; ``gains``
    each frame's camera gains ``(3,)`` or None, a list (None: no frame has any); ``draws`` each frame's random
    draws by stage name (a list of mappings or None; None: nothing drawn); ``inputs`` the frames'
    :class:`OpticsInput` objects where the caller has them (None: not given)."""
    depth: object
    corners: object
    gains: list | None = None
    draws: list | None = None
    inputs: list | None = None

    def draws_of(self, stage: "Stage", n: int) -> list:
        """``stage``'s draw of each of the ``n`` frames (None where it drew nothing)."""
        if self.draws is None:
            return [None] * n
        return [None if d is None else d.get(stage.name) for d in self.draws]


class Stage(ABC):
    """One step of the optics after the shading, with its numpy and its torch kernel (see the module
    docstring). Built once per renderer from its :class:`Optics`; may keep caches between frames.

    ``banded``: the numpy kernel works on any band of a frame's rows alone, in place (so the renderer
    can run it while the band is in the cache); False: it needs the whole frame and returns a new one.
    ``final``: the readout, last in the list; it turns the float frame into the camera's uint8
    frame (its :meth:`apply` reads the rows and writes its own output, :meth:`result`), and is skipped
    for an unquantised frame (:meth:`Renderer.render_float`, :meth:`BatchRenderer.compose`)."""

    name: str = ""
    banded: bool = True
    final: bool = False

    def __init__(self, optics: Optics):
        self.optics = optics

    def draw(self, rng, noise: bool):
        """This stage's random draws for one frame from the frame's generator ``rng()`` (:func:`frame_rng`;
        the stages draw in their list's order; ``noise`` False: a noiseless frame). Default: none (None).
        The renderer hands them back in the frame's input (``draws[name]``)."""
        return None

    @abstractmethod
    def prepare(self, frame: FrameInput):
        """numpy: this frame's state for :meth:`apply` (reading what it needs of ``frame``, its draw
        ``frame.draws.get(self.name)`` included), or None where the stage leaves the frame as it is. A stage
        returns the same state object for the same inputs where it can (the renderer then reuses a flat
        gel's frame)."""

    @abstractmethod
    def apply(self, rows: np.ndarray, y0: int, state) -> np.ndarray:
        """numpy kernel: the frame's rows from ``y0`` (float32 ``(n, W, 3)`` DN; the whole frame for a stage
        that is not ``banded``) after this stage, in place for a ``banded`` stage."""

    @abstractmethod
    def apply_torch(self, frames, batch: BatchInput):
        """torch kernel: ``frames`` ``(B, 3, H, W)`` DN after this stage (reading what it needs of ``batch``,
        its draws :meth:`BatchInput.draws_of` included)."""

    def result(self, state) -> np.ndarray:
        """The ``final`` stage's output once every row of the frame went through :meth:`apply`."""
        raise NotImplementedError(f"{self.name} is not the final stage")


class MarkerShading(Stage):
    """The frame times ``1 - darkness * blur(coverage)`` of the profile's markers
    (:mod:`gelsim.optics.ops.markers`), at the shading resolution. A frame's factors are reused while its
    markers do not move (a sequence's frames before contact: about 1 ms each at 960x720)."""

    name = "markers"

    def __init__(self, optics: Optics):
        super().__init__(optics)
        mk = optics.profile.markers
        self.enabled = bool(mk.enabled)
        self.darkness = float(mk.darkness)
        self._last = None                    # (corners, shape, factors) of the last frame

    def prepare(self, frame: FrameInput):
        corners = marker_corners(frame.markers) if self.enabled else None
        if corners is None:
            return None
        if self.optics.supersample > 1:
            corners = fine_px(corners, self.optics.supersample)
        last = self._last
        if last is not None and last[1] == frame.shape and np.array_equal(last[0], corners):
            return last[2]
        factors = marker_factors(corners, self.darkness, self.optics.blur_sigma_px, frame.shape)
        self._last = (corners.copy(), frame.shape, factors)
        return factors

    def apply(self, rows, y0, state):
        apply_marker_factors(rows, state, y0)
        return rows

    def apply_torch(self, frames, batch):
        if not self.enabled or batch.corners is None:
            return frames
        s = self.optics.supersample
        corners = fine_px(batch.corners, s) if s > 1 else batch.corners
        return frames * marker_factor_torch(corners, tuple(frames.shape[-2:]), self.darkness,
                                            self.optics.blur_sigma_px)[:, None]


def check_gains(gains) -> np.ndarray | None:
    """A frame's camera gains as float32 ``(3,)`` (rounded once, so both kernels multiply by the same
    numbers), or None for None; anything but three finite numbers >= 0 is a GelsimError."""
    if gains is None:
        return None
    g = np.asarray(gains, np.float64)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or np.any(g < 0):
        raise GelsimError(f"camera gains {gains!r} must be three finite numbers >= 0 (R, G, B)")
    return g.astype(np.float32)


class CameraGains(Stage):
    """The webcam's exposure and white balance: the frame times per-channel gains (one per frame, given with
    the frame: :class:`gelsim.nuisance.sequence.SequenceNuisance`, which draws them per sequence). Before the
    noise, since a sensor's read noise does not scale with exposure. Nothing where a frame has no gains
    (every frame without a nuisance level: today's bytes)."""

    name = "camera gains"

    def prepare(self, frame: FrameInput):
        return check_gains(frame.gains)

    def apply(self, rows, y0, state):
        rows *= state
        return rows

    def apply_torch(self, frames, batch):
        gains = batch.gains
        if gains is None or all(g is None for g in gains):
            return frames
        import torch

        g = np.stack([np.ones(3, np.float32) if g is None else check_gains(g) for g in gains])
        return frames * torch.from_numpy(g).to(frames.device)[:, :, None, None]


class AreaAverage(Stage):
    """Supersampling's last step: the frame averaged over ``s x s`` blocks, back to the profile's
    resolution (:func:`~gelsim.optics.ops.resample.area_mean`); nothing without supersampling."""

    name = "area average"
    banded = False

    def prepare(self, frame):
        return self if self.optics.supersample > 1 else None

    def apply(self, rows, y0, state):
        return area_mean(rows, self.optics.supersample)

    def apply_torch(self, frames, batch):
        return area_mean_torch(frames, self.optics.supersample)


@dataclass
class _Readout:
    offsets: tuple | None        # the noise's draw, or None for a noiseless frame
    out: np.ndarray              # uint8 (H, W, 3), written row by row


class Readout(Stage):
    """The camera's readout: noise (:class:`~gelsim.optics.ops.readout.NoiseBank`; its field drawn from each
    frame's seed) and 8-bit quantisation. Numpy: one fused pass per band into the uint8 frame."""

    name = "readout"
    final = True

    def __init__(self, optics: Optics):
        super().__init__(optics)
        self._shape = optics.profile.shape + (3,)
        self._banks: dict = {}                # the noise bank per torch device

    def draw(self, rng, noise):
        n = self.optics.noise
        return n.offsets(rng()) if noise and n.active else None

    def prepare(self, frame):
        return _Readout(frame.draws.get(self.name), np.empty(self._shape, np.uint8))

    def apply(self, rows, y0, state):
        if state.offsets is None:
            to_uint8_rows(rows, state.out, y0)
        else:
            self.optics.noise.apply_rows(rows, state.offsets, state.out, y0)
        return rows

    def result(self, state) -> np.ndarray:
        """The uint8 ``(H, W, 3)`` frame."""
        return state.out

    def apply_torch(self, frames, batch):
        noise = self.optics.noise
        draws = batch.draws_of(self, frames.shape[0])
        if not noise.active:
            return readout_torch(frames, None, noise, draws)
        if frames.device not in self._banks:
            self._banks[frames.device] = noise.to_torch(frames.device)
        return readout_torch(frames, self._banks[frames.device], noise, draws)


#: The stages after the shading, in order (the readout last): every renderer's unless it is given its own list
#: (``Renderer(..., stages=)``). A tuple: nothing changes it at run time.
OPTICS_STAGES: tuple[type[Stage], ...] = (MarkerShading, CameraGains, AreaAverage, Readout)
