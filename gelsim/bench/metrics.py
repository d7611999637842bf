"""The bench's image metrics and the pooling of a level's errors against the reference over frames and
scenes (:class:`ErrorAcc`, :func:`accumulate`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..metrics import psnr, ssim_map
from .runs import LevelRun
from .texture import SceneTexture


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """The bench's SSIM of two 8-bit ``(H, W[, C])`` images: :func:`gelsim.metrics.ssim_map` averaged over
    every pixel, border included (as the bench has always reported it), 1 = identical."""
    return float(ssim_map(a, b).mean())


def psnr_from_mse(mse: float) -> float | None:
    """:func:`gelsim.metrics.psnr` for JSON: None for identical images (infinite)."""
    p = psnr(mse)
    return None if math.isinf(p) else p


def rounded(v, n: int):
    return None if v is None else round(float(v), n)


@dataclass
class Mean:
    """A running mean: ``total`` over ``n`` (:meth:`mean`: ``empty`` while nothing was added)."""
    total: float = 0.0
    n: int = 0

    def add(self, total: float, n: int = 1) -> None:
        self.total += total
        self.n += n

    def mean(self, empty: float | None = None) -> float | None:
        return self.total / self.n if self.n else empty


@dataclass
class ErrorAcc:
    """Pools errors over frames and scenes: image L1 and squared error (per pixel and channel) and SSIM
    (per frame), marker distances (mm; all markers, and those in the reference's contact), forces (N, per
    frame), relative contact-area errors, and the texture's band RMS per scene (sums of squares of the
    level's and the reference's gel relief, mm^2, image texture through each one's renderer and through
    the fast shader, DN^2)."""
    l1_dn: Mean = field(default_factory=Mean)
    se_dn2: Mean = field(default_factory=Mean)
    ssims: Mean = field(default_factory=Mean)
    markers_mm: Mean = field(default_factory=Mean)
    contact_markers_mm: Mean = field(default_factory=Mean)
    force_n: Mean = field(default_factory=Mean)
    area_rel: Mean = field(default_factory=Mean)
    texture: dict = field(default_factory=dict)  # scene -> sums [gel^2, ref, img^2, ref, fast img^2, ref]

    def add_frame(self, a: np.ndarray, ref: np.ndarray) -> None:
        d = a.astype(np.float64) - ref.astype(np.float64)
        self.l1_dn.add(float(np.abs(d).sum()), d.size)
        self.se_dn2.add(float((d * d).sum()), d.size)
        self.ssims.add(ssim(a, ref))

    def add_markers(self, xy: np.ndarray, ref: np.ndarray, mm_per_px: float) -> None:
        """Marker centres (..., 2) px and the reference's."""
        _add_distances(self.markers_mm, xy, ref, mm_per_px)

    def add_contact_markers(self, xy: np.ndarray, ref: np.ndarray, mm_per_px: float) -> None:
        """Markers (N, 2) px inside the reference's contact patch, and the reference's."""
        _add_distances(self.contact_markers_mm, xy, ref, mm_per_px)

    def add_forces(self, f: np.ndarray, ref: np.ndarray) -> None:
        self.force_n.add(float(np.abs(np.asarray(f, np.float64) - ref).sum()), len(f))

    def add_area(self, area_mm2: float, ref_mm2: float) -> None:
        if ref_mm2 > 0:
            self.area_rel.add(abs(float(area_mm2) - float(ref_mm2)) / float(ref_mm2))

    def add_texture(self, scene: str, gel: float, ref_gel: float, img: float, ref_img: float,
                    img_fast: float = math.nan, ref_img_fast: float = math.nan) -> None:
        """One frame's band RMS, the level's and the reference's: gel relief (mm), image texture through
        each one's renderer and through the fast shader (DN; NaN: not measured). Frames with no region
        (NaN relief or image) are left out."""
        if not all(math.isfinite(v) for v in (gel, ref_gel, img, ref_img)):
            return
        t = self.texture.setdefault(scene, [0.0] * 6)
        fast = (img_fast, ref_img_fast) if math.isfinite(img_fast) and math.isfinite(ref_img_fast) else (0.0, 0.0)
        for k, v in enumerate((gel, ref_gel, img, ref_img, *fast)):
            t[k] += v * v

    def texture_ratios(self) -> dict[str, tuple[float | None, float | None, float | None]]:
        """Per scene: (kept relief, image texture, image texture through the fast shader) ratios to
        the reference (None where it has none or it was not measured)."""
        def ratio(a, b):
            return math.sqrt(a / b) if b > 0 else None

        return {sc: (ratio(t[0], t[1]), ratio(t[2], t[3]), ratio(t[4], t[5])) for sc, t in self.texture.items()}

    def summary(self) -> dict:
        out = {"image_l1": rounded(self.l1_dn.mean(), 4),
               "psnr": rounded(psnr_from_mse(self.se_dn2.mean()) if self.se_dn2.n else None, 3),
               "ssim": rounded(self.ssims.mean(), 5),
               "marker_err_mm": rounded(self.markers_mm.mean(), 6),
               "marker_err_contact_mm": rounded(self.contact_markers_mm.mean(), 6),
               "force_err_n": rounded(self.force_n.mean(0.0), 5),
               "contact_area_err": rounded(self.area_rel.mean(), 4)}
        # None: not measured (no frames, markers or fabric scenes compared); PSNR also None for
        # identical images
        ratios = self.texture_ratios()
        for k, name, err in ((0, "kept_relief", "texture_err"), (1, "image_texture", "image_texture_err"),
                             (2, "image_texture_fast", "image_texture_fast_err")):
            vals = [v[k] for v in ratios.values() if v[k] is not None and v[k] > 0]
            out[name] = rounded(math.exp(sum(math.log(v) for v in vals) / len(vals)) if vals else None, 4)
            out[f"{name}_min"] = rounded(min(vals) if vals else None, 4)
            out[f"{name}_max"] = rounded(max(vals) if vals else None, 4)
            out[err] = rounded(sum(abs(1 - v) for v in vals) / len(vals) if vals else None, 4)
        return out


def _add_distances(into: Mean, xy: np.ndarray, ref: np.ndarray, mm_per_px: float) -> None:
    """The distances between marker centres ``xy`` and ``ref`` ((..., 2) px), in mm, into ``into``."""
    if xy.size:
        into.add(float(np.linalg.norm(xy - ref, axis=-1).sum()) * mm_per_px, int(np.prod(xy.shape[:-1])))


def accumulate(acc: ErrorAcc, run: LevelRun, ref: LevelRun, mmpp: float, scene: str = "",
               tex: SceneTexture | None = None, ref_tex: SceneTexture | None = None) -> None:
    """Add one scene's errors of ``run`` against ``ref`` (same contact) to ``acc``."""
    touch = np.asarray(ref.contact.in_contact, bool)
    if run.frames is not None and ref.frames is not None:
        for i in np.flatnonzero(touch):
            acc.add_frame(run.frames[i], ref.frames[i])
    if "markers_xy_px" in run.labels and "markers_xy_px" in ref.labels:
        acc.add_markers(run.labels["markers_xy_px"][touch], ref.labels["markers_xy_px"][touch], mmpp)
        if ref_tex is not None and ref_tex.patch is not None:
            for k, i in enumerate(ref_tex.frames):
                xy, rxy = run.labels["markers_xy_px"][i], ref.labels["markers_xy_px"][i]
                if not len(rxy):
                    continue
                h, w = ref_tex.patch.shape[1:]
                col = np.clip(np.rint(rxy[:, 0]).astype(int), 0, w - 1)
                row = np.clip(np.rint(rxy[:, 1]).astype(int), 0, h - 1)
                inside = ref_tex.patch[k][row, col]
                acc.add_contact_markers(xy[inside], rxy[inside], mmpp)
    if "contact_area_mm2" in run.labels and "contact_area_mm2" in ref.labels:
        for i in np.flatnonzero(touch):
            acc.add_area(run.labels["contact_area_mm2"][i], ref.labels["contact_area_mm2"][i])
    if tex is not None and ref_tex is not None:
        for k in range(len(ref_tex.frames)):
            fast = (math.nan, math.nan) if tex.img_fast_rms is None or ref_tex.img_fast_rms is None else \
                (tex.img_fast_rms[k], ref_tex.img_fast_rms[k])
            acc.add_texture(scene, tex.gel_rms[k], ref_tex.gel_rms[k], tex.img_rms[k], ref_tex.img_rms[k], *fast)
    acc.add_forces(run.labels["normal_force_n"], np.asarray(ref.labels["normal_force_n"], np.float64))
