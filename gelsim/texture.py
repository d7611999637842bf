"""How much of a fabric's texture reaches the image: a budget, stage by stage, in the fabric's band.

One press of a catalog fabric on the sensor (the dataset's profile and fidelity), followed through
the pipeline:

1. **fabric**: the relief of the pressed cloth (its protrusion map), in mm;
2. **gel**: the relief of the gel's surface (the imprint's depth map) and its slopes; the ratio to
   the fabric's is the relief the gel keeps;
3. **image**: the texture's contrast in the rendered frame (no noise, no markers; the frame minus
   that of the same imprint smoothed beyond the band, so that only the texture counts), DN, against
   the camera noise in the same band;
4. **H.264**: both again after the dataset's codec (the frames a classifier is given).

Every quantity is taken in the fabric's **pitch band**: spatial wavelengths from half its finest pitch
to twice its coarsest (:func:`band_for`), by a difference of Gaussians, and over the contact (the
apparent contact patch, eroded by a pitch so that its rim, where the imprint's own shading is
strongest, stays out). Image contrast is the RMS over pixels and the three colour channels: each
channel answers to its own LED, and a grey average of three LEDs 120 degrees apart cancels a slope's
first-order response, so it would hide the texture (measured: 8x less on a denim twill).

Used by ``gelsim texture``, ``gelsim bench`` (texture-scale errors) and the tests.
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .errors import GelsimError
from .scene import press_properties

# A Gaussian low-pass of width sigma passes half the power at f = sqrt(ln 2 / 2) / (pi sigma).
_HALF_POWER = math.sqrt(math.log(2.0) / 2.0) / math.pi
# The band spans an octave beyond the pitches on each side: the weave's fundamentals and its first
# harmonics, not the cloth's waviness nor the pixel noise.
BAND_OCTAVES = 1.0
# The region keeps clear of the contact's rim by this many widths of the band's wide Gaussian: the
# rim's strong, smooth shading (the dome's edge) leaks into the band over about that far.
RIM_SIGMAS = 2.0
# Frames per clip when measuring after the codec: the middle one is a predicted (P) frame, as most
# of a sequence's frames are.
CODEC_FRAMES = 5
# The outcome the texture issue asks for: contrast in the pitch band at least this many times the
# noise in that band.
VISIBLE_SNR = 3.0


@dataclass(frozen=True)
class Band:
    """Spatial band, by wavelength: from ``fine_mm`` (shortest) to ``coarse_mm`` (longest)."""
    fine_mm: float
    coarse_mm: float

    def sigmas_px(self, mm_per_px: float) -> tuple[float, float]:
        """(narrow, wide) Gaussian widths in px whose difference passes the band."""
        return _HALF_POWER * self.fine_mm / mm_per_px, _HALF_POWER * self.coarse_mm / mm_per_px


def pitches_mm(fabric) -> tuple[float, float]:
    """(finest, coarsest) structural pitch of a catalog fabric, mm: warp and weft pitches (a basket's
    groups), a corduroy's tuft rows and wales, a felt's or leather's feature size."""
    fam = fabric.family
    if fam in ("velvet", "felt", "fleece", "leather", "suede"):
        p = [fabric.feature_mm]
        if getattr(fabric, "pore_spacing_mm", None):
            p.append(fabric.pore_spacing_mm)
    else:
        p = [v for v in (fabric.warp_pitch_mm, fabric.weft_pitch_mm) if v]
        if fam == "basket":
            p.append(max(p) * fabric.basket_group)
    return float(min(p)), float(max(p))


def band_for(fabric, field_mm: float | None = None) -> Band:
    """The fabric's pitch band, its coarse end capped at a quarter of ``field_mm`` (if given)."""
    lo, hi = pitches_mm(fabric)
    coarse = hi * 2.0 ** BAND_OCTAVES
    if field_mm:
        coarse = min(coarse, field_mm / 4.0)
    return Band(lo / 2.0 ** BAND_OCTAVES, max(coarse, lo))


def bandpass(img: np.ndarray, band: Band, mm_per_px: float) -> np.ndarray:
    """``img`` (H, W) or (H, W, C) in the band (float32, difference of Gaussians)."""
    s1, s2 = band.sigmas_px(mm_per_px)
    a = np.asarray(img, np.float32)
    lo = cv2.GaussianBlur(a, (0, 0), s2, borderType=cv2.BORDER_REFLECT)
    hi = cv2.GaussianBlur(a, (0, 0), s1, borderType=cv2.BORDER_REFLECT) if s1 >= 0.3 else a
    return hi - lo


def band_rms(img: np.ndarray, region: np.ndarray, band: Band, mm_per_px: float) -> float:
    """RMS of ``img`` in the band over ``region`` (bool (H, W)); over pixels and channels."""
    bp = bandpass(img, band, mm_per_px)
    if not region.any():
        return float("nan")
    v = bp[region]
    return float(np.sqrt(np.mean(v.astype(np.float64) ** 2)))


def contact_region(contact_mask: np.ndarray, texture_px: float, rim_px: float) -> np.ndarray:
    """The apparent contact patch (the touching crowns closed over ``texture_px``, the fabric's
    coarsest pitch), eroded by ``rim_px``: bool (H, W)."""
    k = max(1, int(round(texture_px)))
    app = cv2.morphologyEx(contact_mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    r = max(1, int(round(rim_px)))
    return cv2.erode(app, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def texture_frames(renderer, depth_mm: np.ndarray, band: Band, mm_per_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The noiseless, markerless frames (uint8 (H, W, 3)) of ``depth_mm`` (mm, (H, W)) and of the same
    depth smoothed beyond the band. Their difference is the texture's own share of the image: the
    contact's smooth shading (the dome's rim) and the background's illumination field, both partly
    in a coarse band, cancel in it."""
    smooth = cv2.GaussianBlur(depth_mm, (0, 0), band.sigmas_px(mm_per_px)[1], borderType=cv2.BORDER_REFLECT)
    return renderer.render(depth_mm, None, noise=False), renderer.render(smooth, None, noise=False)


@dataclass
class TextureBudget:
    """One fabric, one force: the texture at each stage (see the module docstring). Lengths mm,
    image values DN (0-255), ratios dimensionless; ``snr`` = contrast / noise in the band."""
    fabric_id: int
    family: str
    force_n: float
    band_mm: tuple[float, float]
    contact_mm2: float
    region_mm2: float
    fabric_relief_mm: float
    gel_relief_mm: float
    kept: float
    gel_slope_rms: float
    gel_slope_p95: float
    image_dn: float
    image_dn_rgb: tuple[float, float, float]
    noise_dn: float
    snr: float
    codec_image_dn: float | None = None
    codec_noise_dn: float | None = None
    codec_snr: float | None = None
    timings_s: dict = field(default_factory=dict)

    @property
    def visible(self) -> bool:
        """The outcome's test: contrast at least VISIBLE_SNR x the noise (after the codec if measured)."""
        snr = self.codec_snr if self.codec_snr is not None else self.snr
        return bool(snr >= VISIBLE_SNR)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["visible"] = self.visible
        return d


def _codec(frames: list[np.ndarray], fps: float) -> list[np.ndarray]:
    """Frames through the dataset's H.264 settings and back."""
    from .video import read_video, write_video

    with tempfile.TemporaryDirectory(prefix="gelsim-texture-") as d:
        path = write_video(Path(d) / "clip.mp4", frames, fps=fps, fmt="h264")
        return list(read_video(path))


def texture_budget(fabric, force_n: float, profile, fidelity, *, seed: int = 0, codec: bool = True,
                   renderer=None, frame: bool = False):
    """The texture budget of ``fabric`` pressed flat at ``force_n`` (N) on ``profile`` at ``fidelity``.

    ``frame``: also return the frame as the dataset holds it (markers, noise, after the codec if
    ``codec``): uint8 (H, W, 3) RGB; the result is then (TextureBudget, frame)."""
    import time

    from .fabrics import heightfield
    from .optics import Renderer
    from .stream import FrameRequest, FrameSetup, Touch, make_frames

    if not (math.isfinite(force_n) and force_n > 0):
        raise GelsimError(f"force {force_n} N must be a positive number; give e.g. --force-n 3")
    t0 = time.perf_counter()
    times = {}
    h, w = profile.shape
    mm = profile.image.mm_per_px
    prot = heightfield(fabric, x0_mm=-(w - 1) / 2 * mm, y0_mm=-(h - 1) / 2 * mm, width_px=w, height_px=h,
                       mm_per_px=mm, seed=seed, rotation_deg=fabric.orientation_deg)
    times["fabric"] = time.perf_counter() - t0
    # The press (and, for ``frame``, the frame as the dataset holds it: markers, noise) through the frame pipeline:
    # one touch, pressed once, its frame rendered with each of the clip's noise draws.
    touch = Touch(prot, force_n=force_n, properties=press_properties(fabric))
    ren = renderer or Renderer(profile, "fast", seed=0)
    if frame:
        shots = np.random.default_rng(seed + 1)
        setup = FrameSetup.make(profile, fidelity, sensor_seed=0, renderer=ren)
        made = make_frames([FrameRequest(touch, shots)] * (CODEC_FRAMES if codec else 1), setup)
    else:
        made = make_frames([FrameRequest(touch)], FrameSetup(profile, fidelity))
    im = made.parts[0].imprint
    times["imprint"] = made.seconds["imprint"]
    band = band_for(fabric, min(profile.field_mm))
    _, coarse = pitches_mm(fabric)
    region = contact_region(im.contact_mask, coarse / mm, RIM_SIGMAS * band.sigmas_px(mm)[1])
    fab_rel = band_rms(prot, region, band, mm)
    gel_rel = band_rms(im.depth_mm, region, band, mm)
    gy, gx = np.gradient(bandpass(im.depth_mm, band, mm), mm)
    slope = np.hypot(gx, gy)[region] if region.any() else np.array([np.nan])
    t0 = time.perf_counter()
    clean, macro = texture_frames(ren, im.depth_mm, band, mm)
    flat = ren.render(None, None, noise=False)
    rng = np.random.default_rng(seed)
    noise_only = [ren.render(None, None, seed=rng) for _ in range(CODEC_FRAMES)]
    times["optics"] = time.perf_counter() - t0
    tex_img = clean.astype(np.float32) - macro.astype(np.float32)
    img = band_rms(tex_img, region, band, mm)
    rgb = tuple(band_rms(tex_img[..., c], region, band, mm) for c in range(3))
    noise = band_rms(noise_only[0].astype(np.float32) - flat.astype(np.float32), region, band, mm)
    out = TextureBudget(fabric.id, fabric.family, float(force_n), (band.fine_mm, band.coarse_mm),
                        im.contact_area_mm2, float(region.sum()) * mm * mm, fab_rel, gel_rel,
                        gel_rel / fab_rel if fab_rel > 0 else float("nan"),
                        float(np.sqrt(np.mean(slope.astype(np.float64) ** 2))), float(np.percentile(slope, 95)),
                        img, rgb, noise, img / noise if noise > 0 else float("inf"))
    if codec:
        # The same differences after the codec, each clip a held frame (noise alone varies, as in a
        # sequence; the middle frame is a predicted one).
        t0 = time.perf_counter()
        mid = CODEC_FRAMES // 2
        fps = profile.image.fps_hz

        def coded(frames):
            return _codec(frames, fps)[mid].astype(np.float32)

        ci = band_rms(coded([clean] * CODEC_FRAMES) - coded([macro] * CODEC_FRAMES), region, band, mm)
        cn = band_rms(coded(noise_only) - coded([flat] * CODEC_FRAMES), region, band, mm)
        out.codec_image_dn = ci
        out.codec_noise_dn = cn
        out.codec_snr = ci / cn if cn > 0 else float("inf")
        times["codec"] = time.perf_counter() - t0
    out.timings_s = {k: round(v, 3) for k, v in times.items()}
    if not frame:
        return out
    shots = [p.frame for p in made.parts]
    img = _codec(shots, profile.image.fps_hz)[CODEC_FRAMES // 2] if codec else shots[0]
    return out, img


def sheet(tiles: list[tuple[np.ndarray, str]], columns: int = 10) -> np.ndarray:
    """Labelled tiles (uint8 RGB crops of one size, label text) on a white grid: uint8 RGB."""
    from .fabrics.preview import put_fitted_label

    th, tw = tiles[0][0].shape[:2]
    label_h, pad = 16, 3
    rows = -(-len(tiles) // columns)
    out = np.full((rows * (th + label_h + pad) + pad, columns * (tw + pad) + pad, 3), 255, np.uint8)
    for k, (img, text) in enumerate(tiles):
        r, c = divmod(k, columns)
        y, x = pad + r * (th + label_h + pad), pad + c * (tw + pad)
        out[y + label_h:y + label_h + th, x:x + tw] = img
        put_fitted_label(out, text, (x, y + label_h - 4), tw, 0.36)
    return out


def crop_at(img: np.ndarray, centre_xy: tuple[float, float], size_wh: tuple[int, int]) -> np.ndarray:
    """A ``size_wh`` crop of ``img`` centred near ``centre_xy`` (x, y px), kept inside the frame."""
    h, w = img.shape[:2]
    cw, ch = size_wh
    x0 = int(min(max(round(centre_xy[0] - cw / 2), 0), w - cw))
    y0 = int(min(max(round(centre_xy[1] - ch / 2), 0), h - ch))
    return img[y0:y0 + ch, x0:x0 + cw]
