"""Realism against real GelSight frames: data packs, image metrics, ball presses, scores.

A *data pack* is an ``.npz`` of real ball presses in the format of taxim's
calibration set (Si and Yuan, RA-L 2022; PyPI ``taxim`` 1.4.1, MIT licence):

* ``f0``            uint8 ``(H, W, 3)``: the gel with nothing touching it;
* ``imgs``          uint8 ``(N, H, W, 3)``: one frame per press of a ball;
* ``touch_center``  ``(N, 2)``: contact centre ``(x, y)`` in pixels;
* ``touch_radius``  ``(N,)``: contact radius in pixels.

Channel order: such packs are written from OpenCV, so colours are stored BGR.
For taxim's GelSight R1.5 pack this was checked: taxim's own simulator writes
``f0`` with ``cv2.imwrite`` (which expects BGR). Data loaded here is converted
to RGB, the order of every gelsim image.

Metrics (0-255 images): SSIM and PSNR of :mod:`gelsim.metrics` (SSIM as in Wang et al. 2004,
mean over the three channels and over the pixels whose 11 px window lies inside the image) and
L1 (mean absolute error). They are
computed on a 400x400 crop centred on the contact (Taxim's protocol), inside the
disk of 1.5 contact radii (the *contact*), and as *skill*, ``1 - MSE(sim, real) /
MSE(background, real)`` inside that disk: 0 for the background alone, 1 for a
perfect prediction.

*Small slopes* (issue #11: fabric texture tilts the gel by less than about 0.2): inside the
annotated contact the gel takes the ball's shape, so its slope is known exactly, ``rho /
sqrt(R^2 - rho^2)`` at ``rho`` from the centre. Over the contact's pixels whose slope is below
``SMALL_SLOPE`` (the ball's flat top) the metric compares the colour change, simulated minus the
renderer's background against real minus the pack's ``f0``, per channel: its RMS difference, and
the *gain*, the colour change per unit of slope fitted as ``dc = a_frame + g . grad(depth)`` (an
offset per frame, one 2-vector ``g`` per channel; ``|g|`` in DN per unit slope). Each channel
responds to its own LED's direction, so channels are never averaged before the fit: three LEDs
120 degrees apart cancel in a grey average.
"""
from __future__ import annotations

import io
import math
import os
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_write_bytes
from .errors import GelsimError, check_choice
from .metrics import psnr, ssim
from .params import param

TAXIM_VERSION = "1.4.1"
TAXIM_PACK_MEMBER = "taxim/calib/gelsight/dataPack.npz"
# taxim 1.4.1's real ball presses: name -> (member of the wheel, file in the cache). "r15": GelSight
# R1.5, f0 + 48 presses; "mini": GelSight Mini, f0 + 24 presses (both 640x480).
TAXIM_PACKS = {"r15": (TAXIM_PACK_MEMBER, "dataPack.npz"),
               "mini": ("taxim/calib/gelsight_mini/dataPack.npz", "gelsight_mini/dataPack.npz")}
R15_MM_PER_PX = 0.0295       # taxim's calib/gelsight/params.json
R15_BALL_DIAMETER_MM = 4.0   # taxim's calibration ball
CROP_PX = 400                # Taxim's paper compares 400x400 contact crops
DISK_RADII = 1.5             # the contact disk reaches 1.5 contact radii: the gel's rim and shadows lie inside
SMALL_SLOPE = 0.2            # issue #11: fabric texture's surface slopes are mostly below 0.2
REQUIRED_KEYS = ("f0", "imgs", "touch_center", "touch_radius")
FRAME_SETS = ("even", "odd", "all")


# --------------------------------------------------------------------------------------
# Data packs
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DataPack:
    """Real ball presses. ``f0`` uint8 ``(H, W, 3)`` RGB; ``imgs`` uint8 ``(N, H, W, 3)`` RGB;
    ``centers_px`` float64 ``(N, 2)`` (x, y); ``radii_px`` float64 ``(N,)``; ``source`` the file."""
    f0: np.ndarray
    imgs: np.ndarray
    centers_px: np.ndarray
    radii_px: np.ndarray
    source: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        return self.f0.shape[:2]

    def select(self, frames: str) -> list[int]:
        """Indices of ``frames``: "even" (0, 2, ...), "odd" (1, 3, ...) or "all"."""
        n = len(self.imgs)
        if frames == "even":
            return list(range(0, n, 2))
        if frames == "odd":
            return list(range(1, n, 2))
        if frames == "all":
            return list(range(n))
        raise GelsimError(f"frames {frames!r} is not one of {', '.join(FRAME_SETS)}; pick one")


def check_datapack(data: dict, where: str = "data pack", channel_order: str = "bgr") -> DataPack:
    """Validate the arrays of a data pack (a mapping of the keys above) and convert to RGB."""
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise GelsimError(f"{where} lacks {', '.join(missing)}; a data pack needs {', '.join(REQUIRED_KEYS)}")
    if channel_order not in ("bgr", "rgb"):
        raise GelsimError(f"channel order {channel_order!r} is unknown; give 'bgr' or 'rgb'")
    f0 = np.asarray(data["f0"])
    imgs = np.asarray(data["imgs"])
    c = np.asarray(data["touch_center"], dtype=np.float64)
    r = np.asarray(data["touch_radius"], dtype=np.float64)
    if f0.ndim != 3 or f0.shape[2] != 3:
        raise GelsimError(f"{where}: f0 has shape {f0.shape}; give one (H, W, 3) colour frame")
    if imgs.ndim != 4 or imgs.shape[1:] != f0.shape:
        raise GelsimError(f"{where}: imgs has shape {imgs.shape}, f0 {f0.shape}; give imgs as (N, H, W, 3) "
                          "frames of f0's size")
    n = imgs.shape[0]
    if n == 0:
        raise GelsimError(f"{where}: imgs holds no frame; give at least one ball press")
    if c.shape != (n, 2):
        raise GelsimError(f"{where}: touch_center has shape {c.shape}; give ({n}, 2) centres (x, y) px, one per frame")
    if r.shape != (n,):
        raise GelsimError(f"{where}: touch_radius has shape {r.shape}; give ({n},) radii in px, one per frame")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r > 0)):
        raise GelsimError(f"{where}: touch_center/touch_radius hold non-finite or non-positive values; fix them")
    h, w = f0.shape[:2]
    outside = np.flatnonzero((c[:, 0] < 0) | (c[:, 0] > w - 1) | (c[:, 1] < 0) | (c[:, 1] > h - 1))
    if outside.size:
        i = int(outside[0])
        raise GelsimError(f"{where}: frame {i}'s contact centre ({c[i, 0]:g}, {c[i, 1]:g}) px lies outside the "
                          f"{w}x{h} image; give centres as (x, y) = (column, row) inside it")
    for name, a in (("f0", f0), ("imgs", imgs)):
        if a.dtype != np.uint8:
            if not np.issubdtype(a.dtype, np.number) or a.min() < 0 or a.max() > 255:
                raise GelsimError(f"{where}: {name} has dtype {a.dtype} outside 0-255; give uint8 frames")
    f0 = f0.astype(np.uint8)
    imgs = imgs.astype(np.uint8)
    if channel_order == "bgr":
        f0 = np.ascontiguousarray(f0[..., ::-1])
        imgs = np.ascontiguousarray(imgs[..., ::-1])
    return DataPack(f0, imgs, c, r, where)


def load_datapack(path: str | Path, channel_order: str = "bgr") -> DataPack:
    """Load and validate a data pack ``.npz`` (see the module docstring); colours come out RGB."""
    path = Path(path)
    if not path.is_file():
        raise GelsimError(f"data pack {path} not found; give an .npz with {', '.join(REQUIRED_KEYS)}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files if k in REQUIRED_KEYS}
    except (OSError, ValueError, zipfile.BadZipFile):
        raise GelsimError(f"data pack {path} cannot be read: it is not a numpy .npz file; give an .npz with "
                          f"{', '.join(REQUIRED_KEYS)}") from None
    return check_datapack(data, str(path), channel_order)


def cache_dir() -> Path:
    """Where fetched data lives: ``$GELSIM_CACHE`` or ``~/.cache/gelsim`` (never the repository)."""
    env = os.environ.get("GELSIM_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "gelsim"


def r15_pack_path() -> Path:
    """Path of the cached R1.5 data pack (it may not exist yet; see :func:`fetch_r15_pack`)."""
    return taxim_pack_path("r15")


def taxim_pack_path(name: str) -> Path:
    """Path of a cached taxim data pack (``"r15"`` or ``"mini"``; it may not exist yet)."""
    check_choice("taxim data pack", name, TAXIM_PACKS)
    return cache_dir() / f"taxim-{TAXIM_VERSION}" / TAXIM_PACKS[name][1]


def fetch_r15_pack() -> Path:
    """The GelSight R1.5 data pack from taxim's wheel (:func:`fetch_taxim_pack`)."""
    return fetch_taxim_pack("r15")


def fetch_taxim_pack(name: str = "r15") -> Path:
    """A data pack from taxim's wheel (``"r15"``: GelSight R1.5; ``"mini"``: GelSight Mini),
    downloaded once into the cache.

    Runs ``pip download taxim==1.4.1 --no-deps`` (a 27 MB wheel) and extracts only the pack's
    ``dataPack.npz``; taxim's code is never installed or imported.
    """
    out = taxim_pack_path(name)
    member = TAXIM_PACKS[name][0]
    if out.is_file():
        return out
    wheel_dir = cache_dir() / "wheels"
    wheels = sorted(wheel_dir.glob(f"taxim-{TAXIM_VERSION}-*.whl"))
    if not wheels:
        wheel_dir.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-m", "pip", "download", f"taxim=={TAXIM_VERSION}", "--no-deps",
               "--only-binary", ":all:", "-d", str(wheel_dir)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        wheels = sorted(wheel_dir.glob(f"taxim-{TAXIM_VERSION}-*.whl"))
        if res.returncode != 0 or not wheels:
            tail = (res.stderr or res.stdout).strip().splitlines()[-1:] or ["no output"]
            raise GelsimError(f"could not download taxim {TAXIM_VERSION} ({tail[0]}); check the network or "
                              f"give --datapack PATH to a local dataPack.npz")
    try:
        with zipfile.ZipFile(wheels[-1]) as z:
            blob = z.read(member)
    except (KeyError, zipfile.BadZipFile) as e:
        raise GelsimError(f"{wheels[-1]} holds no readable {member} ({e}); delete it and retry") from None
    np.load(io.BytesIO(blob))  # fail now, not later, on a corrupt member (and write nothing)
    atomic_write_bytes(out, blob)
    return out


def resolve_datapack(path: str | Path | None) -> Path:
    """``path`` if given (``"r15"`` or ``"mini"``: that taxim pack, fetched on demand), else the R1.5 pack."""
    if not path:
        return fetch_r15_pack()
    if str(path) in TAXIM_PACKS:
        return fetch_taxim_pack(str(path))
    return Path(path)


def check_geometry(pack: DataPack, mm_per_px: float, ball_diameter_mm: float, where: str = "data pack") -> None:
    """Check that ball presses of ``ball_diameter_mm`` seen at ``mm_per_px`` fit the pack: the ball fits
    in the field of view, and no annotated contact is wider than the ball (a contact radius is at most
    the ball's radius)."""
    if not (math.isfinite(mm_per_px) and mm_per_px > 0 and math.isfinite(ball_diameter_mm) and ball_diameter_mm > 0):
        raise GelsimError("--mm-per-px and --ball-diameter-mm must be positive numbers")
    h, w = pack.shape
    fw, fh = w * mm_per_px, h * mm_per_px
    if ball_diameter_mm > min(fw, fh):
        raise GelsimError(f"{where}: a {ball_diameter_mm:g} mm ball is larger than the {fw:.1f} x {fh:.1f} mm field "
                          f"({w}x{h} px at {mm_per_px:g} mm/px); check --ball-diameter-mm and --mm-per-px")
    r_max = float(pack.radii_px.max()) * mm_per_px
    if r_max > ball_diameter_mm / 2.0 * (1.0 + 1e-6):
        i = int(np.argmax(pack.radii_px))
        raise GelsimError(f"{where}: frame {i}'s contact radius {pack.radii_px[i]:g} px = {r_max:.2f} mm exceeds the "
                          f"{ball_diameter_mm:g} mm ball's radius; check --mm-per-px and --ball-diameter-mm")


# --------------------------------------------------------------------------------------
# Measured realism of the shipped profiles (assets/realism.toml)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RealismRecord:
    """One shipped profile's held-out realism, as ``gelsim realism`` printed it (see the file's header)."""
    datapack: str = param(doc="the data pack: 'r15', 'mini' or a description")
    frames: str = param(doc="the frames scored: 'odd' or 'even' (fitted on the others)")
    frame_count: int = param(lo=1, hi=100000, doc="number of frames scored")
    mm_per_px: float = param(lo=1e-4, hi=1.0, lo_open=True, doc="pixel size used, mm")
    ball_diameter_mm: float = param(lo=0.1, hi=100.0, doc="ball diameter used, mm")
    skill: float = param(lo=-100.0, hi=1.0, doc="1 - MSE(sim) / MSE(background) in the contact disks")
    contact_psnr_db: float = param(lo=0.0, hi=100.0, doc="PSNR in the contact disks, dB")
    contact_l1_dn: float = param(lo=0.0, hi=255.0, doc="mean absolute error in the contact disks, DN")
    crop_ssim: float = param(lo=-1.0, hi=1.0, doc="SSIM of 400x400 crops around the contacts")
    crop_psnr_db: float = param(lo=0.0, hi=100.0, doc="PSNR of the crops, dB")
    crop_l1_dn: float = param(lo=0.0, hi=255.0, doc="mean absolute error of the crops, DN")
    baseline_contact_psnr_db: float = param(lo=0.0, hi=100.0, doc="the background alone: contact PSNR, dB")
    baseline_contact_l1_dn: float = param(lo=0.0, hi=255.0, doc="the background alone: contact L1, DN")
    baseline_crop_ssim: float = param(lo=-1.0, hi=1.0, doc="the background alone: crop SSIM")
    baseline_crop_psnr_db: float = param(lo=0.0, hi=100.0, doc="the background alone: crop PSNR, dB")
    baseline_crop_l1_dn: float = param(lo=0.0, hi=255.0, doc="the background alone: crop L1, DN")
    small_slope_rms_dn: float = param(lo=0.0, hi=255.0, doc="small-slope RMS error, DN")
    baseline_small_slope_rms_dn: float = param(lo=0.0, hi=255.0, doc="the background alone: small-slope RMS, DN")
    skill_ci95: tuple[float, float] = param(doc="95% interval of the skill, bootstrap over the scored presses")
    registered_skill: float = param(lo=-100.0, hi=1.0, doc="the skill with each scored press registered against "
                                                            "the fitted frames' table: the pose fitted, an upper "
                                                            "bound, not a held-out figure")
    registered_skill_ci95: tuple[float, float] = param(doc="its 95% interval")
    centres: str = param("annotated", doc="where the scored balls were placed (the headline): 'annotated' (the "
                                          "pack's contact centres) or 'detected' (each frame's flat point, "
                                          "gelsim.centres); never from the scored model")
    annotated_skill: float | None = param(None, lo=-100.0, hi=1.0,
                                          doc="with detected centres: the skill at the pack's annotated ones")
    annotated_skill_ci95: tuple[float, float] | None = param(None, doc="its 95% interval")

    def validate(self, where: str) -> None:
        if self.centres not in ("annotated", "detected"):
            raise GelsimError(f"{where}: centres {self.centres!r} is not 'annotated' or 'detected'; fix it")
        if (self.annotated_skill is None) != (self.centres == "annotated"):
            raise GelsimError(f"{where}: give annotated_skill exactly when centres is 'detected'")
        if (self.annotated_skill is None) != (self.annotated_skill_ci95 is None):
            raise GelsimError(f"{where}: give annotated_skill_ci95 with annotated_skill")
        for name in ("skill", "annotated_skill", "registered_skill"):
            v, ci = getattr(self, name), getattr(self, f"{name}_ci95")
            if v is not None and not ci[0] <= v <= ci[1]:
                raise GelsimError(f"{where}: {name} {v} lies outside its interval {list(ci)}; fix one of them")


def realism_records(path: str | Path | None = None) -> dict[str, RealismRecord]:
    """The measured realism of the shipped profiles (``assets/realism.toml``), by profile name."""
    from .params import ASSETS_DIR, build, load_toml

    path = Path(path) if path else ASSETS_DIR / "realism.toml"
    data = load_toml(path)
    out = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise GelsimError(f"{path.name}: {name!r} is not a table; give one [profile-name] table per profile")
        out[name] = build(RealismRecord, table, where=f"{path.name}[{name}]")
    return out


# --------------------------------------------------------------------------------------
# Metrics on a contact (SSIM and PSNR themselves: gelsim.metrics)
# --------------------------------------------------------------------------------------
def crop_box(center_px, shape: tuple[int, int], size: int = CROP_PX) -> tuple[slice, slice]:
    """Rows and columns of the ``size`` square centred on ``center_px`` (x, y), shifted to lie inside."""
    h, w = shape
    sh, sw = min(size, h), min(size, w)
    x0 = int(round(center_px[0])) - sw // 2
    y0 = int(round(center_px[1])) - sh // 2
    x0 = min(max(x0, 0), w - sw)
    y0 = min(max(y0, 0), h - sh)
    return slice(y0, y0 + sh), slice(x0, x0 + sw)


def disk_mask(center_px, radius_px: float, shape: tuple[int, int]) -> np.ndarray:
    """bool ``(H, W)``: pixel centres within ``radius_px`` of ``center_px`` (x, y)."""
    h, w = shape
    y, x = np.ogrid[:h, :w]
    return (x - center_px[0]) ** 2 + (y - center_px[1]) ** 2 <= radius_px ** 2


def frame_metrics(sim: np.ndarray, real: np.ndarray, center_px, radius_px: float) -> dict:
    """Metrics of one predicted frame against the real one (uint8 or float ``(H, W, 3)``, 0-255).

    Returns ``{"crop": {ssim, psnr, l1}, "contact": {ssim, psnr, l1}, "contact_mse"}``.
    """
    sim = np.asarray(sim, np.float64)
    real = np.asarray(real, np.float64)
    if sim.shape != real.shape:
        raise GelsimError(f"simulated frame is {sim.shape}, real {real.shape}; render at the real frame's size")
    shape = real.shape[:2]
    cb = crop_box(center_px, shape)
    dc = sim[cb] - real[cb]
    crop = {"ssim": ssim(sim[cb], real[cb]), "psnr": psnr(float((dc ** 2).mean())), "l1": float(np.abs(dc).mean())}
    rd = DISK_RADII * radius_px
    m = disk_mask(center_px, rd, shape)
    dd = sim[m] - real[m]
    mse = float((dd ** 2).mean())
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    bb = slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)
    contact = {"ssim": ssim(sim[bb], real[bb]), "psnr": psnr(mse), "l1": float(np.abs(dd).mean())}
    return {"crop": crop, "contact": contact, "contact_mse": mse}


# Skill's interval: a percentile bootstrap over the scored presses (each resample draws as many presses
# as were scored, with replacement, and takes 1 - sum MSE(sim) / sum MSE(background) over them).
# 10,000 resamples put the Monte Carlo error of the 2.5% and 97.5% quantiles under 1% of the interval's
# width; the seed is fixed so that the same frames give the same interval.
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 20200
CI_LEVEL = 0.95


def skill_interval(sim_mse, base_mse, level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                   seed: int = BOOTSTRAP_SEED) -> list[float]:
    """``[low, high]`` of the skill ``1 - sum(sim_mse) / sum(base_mse)`` over presses resampled with
    replacement (``float (n,)`` each, one value per press: the contact disk's MSE)."""
    sim = np.asarray(sim_mse, np.float64)
    base = np.asarray(base_mse, np.float64)
    if sim.shape != base.shape or sim.ndim != 1 or sim.size == 0:
        raise GelsimError(f"skill_interval needs two equal (n,) arrays of per-press MSEs, got {sim.shape} and "
                          f"{base.shape}")
    draws = np.random.default_rng(seed).integers(0, sim.size, (resamples, sim.size))
    with np.errstate(divide="ignore", invalid="ignore"):
        reps = 1.0 - sim[draws].sum(axis=1) / base[draws].sum(axis=1)
    lo, hi = np.quantile(reps[np.isfinite(reps)], [(1 - level) / 2, (1 + level) / 2])
    return [float(lo), float(hi)]


def summarize(per_frame: list[dict], base_frame: list[dict]) -> dict:
    """Means over frames of :func:`frame_metrics` results; PSNR from the mean MSE would weigh frames
    unevenly, so PSNR is the mean of the per-frame PSNRs (as the other metrics). Skill is
    ``1 - sum MSE(sim) / sum MSE(background)`` over all frames' disks, ``skill_ci95`` its 95%
    interval over the frames (:func:`skill_interval`)."""
    def mean(rows, sect, key):
        return float(np.mean([r[sect][key] for r in rows]))

    def block(rows):
        return {s: {k: mean(rows, s, k) for k in ("ssim", "psnr", "l1")} for s in ("crop", "contact")}

    out = block(per_frame)
    sim_mse = np.array([r["contact_mse"] for r in per_frame])
    bg_mse = np.array([r["contact_mse"] for r in base_frame])
    out["skill"] = 1.0 - float(sim_mse.sum()) / float(bg_mse.sum()) if bg_mse.sum() > 0 else 0.0
    out["skill_ci95"] = skill_interval(sim_mse, bg_mse) if bg_mse.sum() > 0 else [0.0, 0.0]
    out["baseline"] = block(base_frame)
    out["baseline"]["skill"] = 0.0
    return out


def ball_cap(center_px, radius_px: float, shape: tuple[int, int], mm_per_px: float, ball_diameter_mm: float,
             stride: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels where the gel takes the ball's shape (inside the annotated contact, clipped to the
    ball's radius; every ``stride``-th row and column, counted from 0) and the sphere there:
    ``(yy, xx, gx, gy, sag)``, int ``(n,)`` row and column (row-major order), the gradient of the
    imprint depth ``-(p - c) / sqrt(R^2 - rho^2)`` (mm/mm, steepest at the rim) and the sphere's rise
    above its lowest point ``R - sqrt(R^2 - rho^2)`` (mm), float64 ``(n,)``."""
    h, w = shape
    r_ball = ball_diameter_mm / 2.0
    r = min(radius_px, r_ball / mm_per_px)
    cx, cy = float(center_px[0]), float(center_px[1])
    y0, y1 = max(0, math.ceil((cy - r) / stride)), min(-(-h // stride), math.floor((cy + r) / stride) + 1)
    x0, x1 = max(0, math.ceil((cx - r) / stride)), min(-(-w // stride), math.floor((cx + r) / stride) + 1)
    y = np.arange(y0, max(y0, y1)) * stride
    x = np.arange(x0, max(x0, x1)) * stride
    yy, xx = np.meshgrid(y, x, indexing="ij")
    keep = (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    yy, xx = yy[keep], xx[keep]
    dx = (xx - cx) * mm_per_px
    dy = (yy - cy) * mm_per_px
    root = np.sqrt(np.maximum(r_ball * r_ball - dx * dx - dy * dy, 1e-12))
    return yy, xx, -dx / root, -dy / root, r_ball - root


def ball_slope(center_px, radius_px: float, shape: tuple[int, int], mm_per_px: float,
               ball_diameter_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gel's slope where it takes the ball's shape (:func:`ball_cap`): ``(mask, gx, gy)``, bool
    ``(H, W)`` and float64 ``(n,)`` for the mask's pixels (row-major)."""
    yy, xx, gx, gy, _ = ball_cap(center_px, radius_px, shape, mm_per_px, ball_diameter_mm)
    m = np.zeros(shape, bool)
    m[yy, xx] = True
    return m, gx, gy


def small_slope_frame(sim_delta: np.ndarray, real_delta: np.ndarray, center_px, radius_px: float,
                      mm_per_px: float, ball_diameter_mm: float, limit: float = SMALL_SLOPE,
                      lower: float = 0.0) -> dict:
    """One frame's part of the small-slope metric: the colour changes ``(H, W, 3)`` (simulated minus its
    background, real minus its background) at the contact's pixels with slope in ``[lower, limit)``.
    Returns ``{"sim", "real"}`` float64 ``(n, 3)`` and ``{"gx", "gy"}`` ``(n,)`` (see :func:`ball_slope`)."""
    m, gx, gy = ball_slope(center_px, radius_px, real_delta.shape[:2], mm_per_px, ball_diameter_mm)
    slope = np.hypot(gx, gy)
    keep = (slope >= lower) & (slope < limit)
    return {"sim": np.asarray(sim_delta, np.float64)[m][keep], "real": np.asarray(real_delta, np.float64)[m][keep],
            "gx": gx[keep], "gy": gy[keep]}


def _channel_gains(parts: list[dict], key: str) -> np.ndarray:
    """``|g|`` per channel (DN per unit slope) of ``dc = a_frame + g . grad`` over the frames' pixels."""
    xs, ys = [], []
    for p in parts:
        if len(p["gx"]) < 3:
            continue    # a frame offset and two slopes need three pixels
        g = np.stack([p["gx"], p["gy"]], axis=1)
        xs.append(g - g.mean(axis=0))                   # the per-frame offset, eliminated
        ys.append(p[key] - p[key].mean(axis=0))
    if not xs:
        return np.full(3, np.nan)
    coef, *_ = np.linalg.lstsq(np.concatenate(xs), np.concatenate(ys), rcond=None)
    return np.hypot(coef[0], coef[1])


def small_slope_summary(parts: list[dict], limit: float = SMALL_SLOPE) -> dict:
    """The small-slope metric over frames (:func:`small_slope_frame` results).

    Returns ``pixels``; ``rms_dn`` and ``rms_dn_rgb`` (simulated vs real change); ``baseline_rms_dn``
    (the background alone: the real change itself); ``gain_sim_dn``, ``gain_real_dn`` (DN per unit
    slope, per channel) and ``gain_ratio`` (sim / real, per channel); ``slope_below``. Values that
    cannot be measured (no pixel, fewer than 3 per frame, a zero real gain) are None."""
    n = int(sum(len(p["gx"]) for p in parts))
    out = {"slope_below": float(limit), "pixels": n}
    if n == 0:      # no contact pixel that flat: nothing measured (None, which JSON can carry)
        return {**out, "rms_dn": None, "rms_dn_rgb": [None] * 3, "baseline_rms_dn": None,
                "gain_sim_dn": [None] * 3, "gain_real_dn": [None] * 3, "gain_ratio": [None] * 3}
    e = np.concatenate([p["sim"] - p["real"] for p in parts])
    real = np.concatenate([p["real"] for p in parts])
    gs, gr = _channel_gains(parts, "sim"), _channel_gains(parts, "real")
    def listed(a):
        return [float(v) if np.isfinite(v) else None for v in a]

    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = gs / gr
    return {**out, "rms_dn": float(np.sqrt((e ** 2).mean())), "rms_dn_rgb": np.sqrt((e ** 2).mean(axis=0)).tolist(),
            "baseline_rms_dn": float(np.sqrt((real ** 2).mean())), "gain_sim_dn": listed(gs),
            "gain_real_dn": listed(gr), "gain_ratio": listed(ratio)}


# --------------------------------------------------------------------------------------
# Ball presses
# --------------------------------------------------------------------------------------
def ball_indentation_mm(contact_radius_mm: float, ball_diameter_mm: float) -> float:
    """Depth of a sphere whose cap through the gel plane has ``contact_radius_mm``: ``R - sqrt(R^2 - a^2)``
    (a contact wider than the ball is clipped to the ball's radius)."""
    r = ball_diameter_mm / 2.0
    a = min(contact_radius_mm, r)
    return r - math.sqrt(max(r * r - a * a, 0.0))


def ball_depth(profile, center_px, radius_px: float, ball_diameter_mm: float, fidelity="balanced") -> np.ndarray:
    """Imprint of a ball pressed until its contact has ``radius_px``: float32 ``(H, W)`` mm.

    The sphere (``gelsim.indenters.sphere``) is centred on ``center_px`` (x, y) and
    pressed to the depth that gives that contact radius geometrically; the gel's
    spread around it comes from :func:`gelsim.gel.press` (pyramid model at the
    profile's resolution for ``balanced``).
    """
    from .gel import press
    from .indenters import sphere

    h, w = profile.shape
    mm = profile.image.mm_per_px
    cx = (center_px[0] - (w - 1) / 2.0) * mm
    cy = (center_px[1] - (h - 1) / 2.0) * mm
    prot = sphere(ball_diameter_mm, profile, center_mm=(cx, cy))
    d = ball_indentation_mm(radius_px * mm, ball_diameter_mm)
    return press(prot, profile, fidelity, depth_mm=d).depth_mm


def evaluate(profile, pack: DataPack, frames: str = "odd", *, ball_diameter_mm: float = R15_BALL_DIAMETER_MM,
             backend: str = "fast", keep: int | None = None) -> dict:
    """Render each selected press with ``profile`` (noiseless: the expected frame) and score it.

    ``profile.image.mm_per_px`` sets the scale (pass a profile replaced with the pack's
    scale). Returns :func:`summarize`'s dict plus ``"per_frame"`` (each scored frame's index, centre
    and contact MSEs, simulated and background), ``"small_slope"`` (:func:`small_slope_summary`),
    ``"frames"`` (count) and
    ``"ms_per_frame"`` (render time, imprint included); with ``keep`` the frame
    index ``keep`` is also returned as ``"example": (real, sim)`` uint8 RGB.
    """
    import time

    from .optics import Renderer

    if profile.shape != pack.shape:
        raise GelsimError(f"profile {profile.name} renders {profile.shape} px but the data pack's frames are "
                          f"{pack.shape}; use a profile of the pack's size")
    check_geometry(pack, profile.image.mm_per_px, ball_diameter_mm, pack.source or "data pack")
    idx = pack.select(frames)
    if not idx:
        raise GelsimError(f"the data pack has no {frames} frames; give --frames all or a larger pack")
    ren = Renderer(profile, backend)
    sims, bases, small = [], [], []
    example = None
    t = 0.0
    bg = ren.background_float()
    f0 = pack.f0.astype(np.float32)
    try:
        for i in idx:
            t0 = time.perf_counter()
            depth = ball_depth(profile, pack.centers_px[i], pack.radii_px[i], ball_diameter_mm)
            sim = ren.render(depth, None, noise=False)
            t += time.perf_counter() - t0
            real = pack.imgs[i]
            sims.append(frame_metrics(sim, real, pack.centers_px[i], pack.radii_px[i]))
            bases.append(frame_metrics(pack.f0, real, pack.centers_px[i], pack.radii_px[i]))
            small.append(small_slope_frame(sim - bg, real - f0, pack.centers_px[i], pack.radii_px[i],
                                           profile.image.mm_per_px, ball_diameter_mm))
            if keep is not None and i == keep:
                example = (real, sim)
    finally:
        ren.close()
    out = summarize(sims, bases)
    out["per_frame"] = [{"frame": i, "centre_px": [float(v) for v in pack.centers_px[i]],
                         "contact_mse": a["contact_mse"], "baseline_contact_mse": b["contact_mse"]}
                        for i, a, b in zip(idx, sims, bases)]
    out["small_slope"] = small_slope_summary(small)
    out["frames"] = len(idx)
    out["ms_per_frame"] = 1000.0 * t / max(1, len(idx))
    if example is not None:
        out["example"] = example
    return out


def side_by_side(real: np.ndarray, sim: np.ndarray, gain: float = 3.0) -> np.ndarray:
    """uint8 RGB ``(H, 3 W, 3)``: real, simulated and ``gain`` x |difference|, side by side."""
    diff = np.clip(np.abs(real.astype(np.float32) - sim.astype(np.float32)) * gain, 0, 255).astype(np.uint8)
    return np.hstack([real, sim, diff])

