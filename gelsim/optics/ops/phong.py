"""Lambert + Phong shading change of the membrane under the profile's LEDs, over the flat gel's, in DN.

For each LED ``i`` with per-pixel unit direction ``l`` (:func:`gelsim.optics.field.light_maps`) and the
membrane's normal ``n = (-gx, -gy, 1) / sqrt(1 + gx^2 + gy^2)`` (``g``: the imprint's slopes, mm/mm):
``dL_i = kd_i max(n.l, 0) + ks_i max(r_z, 0)^shininess - flat_i``, ``r_z`` the z-component of the mirror
direction ``2 (n.l) n - l`` (the camera looks along z); then colour ``c`` gets ``sum_i color[c, i] dL_i``.
The per-light gains (irradiance, reflectance, vignetting) are folded into maps once
(:func:`phong_lights`), so a frame costs only the terms that depend on the normal.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from ..field import vignetting_map
from . import torch_module
from .filters import mix_channels, mix_channels_torch


@dataclass(frozen=True)
class PhongLights:
    """The shading's inputs, built once per profile (:func:`phong_lights`). Per LED, float32 ``(H, W)``
    maps at the shading resolution: ``lx, ly, lz`` the unit vector towards it; ``kd`` diffuse x
    irradiance x vignetting; ``ks`` specular x irradiance x vignetting; ``flat`` the flat gel's shading x
    vignetting. ``color``: float32 ``(3, K)``, DN per unit of each LED's change per colour channel
    (``gain_dn``, channel gains, LED colours); ``shininess``: Phong exponent; ``specular``: whether the
    highlight term is on. The torch backend holds the same with the maps as device tensors
    (:meth:`to_torch`)."""
    lx: tuple
    ly: tuple
    lz: tuple
    kd: tuple
    ks: tuple
    flat: tuple
    color: np.ndarray
    shininess: float
    specular: bool

    def lights(self):
        """Per LED ``(lx, ly, lz, kd, ks, flat)``."""
        return zip(self.lx, self.ly, self.lz, self.kd, self.ks, self.flat)

    def to_torch(self, device) -> "PhongLights":
        """The same inputs with the maps as float32 tensors on ``device``."""
        torch = torch_module()
        maps = {k: tuple(torch.tensor(a, device=device) for a in getattr(self, k))
                for k in ("lx", "ly", "lz", "kd", "ks", "flat")}
        return PhongLights(**maps, color=self.color, shininess=self.shininess, specular=self.specular)


def phong_lights(profile, maps) -> PhongLights:
    """:class:`PhongLights` of ``profile`` (at the shading resolution) from its light ``maps``."""
    sh = profile.shading
    vig = vignetting_map(profile)
    # colour matrix: output channel c = sum_i gain * colour_i[c] * dL_i
    color = (sh.gain_dn * np.asarray(sh.channel_gain, np.float32)[:, None]
             * np.stack([m.color for m in maps], axis=1)).astype(np.float32)

    def fold(gain, key):
        return tuple(np.ascontiguousarray(gain * getattr(m, key) * vig, dtype=np.float32) for m in maps)

    return PhongLights(lx=tuple(m.lx for m in maps), ly=tuple(m.ly for m in maps), lz=tuple(m.lz for m in maps),
                       kd=fold(sh.diffuse, "att"), ks=fold(sh.specular, "att"), flat=fold(1.0, "flat"),
                       color=np.ascontiguousarray(color), shininess=float(sh.shininess),
                       specular=bool(sh.specular > 0))


def phong_change(gx: np.ndarray, gy: np.ndarray, lights: PhongLights, roi,
                 buffer: Callable[[str, tuple], np.ndarray]) -> np.ndarray:
    """The change over box ``roi`` (row and column slices of the maps) from its slopes ``gx, gy`` (float32
    ``(h, w)``, mm/mm): float32 ``(h, w, 3)`` DN. ``buffer(name, shape)``: float32 work arrays kept between
    frames (cv2 calls with preallocated outputs: numpy temporaries of a full frame cost page faults and
    were 3x slower here)."""
    shape = gx.shape
    nz, tmp = buffer("nz", shape), buffer("tmp", shape)
    cv2.multiply(gx, gx, nz)
    cv2.multiply(gy, gy, tmp)
    cv2.add(nz, tmp, nz)
    cv2.add(nz, 1.0, nz)
    cv2.sqrt(nz, nz)
    cv2.divide(1.0, nz, nz)
    spec = lights.specular
    if spec:
        nz2 = cv2.multiply(nz, 2.0, buffer("nz2", shape))
    d_l = []
    for i, (lx, ly, lz, kd, ks, flat) in enumerate(lights.lights()):
        ndl = buffer(f"ndl{i}", shape)
        cv2.multiply(gx, lx[roi], ndl)
        cv2.subtract(lz[roi], ndl, ndl)
        cv2.multiply(gy, ly[roi], tmp)
        cv2.subtract(ndl, tmp, ndl)
        cv2.multiply(ndl, nz, ndl)                  # n . l
        if spec:
            cv2.multiply(ndl, nz2, tmp)
            cv2.subtract(tmp, lz[roi], tmp)
            cv2.max(tmp, 0.0, tmp)
            cv2.pow(tmp, lights.shininess, tmp)
            cv2.multiply(tmp, ks[roi], tmp)
        cv2.max(ndl, 0.0, ndl)
        cv2.multiply(ndl, kd[roi], ndl)
        if spec:
            cv2.add(ndl, tmp, ndl)
        cv2.subtract(ndl, flat[roi], ndl)
        d_l.append(ndl)
    return mix_channels(d_l[0] if len(d_l) == 1 else cv2.merge(d_l), lights.color)


def phong_change_torch(gx, gy, lights: PhongLights):
    """:func:`phong_change` over whole frames: ``(B, 3, H, W)`` from slopes ``(B, H, W)`` and
    :meth:`PhongLights.to_torch` inputs. The highlight's power is taken in float64 and rounded to float32:
    the same value whichever kernel computes it."""
    torch = torch_module()
    nz = 1.0 / torch.sqrt(gx * gx + gy * gy + 1.0)
    dls = []
    for lx, ly, lz, kd, ks, flat in lights.lights():
        ndl = (lz - gx * lx - gy * ly) * nz
        dl = torch.clamp(ndl, min=0.0) * kd
        if lights.specular:
            r = torch.clamp(ndl * (nz * 2.0) - lz, min=0.0)
            dl = dl + (r.double() ** lights.shininess).float() * ks
        dls.append(dl - flat)
    return mix_channels_torch(dls, lights.color)
