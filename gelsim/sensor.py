"""Sensor profiles: every physical parameter of one GelSight sensor.

A profile is a TOML file under ``gelsim/assets/sensors/`` (or any path), one commented
file per sensor in the spirit of TACTO's ``config_digit.yml``. Units are in the
keys. It loads into the frozen :class:`SensorProfile`; sections:

* ``[image]``      camera resolution, mm per pixel, frame rate
* ``[gel]``        elastomer geometry and stiffness
* ``[markers]``    printed marker grid on the membrane
* ``[[lights]]``   the coloured LEDs at the rim
* ``[shading]``    membrane reflectance
* ``[background]`` the flat-gel image (non-uniform illumination)
* ``[noise]``      camera shot and read noise
* ``[camera]``     optics blur and vignetting
* ``[unit_variation]`` (optional) how much units of this model differ (:mod:`gelsim.units`)

Coordinates used across gelsim: the sensor frame has its origin at the image
centre, ``x`` to the right along image columns, ``y`` down along image rows,
``z`` out of the gel towards the touched object, all in millimetres. Image
arrays are ``(H, W)`` or ``(H, W, 3)`` with row index along ``y``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from .errors import GelsimError
from .params import ASSETS_DIR, build, check_ranges, load_toml, param

SENSORS_DIR = ASSETS_DIR / "sensors"


@dataclass(frozen=True)
class ImageSpec:
    width_px: int = param(lo=16, hi=8192, doc="image width in pixels")
    height_px: int = param(lo=16, hi=8192, doc="image height in pixels")
    mm_per_px: float = param(lo=1e-4, hi=1.0, lo_open=True, doc="size of one pixel on the gel, mm")
    fps_hz: float = param(30.0, lo=1.0, hi=1000.0, doc="camera frame rate, Hz")


@dataclass(frozen=True)
class GelSpec:
    thickness_mm: float = param(lo=0.1, hi=20.0, doc="elastomer thickness, mm")
    young_modulus_mpa: float = param(lo=1e-3, hi=100.0, doc="Young's modulus of the elastomer, MPa")
    poisson_ratio: float = param(lo=0.0, hi=0.5, doc="Poisson's ratio of the elastomer")
    max_indentation_mm: float = param(lo=0.01, hi=20.0, doc="deepest indentation before the pad bottoms out, mm")
    membrane_smoothing_mm: float = param(0.05, lo=0.0, hi=5.0,
                                         doc="length over which the coated membrane smooths sharp relief, mm")
    dome_radius_mm: float = param(0.0, lo=0.0, hi=1e5,
                                  doc="radius of curvature of the gel's domed surface, mm (its edges lie "
                                      "r^2 / 2R below the centre); 0 = flat")

    def sag_mm(self, x_mm, y_mm):
        """Height of the undeformed gel surface below its apex at sensor-frame points (mm, >= 0);
        0 for a flat gel. The paraboloid r^2 / 2R (a sphere's cap to < 0.1% at r / R < 0.15)."""
        return GelSpec.sag_mm_of(self.dome_radius_mm, x_mm, y_mm)

    @staticmethod
    def sag_mm_of(dome_radius_mm: float, x_mm, y_mm):
        """:meth:`sag_mm` of a gel whose dome has radius ``dome_radius_mm`` (0 = flat)."""
        if not dome_radius_mm:
            return 0.0 * (x_mm + y_mm)
        return (x_mm * x_mm + y_mm * y_mm) / (2.0 * dome_radius_mm)


@dataclass(frozen=True)
class MarkerSpec:
    enabled: bool = param(True, doc="draw markers at all")
    size_mm: float = param(0.4, lo=0.01, hi=5.0, doc="side (square) or diameter (disk) of a marker, mm")
    pitch_mm: float = param(1.6, lo=0.05, hi=20.0, doc="distance between neighbouring markers, mm")
    layout: Literal["square", "hex"] = param("square", doc="grid layout")
    shape: Literal["square", "disk"] = param("square", doc="marker shape")
    darkness: float = param(0.85, lo=0.0, hi=1.0, doc="fraction of the light a marker absorbs")
    jitter_mm: float = param(0.0, lo=0.0, hi=1.0, doc="random placement error of printed markers, mm")
    missing_fraction: float = param(0.0, lo=0.0, hi=0.5,
                                    doc="fraction of the printed grid's markers missing (not printed or worn off)")


@dataclass(frozen=True)
class LightSpec:
    name: str = param(doc="label, e.g. red")
    color_rgb: tuple[float, float, float] = param(doc="linear RGB colour of the LED, each 0-1")
    azimuth_deg: float = param(lo=-360.0, hi=360.0,
                               doc="direction the light comes FROM in the image plane: 0 = from +x (right), 90 = from +y (bottom)")
    elevation_deg: float = param(lo=0.0, hi=90.0, doc="angle of the light above the gel plane, degrees")
    intensity: float = param(1.0, lo=0.0, hi=100.0, doc="relative intensity")
    falloff_per_mm: float = param(0.0, lo=0.0, hi=10.0,
                                  doc="exponential decay of the LED's light across the gel, per mm from its rim")
    distance_mm: float = param(0.0, lo=0.0, hi=1000.0,
                               doc="distance of the LED from the gel centre in the gel plane, mm; it sits at "
                                   "elevation_deg seen from the centre, so the light's direction varies across "
                                   "the gel; 0 = just outside the image corners (the field's half-diagonal)")

    def validate(self, where: str) -> None:
        if any(not 0.0 <= c <= 1.0 for c in self.color_rgb):
            raise GelsimError(f"{where}.color_rgb: each component must be in 0-1 (linear), got {self.color_rgb}")


@dataclass(frozen=True)
class ShadingSpec:
    diffuse: float = param(1.0, lo=0.0, hi=10.0, doc="Lambertian gain of the membrane")
    specular: float = param(0.0, lo=0.0, hi=10.0, doc="specular gain")
    shininess: float = param(10.0, lo=1.0, hi=1000.0, doc="Phong exponent")
    gain_dn: float = param(120.0, lo=0.0, hi=1000.0, doc="image DN added per unit of (shading - flat shading)")
    model: Literal["phong", "lut"] = param("phong", doc="fast backend's shading: 'phong' from the lights above, "
                                                       "'lut' a table calibrated on real frames (`gelsim calibrate`)")
    table: str = param("", doc="shading table .npz for model 'lut', relative to the profile")
    channel_gain: tuple[float, float, float] = param(
        (1.0, 1.0, 1.0), lo=0.0, hi=10.0,
        doc="factor on each colour channel's shading change (R, G, B): one unit's LEDs brighter or dimmer "
            "than the calibrated one's; models 'lut' and 'phong'")
    channel_rotation_deg: tuple[float, float, float] = param(
        (0.0, 0.0, 0.0), lo=-180.0, hi=180.0,
        doc="rotation of each colour channel's LED about the gel normal (R, G, B), degrees, against the "
            "calibrated table (an LED mounted off its place); model 'lut' (phong: edit [[lights]] azimuth_deg)")

    def validate(self, where: str) -> None:
        if self.model == "lut" and not self.table:
            raise GelsimError(f"{where}: model 'lut' needs a table; name the .npz written by `gelsim calibrate`")


@dataclass(frozen=True)
class BackgroundSpec:
    rgb_dn: tuple[float, float, float] = param(doc="mean flat-gel colour, 0-255")
    led_tint_dn: float = param(30.0, lo=0.0, hi=255.0,
                               doc="extra brightness of each LED's colour near its own rim, 0-255")
    nonuniformity_dn: float = param(4.0, lo=0.0, hi=100.0,
                                    doc="amplitude (standard deviation) of the smooth random illumination field, 0-255")
    nonuniformity_scale_mm: float = param(3.0, lo=0.05, hi=1000.0, lo_open=True,
                                          doc="correlation length of the smooth random illumination field, mm")
    image: str = param("", doc="optional background image (PNG, relative to the profile) replacing the parametric field")
    image_resample: Literal["area", "linear"] = param(
        "area", doc="how the image is brought to the profile's size: 'area' (OpenCV INTER_AREA: pixel "
                    "replication when enlarging) or 'linear' (bilinear, for a smooth downsampled field)")
    gain: float = param(1.0, lo=0.05, hi=10.0, doc="factor on the whole flat-gel image (image or parametric): "
                                                   "the camera's exposure, with [shading] gain_dn for the shading")


@dataclass(frozen=True)
class NoiseSpec:
    read_sigma_dn: float = param(1.5, lo=0.0, hi=50.0, doc="Gaussian read noise, DN (0-255)")
    shot_gain: float = param(0.03, lo=0.0, hi=5.0, doc="shot-noise variance per DN of signal")


@dataclass(frozen=True)
class CameraSpec:
    blur_sigma_px: float = param(0.0, lo=0.0, hi=20.0, doc="Gaussian blur of the lens, px")
    vignetting: float = param(0.0, lo=0.0, hi=1.0, doc="brightness lost at the image corners, fraction")


@dataclass(frozen=True)
class UnitVariationSpec:
    """How much units of one sensor model differ (``[unit_variation]``): the ranges that
    :func:`gelsim.units.draw_unit` draws one unit from, uniformly. Fractions are relative
    (``0.1`` = +-10%), the rest absolute; each range's source or reason sits beside it in the
    profile. All default to 0 (no variation)."""
    led_intensity_frac: float = param(0.0, lo=0.0, hi=0.9, doc="each LED's brightness, +-fraction")
    led_color_frac: float = param(0.0, lo=0.0, hi=0.9, doc="each component of each LED's colour, +-fraction")
    led_azimuth_deg: float = param(0.0, lo=0.0, hi=45.0, doc="each LED's direction about the gel normal, +-degrees")
    led_elevation_deg: float = param(0.0, lo=0.0, hi=30.0, doc="each LED's elevation, +-degrees (lights only)")
    background_offset_dn: float = param(0.0, lo=0.0, hi=60.0,
                                        doc="flat-gel colour per channel, +-DN (parametric background)")
    background_nonuniformity_frac: float = param(0.0, lo=0.0, hi=0.9,
                                                 doc="amplitude of the illumination's blotches, +-fraction")
    gel_thickness_frac: float = param(0.0, lo=0.0, hi=0.5, doc="elastomer thickness, +-fraction")
    gel_modulus_frac: float = param(0.0, lo=0.0, hi=0.9, doc="elastomer Young's modulus, +-fraction")
    marker_size_frac: float = param(0.0, lo=0.0, hi=0.5, doc="marker size, +-fraction")
    marker_pitch_frac: float = param(0.0, lo=0.0, hi=0.2, doc="marker pitch, +-fraction")
    marker_jitter_mm: float = param(0.0, lo=0.0, hi=0.5, doc="printing jitter added to the profile's, 0 to this, mm")
    marker_missing_max: float = param(0.0, lo=0.0, hi=0.5, doc="fraction of markers missing, 0 to this")
    read_noise_frac: float = param(0.0, lo=0.0, hi=0.9, doc="camera read noise, +-fraction")
    blur_px: float = param(0.0, lo=0.0, hi=5.0, doc="lens blur added to the profile's, 0 to this, px (sigma)")
    exposure_frac: float = param(0.0, lo=0.0, hi=0.5,
                                 doc="camera exposure: the whole image's brightness, +-fraction")
    dome_radius_frac: float = param(0.0, lo=0.0, hi=0.5, doc="the gel dome's radius of curvature, +-fraction "
                                                             "(a flat gel stays flat)")


@dataclass(frozen=True)
class SensorProfile:
    name: str
    image: ImageSpec
    gel: GelSpec
    markers: MarkerSpec
    lights: tuple[LightSpec, ...]
    shading: ShadingSpec
    background: BackgroundSpec
    noise: NoiseSpec
    camera: CameraSpec
    description: str = ""
    unit_variation: UnitVariationSpec | None = None   # ranges of one unit's parameters (gelsim.units)
    source: str = ""  # file the profile was loaded from (set by load_profile)

    def validate(self, where: str) -> None:
        if len(self.lights) == 0:
            raise GelsimError(f"{where}: a profile needs at least one [[lights]] entry")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` in pixels."""
        return (self.image.height_px, self.image.width_px)

    @property
    def field_mm(self) -> tuple[float, float]:
        """Field of view ``(width, height)`` on the gel in mm."""
        return (self.image.width_px * self.image.mm_per_px, self.image.height_px * self.image.mm_per_px)

    def resolution_range(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """The smallest and largest ``(width, height)`` px this sensor can be imaged at over its field
        (:meth:`with_resolution`): at most ImageSpec's largest mm per pixel and its pixel counts, the
        smallest at the profile's aspect ratio."""
        fw, _ = self.field_mm
        lo_w = max(int(_limit("width_px", "lo")), math.ceil(fw / _limit("mm_per_px", "hi") - 1e-9))
        lo_h = max(int(_limit("height_px", "lo")), math.ceil(lo_w * self.image.height_px / self.image.width_px))
        return (lo_w, lo_h), (int(_limit("width_px", "hi")), int(_limit("height_px", "hi")))

    def with_resolution(self, width_px: int, height_px: int | None = None) -> "SensorProfile":
        """The same sensor (same field of view in mm) imaged at another resolution.

        ``height_px`` defaults to keeping the aspect ratio. Used for reduced-size
        datasets and tests; every parameter in mm stays the same.
        """
        (lo_w, lo_h), (hi_w, hi_h) = self.resolution_range()
        if height_px is None:
            height_px = max(lo_h, round(width_px * self.image.height_px / self.image.width_px))
        if not (lo_w <= width_px <= hi_w and lo_h <= height_px <= hi_h):
            raise GelsimError(f"resolution {width_px}x{height_px} is out of range for {self.name}; give {lo_w}x{lo_h} "
                              f"to {hi_w}x{hi_h} px (its {self.field_mm[0]:.1f} mm field at most "
                              f"{_limit('mm_per_px', 'hi'):g} mm per pixel)")
        scale = self.image.width_px / width_px
        image = dataclasses.replace(self.image, width_px=int(width_px), height_px=int(height_px),
                                    mm_per_px=self.image.mm_per_px * scale)
        check_ranges(image, f"{self.name} at {width_px}x{height_px} px")
        return dataclasses.replace(self, image=image)


def _limit(name: str, bound: str) -> float:
    """ImageSpec's declared bound (``"lo"`` or ``"hi"``) of its field ``name``."""
    return next(f for f in dataclasses.fields(ImageSpec) if f.name == name).metadata[bound]


def list_profiles() -> list[str]:
    """Names of the profiles shipped in ``gelsim/assets/sensors/``."""
    return sorted(p.stem for p in SENSORS_DIR.glob("*.toml"))


def resolve_profile_path(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise GelsimError(f"sensor profile file {p} not found; give an existing .toml or one of: "
                              + ", ".join(list_profiles()))
        return p
    p = SENSORS_DIR / f"{name_or_path}.toml"
    if not p.exists():
        raise GelsimError(f"unknown sensor profile {str(name_or_path)!r}; choose one of "
                          + ", ".join(list_profiles()) + " or give a path to a .toml file")
    return p


def load_profile(name_or_path: str | Path = "vitac") -> SensorProfile:
    """Load a sensor profile by name (``vitac``, ``gelsight-r15``) or TOML path."""
    path = resolve_profile_path(name_or_path)
    data = load_toml(path)
    data.setdefault("name", path.stem)
    prof = build(SensorProfile, data, where=path.name)
    return dataclasses.replace(prof, source=str(path))
