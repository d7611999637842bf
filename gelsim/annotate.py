"""Pictures of tactile frames for people: captions, the frame minus the flat gel, marker arrows, the flat gel
of a sensor, and what a dataset's per-frame nuisance record holds. Shared by the previews
(:mod:`gelsim.previews`), the first look (:mod:`gelsim.firstlook`) and ``gelsim show`` (:mod:`gelsim.show`).

A camera frame holds a few DN of texture on a grey gel; what the contact changed shows when the flat gel's
frame (same sensor unit, markers at rest) is taken away and the rest stretched to the full range.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: The difference is stretched so that this percentile of its magnitude reaches full scale (a few
#: marker edges may clip).
STRETCH_PERCENTILE = 99.5
#: Caption font scale (OpenCV's Hershey simplex) per pixel of image width: 0.8 on a 960 px frame, where
#: a line is about 20 px tall; never below :data:`MIN_CAPTION_SCALE`, where the glyphs stay legible.
CAPTION_SCALE_PER_PX = 0.8 / 960
MIN_CAPTION_SCALE = 0.4
#: Line spacing and left margin of captions, px at caption scale 1 (a line of scale s is about 22 s px tall;
#: 14 px apart at the smallest scale).
CAPTION_LINE_PX = 35
CAPTION_MARGIN_PX = 10
#: The outline: the glyphs drawn in black shifted by up to this many px per unit of caption scale (at
#: least 1), under the white glyphs. A thicker black stroke instead widens OpenCV's glyph advances, so its
#: text ran past the white ("poplin" read "poplinn").
OUTLINE_PX_PER_SCALE = 2.5
#: Marker arrows: colour (RGB) and the length, px, the largest displacement of a panel is drawn at (the
#: field's shape matters, its size is said in the caption).
ARROW_COLOUR = (255, 230, 40)
ARROW_LONGEST_PX = 24.0


def caption_scale(width_px: int) -> float:
    """The caption font scale for an image ``width_px`` wide."""
    return max(MIN_CAPTION_SCALE, CAPTION_SCALE_PER_PX * width_px)


def caption(img: np.ndarray, lines: list[str] | str, scale: float | None = None, first_line: int = 0) -> np.ndarray:
    """A copy of uint8 RGB ``img`` with ``lines`` in white on a black outline from its top-left corner,
    starting at line ``first_line``; ``scale``: the font scale (default :func:`caption_scale`)."""
    lines = [lines] if isinstance(lines, str) else list(lines)
    scale = caption_scale(img.shape[1]) if scale is None else scale
    out = np.ascontiguousarray(img).copy()
    step = max(10, round(CAPTION_LINE_PX * scale))
    thick = max(1, round(1.5 * scale))
    reach = max(1, round(OUTLINE_PX_PER_SCALE * scale))
    diag = max(1, reach // 2)
    offsets = [(a * diag, b * diag) for a in (-1, 1) for b in (-1, 1)] + \
              [(0, reach), (reach, 0), (0, -reach), (-reach, 0)]
    for i, text in enumerate(lines):
        x, y = round(CAPTION_MARGIN_PX * scale), step * (first_line + i + 1)
        for dx, dy in offsets:
            cv2.putText(out, text, (x + dx, y + dy), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thick, cv2.LINE_AA)
        cv2.putText(out, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return out


#: A pixel darker than this fraction of its image's median brightness is marker ink (printed markers are
#: near black on the lit gel): the stretch is measured without such pixels, whose edges move with the
#: markers by tens of DN and would otherwise set it, leaving the weave and the contact a few DN of grey.
MARKER_DARK_FRACTION = 0.6


def gel_pixels(img: np.ndarray) -> np.ndarray:
    """bool (..., H, W): the pixels of uint8 RGB ``img`` (..., H, W, 3) that are lit gel, not marker ink
    (:data:`MARKER_DARK_FRACTION` of each image's median brightness)."""
    lum = img.astype(np.float32).mean(-1)
    median = np.median(lum.reshape(*lum.shape[:-2], -1), axis=-1)[..., None, None]
    return lum > MARKER_DARK_FRACTION * median


def stretch_gain(differences: np.ndarray, where: np.ndarray | None = None) -> float:
    """The gain that takes the :data:`STRETCH_PERCENTILE` magnitude of float ``differences`` (DN, (..., H, W,
    3)) to 127 DN, over the pixels ``where`` (bool (..., H, W); None or none: all); at least 1: a difference
    below 1 DN is not blown up into noise."""
    values = np.abs(differences)
    if where is not None and where.any():
        values = values[where]
    scale = float(np.percentile(values, STRETCH_PERCENTILE)) if values.size else 0.0
    return 127.0 / max(scale, 1.0)


def stretched(difference: np.ndarray, gain: float) -> np.ndarray:
    """Float ``difference`` (DN) around mid-grey 128, times ``gain``, as uint8."""
    return np.clip(128.0 + difference * gain, 0, 255).astype(np.uint8)


def stretched_difference(frame: np.ndarray, flat: np.ndarray) -> tuple[np.ndarray, float]:
    """``frame - flat`` per channel, mapped to uint8 around mid-grey 128 with the gain that takes its
    :data:`STRETCH_PERCENTILE` magnitude over the lit gel (:func:`gel_pixels` of both) to 127, marker edges
    clipping (returned with the image: how much it was stretched)."""
    return _stretch(frame, flat)


def _stretch(frames: np.ndarray, flat: np.ndarray) -> tuple[np.ndarray, float]:
    diff = frames.astype(np.float32) - flat.astype(np.float32)
    gain = stretch_gain(diff, gel_pixels(frames) & gel_pixels(flat))
    return stretched(diff, gain), gain


def stretched_differences(frames: np.ndarray, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`stretched_difference` of each of uint8 ``frames`` (T, H, W, 3): uint8 (T, H, W, 3) and the gains
    (T,). Each frame gets its own gain (said in its caption): one gain for all lets a frame that changed a
    lot (a webcam's dark first frames, -100 DN) flatten the others' contact to grey."""
    out = np.empty(frames.shape, np.uint8)
    gains = np.empty(len(frames))
    for k, f in enumerate(frames):
        out[k], gains[k] = _stretch(f, flat)
    return out, gains


def draw_arrows(img: np.ndarray, start_px: np.ndarray, end_px: np.ndarray, gain: float,
                colour: tuple[int, int, int] = ARROW_COLOUR) -> np.ndarray:
    """A copy of uint8 RGB ``img`` with an arrow from each ``start_px`` towards ``end_px`` (float (N, 2), (x, y)
    px of ``img``), ``gain`` times the displacement long; points that moved less than half a pixel when drawn
    get a dot."""
    out = np.ascontiguousarray(img).copy()
    thick = max(1, round(img.shape[1] / 480))
    for (x0, y0), (x1, y1) in zip(np.asarray(start_px, float), np.asarray(end_px, float)):
        if not np.isfinite([x0, y0, x1, y1]).all():
            continue
        tip = (x0 + gain * (x1 - x0), y0 + gain * (y1 - y0))
        p0, p1 = (round(x0), round(y0)), (round(tip[0]), round(tip[1]))
        if abs(tip[0] - x0) + abs(tip[1] - y0) < 0.5:
            cv2.circle(out, p0, thick, colour, -1, cv2.LINE_AA)
        else:
            cv2.arrowedLine(out, p0, p1, colour, thick, cv2.LINE_AA, tipLength=0.3)
    return out


def arrow_gain(displacements_px: np.ndarray) -> float:
    """The magnification that draws the longest of ``displacements_px`` (float (..., 2), px) at
    :data:`ARROW_LONGEST_PX` (1 when nothing moved)."""
    d = np.asarray(displacements_px, float).reshape(-1, 2)
    longest = float(np.nanmax(np.hypot(d[:, 0], d[:, 1]))) if d.size else 0.0
    return ARROW_LONGEST_PX / longest if longest > 1e-6 else 1.0


def flat_frame(profile, fidelity: str, seed: int) -> np.ndarray:
    """The flat gel of sensor ``profile`` as a dataset made at ``fidelity`` (its supersampling) with sensor seed
    ``seed`` shows it: uint8 RGB (H, W, 3), markers at rest, no noise. The numpy backend renders it whatever
    backend made the data (the flat gel is the same within its tolerance). A dataset's sensor, unit by unit:
    :func:`gelsim.dataset.dataset_flat_frame`."""
    from .fidelity import get_fidelity
    from .markers import rest_markers
    from .optics import Renderer

    renderer = Renderer(profile, "fast", supersample=get_fidelity(fidelity).supersample, seed=seed)
    try:
        markers = rest_markers(profile, seed=seed) if profile.markers.enabled else None
        return renderer.render(None, markers, noise=False)
    finally:
        renderer.close()


#: Where a dataset keeps a per-frame nuisance record of a sequence, relative to its root, tried after the
#: manifest entry's own ``nuisance`` path (``{fabric:03d}`` as in the labels' folders).
NUISANCE_PATHS = ("nuisance/f{fabric:03d}/{id}.npz", "nuisance/{id}.npz")


def nuisance_record(root: Path, sequence: dict) -> dict | None:
    """The per-frame nuisance record of ``sequence`` (key -> array with one row per frame), read from the
    manifest entry's ``nuisance`` path or :data:`NUISANCE_PATHS`; None when the dataset has none."""
    from .errors import GelsimError

    root = Path(root)
    names = ([sequence["nuisance"]] if isinstance(sequence.get("nuisance"), str) else []) + \
            [p.format(id=sequence["id"], fabric=sequence["fabric_id"]) for p in NUISANCE_PATHS]
    path = next((root / n for n in names if (root / n).is_file()), None)
    if path is None:
        return None
    try:
        with np.load(path) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except Exception as e:  # an unreadable record is said, not a traceback
        raise GelsimError(f"cannot read the nuisance record {path} ({type(e).__name__}); regenerate the dataset "
                          "or move the file away") from None


def varying_nuisance(record: dict | None, count: int) -> dict[str, np.ndarray]:
    """The numeric per-frame arrays (``count`` rows, 1-D or 2-D) of a nuisance record that change over the
    sequence: the stages that did something (a dataset may hold a record of constant "nothing applied" rows
    for every sequence, with no level or where a stage did nothing)."""
    out = {}
    for key, value in (record or {}).items():
        v = np.asarray(value)
        if v.ndim in (1, 2) and len(v) == count and np.issubdtype(v.dtype, np.number) and np.ptp(v, axis=0).max() > 0:
            out[key] = v.astype(float)
    return out


def tile(img: np.ndarray, width: int) -> np.ndarray:
    """``img`` scaled to ``width`` px wide (aspect kept; area averaging when shrinking)."""
    if img.shape[1] == width:
        return img
    h = max(1, round(img.shape[0] * width / img.shape[1]))
    interp = cv2.INTER_AREA if width < img.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(img, (width, h), interpolation=interp)


def read_frames(root: Path, sequence: dict) -> np.ndarray:
    """The uint8 (T, H, W, 3) RGB frames of ``sequence`` (a manifest entry) of the dataset at ``root``."""
    from .video import read_video

    return read_video(Path(root) / sequence["video"])
