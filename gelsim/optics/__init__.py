"""Photometric rendering: gel imprint + markers + sensor profile -> uint8 RGB camera frame.

:class:`Renderer` is the one place that chooses a backend. Every backend computes only the
*shading change* of the deformed membrane over the flat gel (a
:class:`~gelsim.optics.shader.Shader`); the flat background, the markers, the supersampling's
average, the camera noise and the quantisation are the stages of one composition
(:mod:`gelsim.optics.composite`), so the backends differ in shading alone:

* ``fast``: Lambert + Phong from surface normals under the profile's LEDs,
  numpy/OpenCV in float32, shading only the box around the imprint
  (:mod:`gelsim.optics.fast`);
* ``fast`` with ``[shading] model = "lut"``: a table calibrated on real frames, with its LED
  shadows and its depth and halo terms (:mod:`gelsim.optics.lut`, written by ``gelsim calibrate``);
* ``pyrender``: the deformed gel as a mesh lit by spot lights with shadows,
  OpenGL through OSMesa or EGL (:mod:`gelsim.optics.pyrender_backend`), the
  yardstick for ``fast``. It always shades from the profile's lights (a
  calibrated table has no meaning for a mesh renderer);
* ``torch``: ``fast``'s optics in PyTorch on ``device`` (``cpu`` or ``cuda``), equal to
  ``fast`` within a stated tolerance (:mod:`gelsim.optics.torch_backend`, whose
  ``BatchRenderer`` runs the same composition on ``B`` frames at once).

Each primitive of these optics (blurs, slopes, resampling, Phong, the table's lookup, shadows,
depth and halo terms, markers, noise and quantisation) has its numpy and its torch kernel side by
side in :mod:`gelsim.optics.ops`, checked against each other op by op.

Pipeline per frame (all float32 DN until the readout; ``s``: the supersampling)::

    background (cached, vignetted, blurred) + blur(shading change) x vignetting [+ shadows + depth/halo terms]
      -> x (1 - darkness * blur(marker coverage)) -> [area average over s x s blocks]
      -> + noise(sqrt(read^2 + shot_gain * signal)) -> uint8 (rounded, saturating)

The camera blur is applied to the shading change and to the marker coverage
separately rather than to their product; the background is smooth, so the
difference is far below one DN.
"""
from __future__ import annotations

import numpy as np

from ..errors import GelsimError, check_choice
from .composite import OPTICS_STAGES, FrameInput, Optics, OpticsInput, Stage, check_depth, frame_rng
from .ops.filters import blur_radius_px, gaussian_blur
from .ops.readout import to_uint8
from .ops.resample import upsample
from .shader import Shader, shader_class, work_array

BACKENDS = ("fast", "pyrender", "torch")

__all__ = ["Renderer", "render", "available_backends", "check_depth", "BACKENDS", "Shader", "OpticsInput"]


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


class Renderer:
    """Renders frames of one sensor.

    ``profile``: a :class:`~gelsim.sensor.SensorProfile`; ``backend``: ``"fast"``,
    ``"pyrender"`` or ``"torch"``; ``supersample``: shade and draw at this many times the
    resolution (1-4), then area-average down; ``seed``: fixes the background's
    random illumination field and the noise bank; ``device``: where the ``torch``
    backend computes (``"cpu"``, ``"cuda"``; default the CPU), for no other backend; ``stages``: the
    stages after the shading, in order, the readout last (default
    :data:`~gelsim.optics.composite.OPTICS_STAGES`; a test or a study gives its own list).

    Public inputs, read by :class:`~gelsim.optics.torch_backend.BatchRenderer`: ``optics``
    (:class:`~gelsim.optics.composite.Optics`), ``shader`` (the backend's
    :class:`~gelsim.optics.shader.Shader`), ``stages`` (the list, built).
    """

    def __init__(self, profile, backend: str = "fast", *, supersample: int = 1, seed: int = 0,
                 device: str | None = None, stages: tuple[type[Stage], ...] = OPTICS_STAGES):
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
        self.optics = Optics.build(profile, self.supersample, self.seed)
        cls = shader_class(backend, profile)
        fine = self.optics.fine
        # (the light maps are made only for a shader that reads them: a calibrated table does not, and
        # keeping them cost a dataset worker 41 MB of its peak at 960x720)
        maps = self.optics.maps if cls.reads_light_maps(fine) else None
        self.shader: Shader = cls(fine, maps, device=device) if backend == "torch" else cls(fine, maps)
        self.stages = [stage(self.optics) for stage in stages]
        names = [st.name for st in self.stages]
        if not self.stages or not self.stages[-1].final or any(st.final for st in self.stages[:-1]) \
                or len(set(names)) != len(names):
            raise GelsimError(f"optics stages {names}: give stages of distinct names with the readout (the final "
                              "stage) last, once")
        self._shape, self._fine_shape = profile.shape, self.optics.fine.shape + (3,)
        self._bufs: dict[str, np.ndarray] = {}
        # the last flat gel's frame after the stages before the readout, and those stages' states: reused
        # while they are the same objects (the markers at rest before contact: 0.6 ms of copy and 0.3 of
        # markers saved per 960x720 frame)
        self._flat: tuple[list, np.ndarray] | None = None

    def background(self) -> np.ndarray:
        """The flat gel without markers or noise: uint8 ``(H, W, 3)`` RGB."""
        return to_uint8(self.optics.background)

    def background_float(self) -> np.ndarray:
        """The flat gel without markers or noise, unquantised: float32 ``(H, W, 3)`` DN (a copy)."""
        return self.optics.background.copy()

    def render_float(self, depth_mm: np.ndarray | None, markers=None, *, gains=None) -> np.ndarray:
        """The noiseless, unquantised frame: float32 ``(H, W, 3)`` DN (may leave 0-255 before saturation)."""
        return self._run(OpticsInput(depth_mm, markers, gains), False).copy()

    def render(self, depth_mm: np.ndarray | None, markers=None, *, seed: int | np.random.Generator = 0,
               noise: bool = True, gains=None) -> np.ndarray:
        """One camera frame: uint8 ``(H, W, 3)`` RGB.

        ``depth_mm``: float32 ``(H, W)`` imprint in mm (>= 0), or None for a flat
        gel; ``markers``: an object with ``.corners_px`` float32 ``(N, 4, 2)``
        (x, y) px, such an array, or None; ``seed``: picks this frame's noise
        (same seed, same frame); ``noise``: False for a noiseless frame; ``gains``: the camera's
        per-channel gains (3,) before the noise (:class:`~gelsim.optics.composite.CameraGains`; None: 1).
        """
        return self._run(OpticsInput(depth_mm, markers, gains, seed, noise), True)

    def render_input(self, inputs: OpticsInput) -> np.ndarray:
        """One camera frame, uint8 ``(H, W, 3)`` RGB, of a frame's inputs in one object (:class:`OpticsInput`:
        what :meth:`render` takes by name)."""
        return self._run(inputs, True)

    def _run(self, inputs: OpticsInput, final: bool) -> np.ndarray:
        """The frame through the shading and the stages: uint8 when ``final`` (each stage drawing from the
        frame's generator, :func:`~gelsim.optics.composite.frame_rng` of ``inputs.seed``, in turn), else the
        float frame before the readout (the cached background itself, or a work buffer that the next frame
        overwrites: callers must not modify or keep it).

        Where every stage with something to do works on bands of rows (no supersampling), the shader
        hands each band of a shaded frame to them as soon as its rows are final, while they are in the
        cache (:meth:`Shader.compose`'s ``finish``): the frame's float32 copy is then never written to
        memory (8 MB at 960x720)."""
        depth = check_depth(inputs.depth_mm, self._shape)
        extent = inputs.extent                       # (check_depth's clipping keeps the positive pixels)
        if depth is not None and self.supersample > 1:
            depth = upsample(depth, self.supersample, self._fine_shape[:2])
            extent = None                            # (a box of the output pixels, not of the fine ones)
        stages = self.stages if final else [st for st in self.stages if not st.final]
        draws = {}
        if final:
            rng = frame_rng(inputs.seed)
            for st in stages:
                d = st.draw(rng, inputs.noise)
                if d is not None:
                    draws[st.name] = d
        inp = FrameInput(depth, inputs.markers, self._fine_shape, inputs.gains, draws, inputs)
        active = []
        for st in stages:
            state = st.prepare(inp)
            if state is not None:
                active.append((st, state))
        bg, sigma = self.optics.background_fine, self.optics.blur_sigma_px
        if depth is not None:
            if final and all(st.banded for st, _ in active):
                def band(rows: np.ndarray, y0: int, y1: int) -> None:
                    for st, state in active:
                        st.apply(rows, y0, state)

                # bands finished as they are composed need no frame: the shader composes them in a
                # band-sized buffer, and the frame buffer keeps what it held (the flat gel, say)
                if self.shader.compose(None, bg, depth, blur_radius_px(sigma), sigma, gaussian_blur, band, extent):
                    st, state = active[-1]           # the readout
                    return st.result(state)
            else:
                frame = self._work("frame", bg.shape)
                if self.shader.compose(frame, bg, depth, blur_radius_px(sigma), sigma, gaussian_blur, None, extent):
                    self._flat = None                # the frame buffer holds shading now
                    return self._apply(frame, True, active)
        return self._apply_flat(active)

    def _apply(self, frame: np.ndarray, owned: bool, active: list) -> np.ndarray:
        """``frame`` through the ``active`` stages' numpy kernels, whole; ``owned``: whether ``frame`` may be
        modified in place (else it is first copied to the frame buffer)."""
        for st, state in active:
            if st.final:                             # the readout reads the frame, writes its own
                st.apply(frame, 0, state)
                return st.result(state)
            if st.banded and not owned:
                buf = self._work("frame", frame.shape)
                np.copyto(buf, frame)
                frame, owned = buf, True
            out = st.apply(frame, 0, state)
            owned = owned or out is not frame
            frame = out
        return frame

    def _apply_flat(self, active: list) -> np.ndarray:
        """:meth:`_apply` of the flat gel, whose frame before the readout is reused while the stages'
        states are the same objects."""
        head = [(st, state) for st, state in active if not st.final]
        tail = [(st, state) for st, state in active if st.final]
        last = self._flat
        if not head:
            frame = self.optics.background
        elif last is not None and len(last[0]) == len(head) and \
                all(a is c and b is d for (a, b), (c, d) in zip(last[0], head)):
            frame = last[1]
        else:
            frame = self._apply(self.optics.background_fine, False, head)
            self._flat = (head, frame)
        return self._apply(frame, False, tail) if tail else frame

    def _work(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """A float32 work array kept between frames (:func:`~gelsim.optics.shader.work_array`)."""
        return work_array(self._bufs, name, shape)

    def close(self) -> None:
        """Free the backend's resources (the GL context for pyrender)."""
        self.shader.close()


def render(depth_mm, markers, profile, *, backend: str = "fast", seed: int = 0) -> np.ndarray:
    """One frame with a throw-away :class:`Renderer` (background seed and noise seed both ``seed``)."""
    r = Renderer(profile, backend, seed=seed)
    try:
        return r.render(depth_mm, markers, seed=seed)
    finally:
        r.close()
