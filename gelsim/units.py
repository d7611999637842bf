"""Per-unit randomisation: one unit of a sensor model, drawn from the profile's ``[unit_variation]``.

Units of one model differ: LEDs are brighter or dimmer and sit a little off their places, gels
are cast thicker or softer, markers are printed larger, further apart or not at all, cameras
differ in noise, focus and exposure. A model learned on one unit's images can fail on the next.
:func:`draw_unit` returns the profile of one such unit, drawn uniformly from the ranges of
:class:`gelsim.sensor.UnitVariationSpec` (each range's source or reason is in the profile), and
:func:`unit_record` the parameters that vary, for a dataset's labels.

What a draw changes, per shading model:

* LED intensity: ``[[lights]] intensity`` (phong, pyrender) and ``[shading] channel_gain`` of the
  LED's colour channel (calibrated table, phong), each LED on its own;
* LED colour: each component of ``[[lights]] color_rgb`` (phong, pyrender, the parametric
  background's LED tint); a calibrated table keeps its measured colours;
* LED direction: ``[[lights]] azimuth_deg`` and ``elevation_deg`` (phong, pyrender), and
  ``[shading] channel_rotation_deg`` (the table turned per channel, with its shadows);
* background: ``rgb_dn`` offset per channel and the blotches' amplitude (parametric background;
  a measured background image keeps its pattern);
* gel: ``thickness_mm``, ``young_modulus_mpa`` and ``dome_radius_mm`` (0, flat, stays flat);
* markers: ``size_mm``, ``pitch_mm``, extra ``jitter_mm`` and ``missing_fraction``;
* camera: ``read_sigma_dn``, extra ``blur_sigma_px``, and the exposure, a factor on both
  ``[background] gain`` and ``[shading] gain_dn``.

Draws come from ``numpy.random.default_rng([seed, UNIT_STREAM])`` in a fixed order, whatever
ranges are zero, so one seed gives one unit and changing one range leaves the other draws.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .errors import GelsimError
from .params import check_ranges
from .sensor import SensorProfile, UnitVariationSpec

UNIT_STREAM = 0x0D17     # a stream of its own, apart from the noise and jitter streams of the same seed


def _uniform(rng: np.random.Generator, half_width: float, n: int | tuple = 1) -> np.ndarray:
    """Uniform in ``[-half_width, half_width]`` (always ``n`` draws, so the stream's order is fixed)."""
    return rng.uniform(-1.0, 1.0, n) * half_width


def draw_unit(profile: SensorProfile, seed: int) -> SensorProfile:
    """One unit of ``profile``'s sensor model: a profile with the ``[unit_variation]`` draws applied.

    ``seed``: int, the unit (same seed, same unit). A profile without ``[unit_variation]`` (or with
    all ranges 0) comes back unchanged. The returned profile keeps the section (so a unit can be
    told from its model) and is named ``<name>#unit<seed>``."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise GelsimError(f"unit seed {seed!r} is not an integer; give an int")
    v = profile.unit_variation
    if v is None:
        return profile
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, UNIT_STREAM])
    nl = len(profile.lights)
    d_int = _uniform(rng, v.led_intensity_frac, nl)
    d_col = _uniform(rng, v.led_color_frac, (nl, 3))
    d_az = _uniform(rng, v.led_azimuth_deg, nl)
    d_el = _uniform(rng, v.led_elevation_deg, nl)
    d_bg = _uniform(rng, v.background_offset_dn, 3)
    d_blot = float(_uniform(rng, v.background_nonuniformity_frac)[0])
    d_thick = float(_uniform(rng, v.gel_thickness_frac)[0])
    d_mod = float(_uniform(rng, v.gel_modulus_frac)[0])
    d_size = float(_uniform(rng, v.marker_size_frac)[0])
    d_pitch = float(_uniform(rng, v.marker_pitch_frac)[0])
    d_jit = float(rng.uniform(0.0, 1.0)) * v.marker_jitter_mm
    d_miss = float(rng.uniform(0.0, 1.0)) * v.marker_missing_max
    d_read = float(_uniform(rng, v.read_noise_frac)[0])
    d_blur = float(rng.uniform(0.0, 1.0)) * v.blur_px
    d_exp = float(_uniform(rng, v.exposure_frac)[0])
    d_dome = float(_uniform(rng, v.dome_radius_frac)[0])    # drawn last: added after the others

    lights = []
    ch_gain = [1.0, 1.0, 1.0]
    ch_rot = [0.0, 0.0, 0.0]
    for k, lt in enumerate(profile.lights):
        col = tuple(float(np.clip(c * (1.0 + d), 0.0, 1.0)) for c, d in zip(lt.color_rgb, d_col[k]))
        el = float(np.clip(lt.elevation_deg + d_el[k], 0.0, 90.0))
        lights.append(dataclasses.replace(lt, intensity=lt.intensity * (1.0 + float(d_int[k])), color_rgb=col,
                                          azimuth_deg=lt.azimuth_deg + float(d_az[k]), elevation_deg=el))
        if max(lt.color_rgb) > 0:
            c = int(np.argmax(lt.color_rgb))           # the colour channel this LED drives
            ch_gain[c] *= 1.0 + float(d_int[k])
            ch_rot[c] += float(d_az[k])
    sh = profile.shading
    shading = dataclasses.replace(
        sh, gain_dn=sh.gain_dn * (1.0 + d_exp),
        channel_gain=tuple(g * cg for g, cg in zip(sh.channel_gain, ch_gain)),
        channel_rotation_deg=tuple(float((r + cr + 180.0) % 360.0 - 180.0)
                                   for r, cr in zip(sh.channel_rotation_deg, ch_rot)))
    bg = profile.background
    background = dataclasses.replace(
        bg, rgb_dn=tuple(float(np.clip(c + float(d), 0.0, 255.0)) for c, d in zip(bg.rgb_dn, d_bg)),
        nonuniformity_dn=bg.nonuniformity_dn * (1.0 + d_blot), gain=bg.gain * (1.0 + d_exp))
    gel = dataclasses.replace(profile.gel, thickness_mm=profile.gel.thickness_mm * (1.0 + d_thick),
                              young_modulus_mpa=profile.gel.young_modulus_mpa * (1.0 + d_mod),
                              dome_radius_mm=profile.gel.dome_radius_mm * (1.0 + d_dome))
    mk = profile.markers
    markers = dataclasses.replace(mk, size_mm=mk.size_mm * (1.0 + d_size), pitch_mm=mk.pitch_mm * (1.0 + d_pitch),
                                  jitter_mm=mk.jitter_mm + d_jit, missing_fraction=min(0.5, mk.missing_fraction + d_miss))
    noise = dataclasses.replace(profile.noise, read_sigma_dn=profile.noise.read_sigma_dn * (1.0 + d_read))
    camera = dataclasses.replace(profile.camera, blur_sigma_px=profile.camera.blur_sigma_px + d_blur)
    where = f"{profile.name} unit {seed}"
    for section in (shading, background, gel, markers, noise, camera, *lights):
        check_ranges(section, where)
    return dataclasses.replace(profile, name=f"{profile.name}#unit{int(seed)}", lights=tuple(lights), shading=shading,
                               background=background, gel=gel, markers=markers, noise=noise, camera=camera)


def unit_record(profile: SensorProfile) -> dict:
    """The parameters a unit draw changes, as plain data (for labels and ``--json``): per LED
    ``intensity``, ``color_rgb``, ``azimuth_deg``, ``elevation_deg``; ``channel_gain``,
    ``channel_rotation_deg``, ``shading_gain_dn``; background ``rgb_dn``, ``nonuniformity_dn``,
    ``gain``; gel ``thickness_mm``, ``young_modulus_mpa``, ``dome_radius_mm``; markers ``size_mm``, ``pitch_mm``,
    ``jitter_mm``, ``missing_fraction``; ``read_sigma_dn``; ``blur_sigma_px``."""
    return {
        "profile": profile.name,
        "lights": [{"name": lt.name, "intensity": lt.intensity, "color_rgb": list(lt.color_rgb),
                    "azimuth_deg": lt.azimuth_deg, "elevation_deg": lt.elevation_deg} for lt in profile.lights],
        "channel_gain": list(profile.shading.channel_gain),
        "channel_rotation_deg": list(profile.shading.channel_rotation_deg),
        "shading_gain_dn": profile.shading.gain_dn,
        "background_rgb_dn": list(profile.background.rgb_dn),
        "background_nonuniformity_dn": profile.background.nonuniformity_dn,
        "background_gain": profile.background.gain,
        "gel_thickness_mm": profile.gel.thickness_mm,
        "gel_young_modulus_mpa": profile.gel.young_modulus_mpa,
        "gel_dome_radius_mm": profile.gel.dome_radius_mm,
        "marker_size_mm": profile.markers.size_mm,
        "marker_pitch_mm": profile.markers.pitch_mm,
        "marker_jitter_mm": profile.markers.jitter_mm,
        "marker_missing_fraction": profile.markers.missing_fraction,
        "read_sigma_dn": profile.noise.read_sigma_dn,
        "blur_sigma_px": profile.camera.blur_sigma_px,
    }


def variation_ranges(profile: SensorProfile) -> dict | None:
    """The profile's ``[unit_variation]`` ranges as plain data (None without the section)."""
    v = profile.unit_variation
    return None if v is None else {f.name: getattr(v, f.name) for f in dataclasses.fields(UnitVariationSpec)}
