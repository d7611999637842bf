"""The contract between :class:`gelsim.optics.Renderer` and its shading backends.

A backend computes only the *shading change* of the deformed membrane over the flat gel, in image DN;
the Renderer composes the background, markers, blur and noise around it (:mod:`gelsim.optics.composite`). A backend is a subclass of
:class:`Shader`, built as ``cls(profile, maps)`` (the profile at the resolution being shaded, its
:func:`~gelsim.optics.field.light_maps`, or None where :meth:`Shader.reads_light_maps` says the class
does not read them for that profile), and implements:

* :meth:`Shader.delta` (abstract): the change over a box around the imprint;
* :meth:`Shader.parts` (default: ``delta``'s box, to be blurred by the camera): the change as several
  boxes, some already blurred (a backend whose shadows carry their own blur);
* :meth:`Shader.compose` (default: add ``parts`` to the background): the whole frame's shading in one
  pass, for a backend that can fuse the blur into its own loop;
* :meth:`Shader.close` (default: nothing): free what the backend holds (a GL context).

The Renderer calls only ``compose`` and ``close``; the defaults give every backend both. Backends are
looked up by name in :data:`SHADER_CLASSES` and checked against this contract when loaded
(:func:`shader_class`), so a backend that misses a method or changes a signature fails at once with one
line instead of mid-render.
"""
from __future__ import annotations

import importlib
import inspect
from abc import ABC, abstractmethod
from typing import Callable

import cv2
import numpy as np

from ..errors import GelsimError

#: A box of the frame: (row slice, column slice).
Roi = tuple[slice, slice]

#: Shading backends by name: module and class. "lut" is the fast backend with a calibrated table
#: (a profile's ``[shading] model = "lut"``).
SHADER_CLASSES: dict[str, tuple[str, str]] = {
    "fast": ("gelsim.optics.fast", "FastShader"),
    "lut": ("gelsim.optics.lut", "LutShader"),
    "pyrender": ("gelsim.optics.pyrender_backend", "PyrenderShader"),
    # the fast backend's shading (table or Phong, shadows) in PyTorch on a device, also batched
    "torch": ("gelsim.optics.torch_backend", "TorchShader"),
}


def work_array(store: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray:
    """The float32 work array ``name`` of ``store``, reallocated when ``shape`` changes: a fresh 8 MB
    array per frame costs about 1 ms of page faults at 960x720, and a frame's passes are memory-bound."""
    buf = store.get(name)
    if buf is None or buf.shape != shape:
        buf = store[name] = np.empty(shape, np.float32)
    return buf


class Shader(ABC):
    """A shading backend (see the module docstring). ``name``: the backend's name in reports."""

    name: str = ""

    @classmethod
    def reads_light_maps(cls, profile) -> bool:
        """Whether this class reads the light maps it is built with for ``profile`` (else it is given None:
        they are 41 MB at 960x720 with three LEDs). Default: it does."""
        return True

    @abstractmethod
    def delta(self, depth_mm: np.ndarray, margin_px: int = 0) -> tuple[Roi, np.ndarray] | None:
        """``(roi, change)``: the box shaded and float32 ``(h, w, 3)`` DN change there (not blurred by
        the camera) for the imprint ``depth_mm`` (float32 ``(H, W)`` mm, >= 0); None for a flat gel.
        ``margin_px`` grows the box (the camera blur's reach)."""

    def parts(self, depth_mm: np.ndarray, margin_px: int,
              blur_sigma_px: float) -> list[tuple[Roi, np.ndarray, bool]] | None:
        """The change as ``[(roi, change, blurred)]`` (``blurred``: the camera blur of ``blur_sigma_px``
        is already applied), or None for a flat gel. Default: :meth:`delta`'s one box, unblurred."""
        res = self.delta(depth_mm, margin_px=margin_px)
        return None if res is None else [(res[0], res[1], False)]

    def compose(self, frame: np.ndarray, bg: np.ndarray, depth_mm: np.ndarray, margin_px: int,
                blur_sigma_px: float, blur: Callable[..., np.ndarray],
                finish: Callable[[np.ndarray, int, int], None] | None = None,
                extent: tuple[int, int, int, int] | None = None) -> bool:
        """Write ``bg + blur(change)`` into ``frame`` (both float32 ``(H, W, 3)`` DN); False, with ``frame``
        untouched, for a flat gel. ``blur(img, sigma_px, dst)`` is the camera blur. ``finish(rows, y0, y1)``
        (optional, only if True is returned): called once per band of frame rows ``y0:y1`` whose values
        are final, ``rows`` float32 ``(y1 - y0, W, 3)`` DN holding them (writable), in row order, the bands
        covering the frame (the renderer runs its stages there: markers, noise, quantisation;
        :mod:`gelsim.optics.composite`). With ``finish``,
        ``frame`` may be None: the rows are then written to work buffers of the shader's own and exist
        only as handed to ``finish``. ``extent``: the box where ``depth_mm > 0``
        (:func:`~gelsim.optics.ops.box.imprint_extent`) where the caller has it, so that a shader need not
        find it again (None: not given; the default does not read it). Default: the :meth:`parts`, each blurred unless it says it is,
        added to the background, then one ``finish`` of the whole frame."""
        parts = self.parts(depth_mm, margin_px, blur_sigma_px)
        if parts is None:
            return False
        if frame is None:
            frame = self._buffer("frame", bg.shape)
        fresh = True                       # frame does not hold the background yet
        for roi, change, blurred in parts:
            if not blurred:
                change = blur(change, blur_sigma_px, self._buffer("blur", change.shape))
            if fresh and change.shape == bg.shape:
                cv2.add(bg, change, frame)          # a whole-frame change: no copy of the background
            else:
                if fresh:
                    np.copyto(frame, bg)
                region = frame[roi]
                cv2.add(region, change, region)
            fresh = False
        if fresh:
            np.copyto(frame, bg)
        if finish is not None:
            finish(frame, 0, frame.shape[0])
        return True

    def close(self) -> None:
        """Free the backend's resources; default: nothing to free."""

    def _buffer(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """A float32 work array of this shader kept between frames (:func:`work_array`)."""
        return work_array(self.__dict__.setdefault("_bufs", {}), name, shape)


# The methods the Renderer relies on, with Shader's parameters (a backend keeps their names and order).
CONTRACT = ("delta", "parts", "compose", "close")


def check_shader(cls, backend: str) -> type[Shader]:
    """``cls`` if it satisfies the Shader contract; else a one-line GelsimError naming what is wrong."""
    where = f"render backend {backend!r}"
    if not (isinstance(cls, type) and issubclass(cls, Shader)):
        raise GelsimError(f"{where}: {cls!r} is not a gelsim.optics.shader.Shader; derive it from Shader")
    missing = sorted(getattr(cls, "__abstractmethods__", ()))
    if missing:
        raise GelsimError(f"{where}: {cls.__name__} does not implement {', '.join(missing)}; implement "
                          "it (see gelsim.optics.shader.Shader)")
    for method in CONTRACT:
        want = list(inspect.signature(getattr(Shader, method)).parameters)
        got = list(inspect.signature(getattr(cls, method)).parameters)
        if got != want:
            raise GelsimError(f"{where}: {cls.__name__}.{method}({', '.join(got)}) does not take the contract's "
                              f"({', '.join(want)}); give it Shader.{method}'s parameters")
    if not (isinstance(cls.name, str) and cls.name):
        raise GelsimError(f"{where}: {cls.__name__} has no name; set the class attribute name")
    return cls


def shader_class(backend: str, profile) -> type[Shader]:
    """The checked Shader class that renders ``backend`` ("fast", "pyrender" or "torch") for ``profile``:
    "fast" with a calibrated table (``[shading] model = "lut"``) is the "lut" backend ("torch" reads
    either shading model itself)."""
    key = "lut" if backend == "fast" and profile.shading.model == "lut" else backend
    if key not in SHADER_CLASSES:
        raise GelsimError(f"unknown render backend {backend!r}; choose one of fast, pyrender, torch")
    module, name = SHADER_CLASSES[key]
    return check_shader(getattr(importlib.import_module(module), name), key)
