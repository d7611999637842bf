"""The texture a run keeps, against its yardstick's: band RMS of the gel's relief and of the image's
texture over the yardstick's contact region (:func:`measure_texture`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GelsimError
from ..fidelity import Fidelity
from ..sensor import SensorProfile
from ..texture import RIM_SIGMAS, Band, band_for, band_rms, contact_region, pitches_mm, texture_frames
from .runs import LevelRun


@dataclass
class SceneTexture:
    """The texture of one run over the in-contact frames it pressed (``frames``, indices into the
    sequence): band RMS of the gel's relief (mm) and of the image's texture (DN; through the run's own
    renderer, and through the fast shader at the image's resolution, which separates the gel's part
    from the renderer's) per frame, NaN where not measured (no texture: the sphere; an empty region). A yardstick's also holds the regions
    the others are measured over (bool (n, H, W)): ``region``, the contact patch in the fabric's
    pitch band (:func:`gelsim.texture.contact_region`), and ``patch``, the apparent contact (for the
    markers in contact)."""
    frames: np.ndarray
    gel_rms: np.ndarray
    img_rms: np.ndarray
    region: np.ndarray | None = None
    patch: np.ndarray | None = None
    img_fast_rms: np.ndarray | None = None   # the image texture through the fast shader, DN


def texture_band(fabric, profile: SensorProfile) -> tuple[Band | None, float, float]:
    """(band or None for an object without texture, closing px, rim px) of the texture metric."""
    if fabric is None:
        return None, 1.0, 0.0
    mm = profile.image.mm_per_px
    band = band_for(fabric, min(profile.field_mm))
    return band, pitches_mm(fabric)[1] / mm, RIM_SIGMAS * band.sigmas_px(mm)[1]


def measure_texture(run: LevelRun, fabric, profile: SensorProfile, renderer,
                    yardstick: SceneTexture | None = None, shader=None) -> SceneTexture:
    """The texture of ``run`` (which kept its imprints) over the yardstick's regions, or, without a
    yardstick, over its own: then the result is a yardstick for other runs on this contact.
    ``renderer``: the run's own; ``shader``: the fast shader at supersample 1 (None: ``renderer`` is
    that already), for the image texture that only the gel changes."""
    band, close_px, rim_px = texture_band(fabric, profile)
    mm = profile.image.mm_per_px
    frames = np.array(sorted(run.imprints or {}), dtype=int) if yardstick is None else yardstick.frames
    gel = np.full(len(frames), np.nan)
    img = np.full(len(frames), np.nan)
    img_fast = np.full(len(frames), np.nan)
    regions, patches = [], []

    def image_rms(ren, depth, region):
        clean, macro = texture_frames(ren, depth, band, mm)
        return band_rms(clean.astype(np.float32) - macro.astype(np.float32), region, band, mm)

    for k, i in enumerate(frames):
        if int(i) not in (run.imprints or {}):
            raise GelsimError(f"frame {i} of the yardstick was not pressed by this run; compare runs on one contact")
        depth, mask = run.imprints[int(i)]
        if yardstick is None:
            region = contact_region(mask, close_px, rim_px) if band is not None else None
            regions.append(region)
            patches.append(contact_region(mask, close_px, 0.0))
        else:
            region = None if yardstick.region is None else yardstick.region[k]
        if band is not None and region.any():
            gel[k] = band_rms(depth, region, band, mm)
            img[k] = image_rms(renderer, depth, region)
            img_fast[k] = img[k] if shader is None else image_rms(shader, depth, region)
    if yardstick is not None:
        return SceneTexture(frames, gel, img, img_fast_rms=img_fast)
    shape = (len(frames), *profile.shape)
    return SceneTexture(frames, gel, img,
                        np.stack(regions) if band is not None and regions else None,
                        np.stack(patches) if patches else np.zeros(shape, bool), img_fast)


def fast_shader(profile: SensorProfile, fid: Fidelity, seed: int):
    """The fast shader at supersample 1 for a level whose own renderer is another (None if not)."""
    if fid.render_backend == "fast" and fid.supersample == 1:
        return None
    from ..optics import Renderer

    return Renderer(profile, "fast", supersample=1, seed=seed)
