"""Photometric rendering: gel imprint + markers + sensor profile -> uint8 RGB camera frame.

:class:`Renderer` is the one place that chooses a backend. Both backends compute
only the *shading change* of the deformed membrane over the flat gel; the flat
background, the markers, the camera blur and noise and the quantisation are
composited identically here, so the backends differ in shading alone:

* ``fast``: Lambert + Phong from surface normals under the profile's LEDs,
  numpy/OpenCV in float32, shading only the box around the imprint
  (:mod:`gelsim.optics.fast`);
* ``fast`` with ``[shading] model = "lut"``: a table calibrated on real frames
  (:mod:`gelsim.optics.lut`, written by ``gelsim calibrate``);
* ``pyrender``: the deformed gel as a mesh lit by spot lights with shadows,
  OpenGL through OSMesa or EGL (:mod:`gelsim.optics.pyrender_backend`), the
  yardstick for ``fast``. It always shades from the profile's lights (a
  calibrated table has no meaning for a mesh renderer);
* ``torch``: ``fast``'s shading in PyTorch on ``device`` (``cpu`` or ``cuda``), equal to
  ``fast`` within a stated tolerance (:mod:`gelsim.optics.torch_backend`, whose
  ``BatchRenderer`` renders whole frames, markers and noise included, ``B`` at a time).

Each backend is a :class:`~gelsim.optics.shader.Shader` (its contract: ``delta``, ``parts``,
``compose``, ``close``), found by name and checked when the Renderer loads it.

Pipeline per frame (all float32 DN 0-255 until the last step)::

    background (cached, vignetted, blurred) + blur(shading change) x vignetting
      -> x (1 - darkness * blur(marker coverage)) -> [area-downsample if supersampled]
      -> + noise(sqrt(read^2 + shot_gain * signal)) -> uint8 (saturating)

The camera blur is applied to the shading change and to the marker coverage
separately rather than to their product; the background is smooth, so the
difference is far below one DN.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..errors import GelsimError, check_choice
from .composite import (NoiseBank, apply_marker_factors, blur_radius_px, gaussian_blur, marker_corners,
                        marker_factors, to_uint8, to_uint8_rows)
from .field import background_float, light_maps
from .shader import Shader, shader_class, work_array

BACKENDS = ("fast", "pyrender", "torch")
_STALE = object()           # Renderer._frame_flat: the frame buffer holds no flat gel under markers

__all__ = ["Renderer", "render", "available_backends", "BACKENDS", "Shader"]


def available_backends() -> list[str]:
    """Backends that can render on this machine (``pyrender`` only if a headless GL context can be made,
    ``torch`` if PyTorch is installed)."""
    import importlib.util

    out = ["fast"]
    from .pyrender_backend import gl_available
    if gl_available():
        out.append("pyrender")
    if importlib.util.find_spec("torch") is not None:
        out.append("torch")
    return out


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


class Renderer:
    """Renders frames of one sensor.

    ``profile``: a :class:`~gelsim.sensor.SensorProfile`; ``backend``: ``"fast"``,
    ``"pyrender"`` or ``"torch"``; ``supersample``: shade and draw at this many times the
    resolution (1-4), then area-average down; ``seed``: fixes the background's
    random illumination field and the noise bank; ``device``: where the ``torch``
    backend computes (``"cpu"``, ``"cuda"``; default the CPU), for no other backend.
    """

    def __init__(self, profile, backend: str = "fast", *, supersample: int = 1, seed: int = 0,
                 device: str | None = None):
        check_choice("render backend", backend, BACKENDS)
        if device is not None and backend != "torch":
            raise GelsimError(f"--device {device} is for the torch backend, not {backend!r}; add --backend torch "
                              "or drop --device")
        if isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer)) \
                or not 1 <= supersample <= 4:
            raise GelsimError(f"supersample {supersample!r} is invalid; give an integer from 1 to 4")
        self.profile = profile
        self.backend = backend
        self.supersample = int(supersample)
        self.seed = int(seed)
        h, w = profile.shape
        s = self.supersample
        self._fine = profile if s == 1 else profile.with_resolution(w * s, h * s)
        maps = light_maps(self._fine)
        self._blur_fine = profile.camera.blur_sigma_px * s
        bg = gaussian_blur(background_float(self._fine, maps, self.seed), self._blur_fine)
        self._bg_fine = bg
        self._bg = bg if s == 1 else cv2.resize(bg, (w, h), interpolation=cv2.INTER_AREA)
        cls = shader_class(backend, profile)
        self._shader: Shader = cls(self._fine, maps, device=device) if backend == "torch" else cls(self._fine, maps)
        self._bufs: dict[str, np.ndarray] = {}
        self._last_markers = None          # (corners, frame shape, marker_factors) of the last frame
        # the marker_factors of the flat gel the "frame" work buffer holds, or _STALE (it holds shading)
        self._frame_flat = _STALE
        n = profile.noise
        self._noise = NoiseBank(profile.shape, n.read_sigma_dn, n.shot_gain, self.seed)

    def background(self) -> np.ndarray:
        """The flat gel without markers or noise: uint8 ``(H, W, 3)`` RGB."""
        return to_uint8(self._bg)

    def background_float(self) -> np.ndarray:
        """The flat gel without markers or noise, unquantised: float32 ``(H, W, 3)`` DN (a copy)."""
        return self._bg.copy()

    def render_float(self, depth_mm: np.ndarray | None, markers=None) -> np.ndarray:
        """The noiseless, unquantised frame: float32 ``(H, W, 3)`` DN (may leave 0-255 before saturation)."""
        return self._compose(depth_mm, markers)[0].copy()

    def _work(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """A float32 work array kept between frames (:func:`~gelsim.optics.shader.work_array`)."""
        return work_array(self._bufs, name, shape)

    def _compose(self, depth_mm, markers, finish=None) -> tuple[np.ndarray, bool]:
        """Like :meth:`render_float`, but returns ``(frame, finished)``: the cached background itself, or a
        work buffer that the next frame overwrites (callers must not modify or keep it), and whether
        ``finish(rows, y0)`` (optional) was called on every band of rows (float32 ``(n, W, 3)``, the
        frame's rows ``y0:y0 + n``) of a shaded frame, its markers darkened, while the band was in the
        cache (the frame is then composed nowhere else) (see :meth:`Shader.compose`; only without
        supersampling: a supersampled frame is finished after its resize)."""
        depth = check_depth(depth_mm, self.profile.shape)
        corners = marker_corners(markers) if self.profile.markers.enabled else None
        s = self.supersample
        if s > 1:
            h, w = self._fine.shape
            if depth is not None:
                depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_LINEAR)
            if corners is not None:
                # pixel centres at integers at both resolutions: x_fine = s (x + 1/2) - 1/2
                corners = s * (corners + 0.5) - 0.5
        bg = self._bg_fine
        frame = self._work("frame", bg.shape)
        # the markers' factors depend on their corners alone: computed first, so that bands can use them
        factors = None if corners is None else self._marker_factors(corners, frame.shape)
        band_finish = None
        if finish is not None and s == 1:
            def band_finish(rows: np.ndarray, y0: int, y1: int) -> None:
                apply_marker_factors(rows, factors, y0)
                finish(rows, y0)
        fresh = True                                 # frame does not hold this frame's shading
        if depth is not None:
            # bands finished as they are composed need no frame: the shader composes them in a
            # band-sized buffer, and the frame buffer keeps what it held (the flat gel, say)
            fresh = not self._shader.compose(None if band_finish is not None else frame, bg, depth,
                                             blur_radius_px(self._blur_fine), self._blur_fine, gaussian_blur,
                                             band_finish)
        if fresh and corners is None:
            return self._bg, False
        if not fresh:
            if band_finish is not None:
                return frame, True
            self._frame_flat = _STALE
            apply_marker_factors(frame, factors)
        elif self._frame_flat is not factors:
            # the flat gel under these markers, unless frame holds it from the last frame already
            # (the markers at rest before contact: 0.6 ms of copy and 0.3 of markers saved)
            np.copyto(frame, bg)
            apply_marker_factors(frame, factors)
            self._frame_flat = factors
        if s > 1:
            frame = cv2.resize(frame, self.profile.shape[::-1], interpolation=cv2.INTER_AREA)
        return frame, False

    def _marker_factors(self, corners: np.ndarray, shape: tuple[int, int, int]):
        """:func:`~gelsim.optics.composite.marker_factors` of ``corners`` (shading-resolution px), reused
        while the markers do not move (a sequence's frames before contact: about 1 ms each at 960x720)."""
        last = self._last_markers
        if last is not None and last[1] == shape and np.array_equal(last[0], corners):
            return last[2]
        factors = marker_factors(corners, self.profile.markers.darkness, self._blur_fine, shape)
        self._last_markers = (corners.copy(), shape, factors)
        return factors

    def render(self, depth_mm: np.ndarray | None, markers=None, *, seed: int | np.random.Generator = 0,
               noise: bool = True) -> np.ndarray:
        """One camera frame: uint8 ``(H, W, 3)`` RGB.

        ``depth_mm``: float32 ``(H, W)`` imprint in mm (>= 0), or None for a flat
        gel; ``markers``: an object with ``.corners_px`` float32 ``(N, 4, 2)``
        (x, y) px, such an array, or None; ``seed``: picks this frame's noise
        (same seed, same frame); ``noise``: False for a noiseless frame.
        """
        noisy = noise and self._noise.active
        out = np.empty(self.profile.shape + (3,), np.uint8)
        draw = []                                    # the noise's offsets, drawn at the first band

        def finish(rows: np.ndarray, y0: int) -> None:
            # each band goes to 8 bits while its rows are in the cache (a 960x720 frame's float32
            # copy is 8 MB: the whole-frame pass read it back from memory)
            if not noisy:
                to_uint8_rows(rows, out, y0)
                return
            if not draw:
                draw.append(self._noise.offsets(seed))
            self._noise.apply_rows(rows, draw[0], out, y0)

        frame, finished = self._compose(depth_mm, markers, finish)
        if finished:
            return out
        if noisy:
            return self._noise.apply(frame, seed)
        return to_uint8(frame)

    def close(self) -> None:
        """Free the backend's resources (the GL context for pyrender)."""
        self._shader.close()


def render(depth_mm, markers, profile, *, backend: str = "fast", seed: int = 0) -> np.ndarray:
    """One frame with a throw-away :class:`Renderer` (background seed and noise seed both ``seed``)."""
    r = Renderer(profile, backend, seed=seed)
    try:
        return r.render(depth_mm, markers, seed=seed)
    finally:
        r.close()
