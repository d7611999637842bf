"""Fast shading backend: Lambert + Phong under the profile's LEDs, numpy/OpenCV in float32.

Only the bounding box of the imprint (plus a margin for the gradient stencil and
the camera blur) is shaded; the rest of the frame is the cached background.
Per-pixel light directions and the flat-gel shading are precomputed once
(:func:`~gelsim.optics.ops.phong.phong_lights`); the shading itself is
:func:`~gelsim.optics.ops.phong.phong_change`, whose torch twin the torch backend runs.
"""
from __future__ import annotations

import numpy as np

from .field import LightMaps
from .ops.box import MARGIN_PX, imprint_roi
from .ops.filters import slopes
from .ops.phong import phong_change, phong_lights
from .shader import Shader


class FastShader(Shader):
    """Shading change of the membrane with respect to the flat gel, in image DN.

    ``profile``: sensor profile at the resolution being rendered; ``maps``: its
    :func:`~gelsim.optics.field.light_maps`. ``lights``: the shading's inputs
    (:class:`~gelsim.optics.ops.phong.PhongLights`, vignetting folded in).
    """

    name = "fast"

    def __init__(self, profile, maps: list[LightMaps]):
        self.profile = profile
        self.maps = maps
        self.lights = phong_lights(profile, maps)
        self.margin_px = MARGIN_PX
        self._bufs: dict[str, np.ndarray] = {}

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: slices of the shaded box and float32 ``(h, w, 3)`` DN change there
        (vignetting applied); None for a flat gel. ``margin_px`` grows the box (e.g. for a blur)."""
        roi = imprint_roi(depth_mm, self.margin_px + margin_px)
        if roi is None:
            return None
        gx, gy = slopes(depth_mm[roi], self.profile.image.mm_per_px)
        return roi, phong_change(gx, gy, self.lights, roi, self._buffer)
