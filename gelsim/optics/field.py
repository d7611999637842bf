"""Light geometry and the flat-gel image shared by every rendering backend.

Each LED of the profile is a point source at the rim: ``distance_mm`` from the
gel centre along its azimuth, at a height that puts it at ``elevation_deg`` seen
from the centre. So, as in a real GelSight, a pixel near an LED sees it higher
in the sky and brighter than a pixel on the far side.

Directions here are in the *viewing frame*: ``x`` right (image columns), ``y``
down (image rows), ``z`` towards the camera. The camera looks through the gel at
the membrane, so an imprint (depth pushed into the gel) is a height towards the
camera. All maps are float32 at the profile's resolution.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import GelsimError


def pixel_grid_mm(profile) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates ``(x, y)`` in mm from the image centre, float32 ``(1, W)`` and ``(H, 1)``."""
    h, w = profile.shape
    mm = profile.image.mm_per_px
    x = ((np.arange(w, dtype=np.float32) - (w - 1) / 2.0) * mm)[None, :]
    y = ((np.arange(h, dtype=np.float32) - (h - 1) / 2.0) * mm)[:, None]
    return x, y


def led_distance_mm(light, profile) -> float:
    """In-plane distance of an LED from the gel centre, mm (``distance_mm`` or the field's half-diagonal)."""
    if light.distance_mm > 0:
        return float(light.distance_mm)
    fw, fh = profile.field_mm
    return 0.5 * math.hypot(fw, fh)


def led_position_mm(light, profile) -> np.ndarray:
    """LED position ``(x, y, z)`` in the viewing frame, mm (float64 ``(3,)``)."""
    r = led_distance_mm(light, profile)
    a = math.radians(light.azimuth_deg)
    return np.array([r * math.cos(a), r * math.sin(a), r * math.tan(math.radians(light.elevation_deg))])


@dataclass
class LightMaps:
    """Per-pixel geometry of one LED over the flat gel (float32 ``(H, W)`` maps)."""
    lx: np.ndarray          # unit vector from the surface to the LED
    ly: np.ndarray
    lz: np.ndarray
    att: np.ndarray         # relative irradiance, intensity * exp(-falloff * (d - d_centre)); 1 x intensity at centre
    flat: np.ndarray        # shading of the flat gel: att * (diffuse * lz + specular * lz^shininess)
    color: np.ndarray       # float32 (3,) linear RGB 0-1


def light_maps(profile) -> list[LightMaps]:
    """Geometry and flat shading of every light of ``profile``."""
    x, y = pixel_grid_mm(profile)
    sh = profile.shading
    out = []
    for light in profile.lights:
        p = led_position_mm(light, profile).astype(np.float32)
        dx, dy = p[0] - x, p[1] - y                       # (1, W), (H, 1) broadcast to (H, W)
        d_plane = np.sqrt(dx * dx + dy * dy)
        inv = 1.0 / np.sqrt(d_plane * d_plane + p[2] * p[2])
        lx, ly, lz = dx * inv, dy * inv, p[2] * inv
        lx, ly, lz = (np.ascontiguousarray(np.broadcast_to(v, profile.shape), dtype=np.float32)
                      for v in (lx, ly, lz))
        d_centre = float(math.hypot(p[0], p[1]))
        att = (light.intensity * np.exp(-light.falloff_per_mm * (d_plane - d_centre))).astype(np.float32)
        # Flat membrane: n = z, so n.l = lz and the mirror direction's z-component is lz too.
        flat = att * (sh.diffuse * lz + sh.specular * np.power(lz, sh.shininess))
        out.append(LightMaps(lx, ly, lz, att, flat.astype(np.float32),
                             np.asarray(light.color_rgb, dtype=np.float32)))
    return out


def flat_shading_rgb(maps: list[LightMaps]) -> np.ndarray:
    """Per-channel shading of the flat gel, sum_i colour_i * flat_i: float32 ``(H, W, 3)``."""
    return sum(m.flat[..., None] * m.color[None, None, :] for m in maps).astype(np.float32)


def vignetting_map(profile) -> np.ndarray:
    """Relative brightness, 1 at the centre down to ``1 - vignetting`` at the corners: float32 ``(H, W)``."""
    x, y = pixel_grid_mm(profile)
    fw, fh = profile.field_mm
    r2 = (x * x + y * y) / ((fw / 2) ** 2 + (fh / 2) ** 2)
    # Quadratic in radius: the leading term of the cos^4 law for small field angles.
    return np.ascontiguousarray(1.0 - profile.camera.vignetting * r2, dtype=np.float32)


def smooth_random_field(profile, seed: int) -> np.ndarray:
    """Zero-mean, unit-std smooth random field with correlation length ``nonuniformity_scale_mm``: float32 ``(H, W)``."""
    h, w = profile.shape
    fw, fh = profile.field_mm
    scale = profile.background.nonuniformity_scale_mm
    gh, gw = max(2, math.ceil(fh / scale) + 1), max(2, math.ceil(fw / scale) + 1)
    rng = np.random.default_rng([seed, 0x0b6])
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    field = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    field -= field.mean()
    std = float(field.std())
    return field / std if std > 0 else field


def _background_image(profile) -> np.ndarray:
    """The profile's background PNG (path relative to the profile file) as float32 RGB ``(H, W, 3)``."""
    spec = profile.background.image
    base = Path(profile.source).parent if profile.source else Path.cwd()
    path = Path(spec) if Path(spec).is_absolute() else base / spec
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise GelsimError(f"background image {path} cannot be read; give a PNG path relative to the profile")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return resize_background(img.astype(np.float32), profile.shape, profile.background.image_resample)


def resize_background(img: np.ndarray, shape: tuple[int, int], resample: str = "area") -> np.ndarray:
    """A background image at ``shape`` (H, W): ``"area"`` (OpenCV's INTER_AREA, which replicates
    pixels when enlarging) or ``"linear"`` (bilinear when enlarging, area when shrinking)."""
    h, w = shape
    if img.shape[:2] == (h, w):
        return img
    shrink = img.shape[0] > h or img.shape[1] > w
    interp = cv2.INTER_AREA if resample == "area" or shrink else cv2.INTER_LINEAR
    return cv2.resize(img, (w, h), interpolation=interp)


def background_float(profile, maps: list[LightMaps], seed: int) -> np.ndarray:
    """The flat gel as the camera sees it, before markers and noise: float32 ``(H, W, 3)``, DN 0-255.

    ``rgb_dn`` plus, for each LED, ``led_tint_dn`` times its colour following its
    flat-gel irradiance (so each LED's colour is brighter near its own rim),
    plus a smooth random illumination field; then vignetting. Without
    vignetting the mean over the image is ``rgb_dn``. A ``background.image``
    (a real flat frame) replaces all of it, vignetting included, since the
    frame already contains its sensor's vignetting; ``camera.vignetting`` then
    still shapes the shading change. ``background.gain`` (exposure) multiplies either.
    """
    bg_spec = profile.background
    if bg_spec.image:
        img = _background_image(profile)
        return img if bg_spec.gain == 1.0 else img * np.float32(bg_spec.gain)
    h, w = profile.shape
    bg = np.empty((h, w, 3), np.float32)
    bg[:] = np.asarray(bg_spec.rgb_dn, np.float32)
    for m in maps:
        rng_ = float(m.flat.max() - m.flat.min())
        if rng_ > 0 and bg_spec.led_tint_dn > 0:
            tint = (m.flat - m.flat.mean()) * (bg_spec.led_tint_dn / rng_)
            bg += tint[..., None] * m.color[None, None, :]
    if bg_spec.nonuniformity_dn > 0:
        bg += (bg_spec.nonuniformity_dn * smooth_random_field(profile, seed))[..., None]
    bg *= vignetting_map(profile)[..., None]
    if bg_spec.gain != 1.0:
        bg *= np.float32(bg_spec.gain)
    return bg
