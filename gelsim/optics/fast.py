"""Fast shading backend: Lambert + Phong under the profile's LEDs, numpy/OpenCV in float32.

Only the bounding box of the imprint (plus a margin for the gradient stencil and
the camera blur) is shaded; the rest of the frame is the cached background.
Per-pixel light directions and the flat-gel shading are precomputed once.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..gel.util import bbox
from .field import LightMaps, vignetting_map
from .shader import Shader


def imprint_extent(depth_mm: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(row0, row1, col0, col1)``, end exclusive, of the box where ``depth_mm > 0``; None if flat.
    (A comparison and OpenCV's bounding box: about 0.15 ms at 960x720, against 0.25 ms for numpy's row
    and column maxima, measured on this project's loaded 2-core machine.)"""
    return bbox(np.asarray(depth_mm) > 0)


def grow_extent(extent, margin_px: int, shape: tuple[int, int]) -> tuple[slice, slice] | None:
    """Slices of ``extent`` (:func:`imprint_extent`) grown by ``margin_px`` within ``shape``."""
    if extent is None:
        return None
    r0, r1, c0, c1 = extent
    h, w = shape
    return (slice(max(0, r0 - margin_px), min(h, r1 + margin_px)),
            slice(max(0, c0 - margin_px), min(w, c1 + margin_px)))


def imprint_roi(depth_mm: np.ndarray, margin_px: int) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box where ``depth_mm > 0``, grown by ``margin_px``; None if flat."""
    return grow_extent(imprint_extent(depth_mm), margin_px, depth_mm.shape)


class FastShader(Shader):
    """Shading change of the membrane with respect to the flat gel, in image DN.

    ``profile``: sensor profile at the resolution being rendered; ``maps``: its
    :func:`~gelsim.optics.field.light_maps`.
    """

    name = "fast"

    def __init__(self, profile, maps: list[LightMaps]):
        self.profile = profile
        self.maps = maps
        self.vignetting = vignetting_map(profile)
        sh = profile.shading
        # colour matrix: output channel c = sum_i gain * colour_i[c] * dL_i
        self.color_matrix = (sh.gain_dn * np.asarray(sh.channel_gain, np.float32)[:, None]
                             * np.stack([m.color for m in maps], axis=1)).astype(np.float32)
        # 1 px for the 3x3 gradient stencil, 1 more so the ROI border is flat for sure
        self.margin_px = 2
        # per-light gains folded into maps once (irradiance x reflectance x vignetting), so a
        # frame costs only the terms that depend on the normal
        vig = self.vignetting
        self._kd = [np.ascontiguousarray(sh.diffuse * m.att * vig, dtype=np.float32) for m in maps]
        self._ks = [np.ascontiguousarray(sh.specular * m.att * vig, dtype=np.float32) for m in maps]
        self._flat = [np.ascontiguousarray(m.flat * vig, dtype=np.float32) for m in maps]
        self._bufs: dict[str, np.ndarray] = {}

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: slices of the shaded box and float32 ``(h, w, 3)`` DN change there
        (vignetting applied); None for a flat gel. ``margin_px`` grows the box (e.g. for a blur)."""
        roi = imprint_roi(depth_mm, self.margin_px + margin_px)
        if roi is None:
            return None
        sh = self.profile.shading
        mm = self.profile.image.mm_per_px
        d = depth_mm[roi]
        # Sobel 3x3 responds 8 per unit step per pixel: scale to a slope in mm/mm.
        gx = cv2.Sobel(d, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / (8.0 * mm), borderType=cv2.BORDER_REPLICATE)
        gy = cv2.Sobel(d, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / (8.0 * mm), borderType=cv2.BORDER_REPLICATE)
        # surface height towards the camera is +depth, so the normal is (-gx, -gy, 1) * nz.
        # cv2 calls with preallocated outputs: numpy temporaries of a full frame cost page
        # faults and were 3x slower here.
        shape = d.shape
        nz, tmp = self._buffer("nz", shape), self._buffer("tmp", shape)
        cv2.multiply(gx, gx, nz)
        cv2.multiply(gy, gy, tmp)
        cv2.add(nz, tmp, nz)
        cv2.add(nz, 1.0, nz)
        cv2.sqrt(nz, nz)
        cv2.divide(1.0, nz, nz)
        spec = sh.specular > 0
        if spec:
            nz2 = cv2.multiply(nz, 2.0, self._buffer("nz2", shape))
        d_l = []
        for i, (m, kd, ks, flat) in enumerate(zip(self.maps, self._kd, self._ks, self._flat)):
            ndl = self._buffer(f"ndl{i}", shape)
            cv2.multiply(gx, m.lx[roi], ndl)
            cv2.subtract(m.lz[roi], ndl, ndl)
            cv2.multiply(gy, m.ly[roi], tmp)
            cv2.subtract(ndl, tmp, ndl)
            cv2.multiply(ndl, nz, ndl)                  # n . l
            if spec:
                # z-component of the mirror direction 2 (n.l) n - l: the camera looks along z
                cv2.multiply(ndl, nz2, tmp)
                cv2.subtract(tmp, m.lz[roi], tmp)
                cv2.max(tmp, 0.0, tmp)
                cv2.pow(tmp, sh.shininess, tmp)
                cv2.multiply(tmp, ks[roi], tmp)
            cv2.max(ndl, 0.0, ndl)
            cv2.multiply(ndl, kd[roi], ndl)
            if spec:
                cv2.add(ndl, tmp, ndl)
            cv2.subtract(ndl, flat[roi], ndl)
            d_l.append(ndl)
        if len(d_l) <= 4:                          # cv2.transform takes 1-4 source channels
            out = cv2.transform(d_l[0] if len(d_l) == 1 else cv2.merge(d_l), self.color_matrix)
        else:
            out = sum(dl[..., None] * self.color_matrix[:, i] for i, dl in enumerate(d_l)).astype(np.float32)
        return roi, out
