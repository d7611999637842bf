"""Preview images of a generated dataset: a frame strip per action, a contact sheet of the fabrics, the
first look (:mod:`gelsim.firstlook`) and a sheet of press, slip and twist frames across families
(:func:`action_sheet`)."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from . import annotate
from .annotate import caption, stretched_difference, stretched_differences
from .atomic import write_png
from .crop import STAM_CPU_CROP, crop_box_px
from .errors import GelsimError
from .firstlook import write_first_look
from .schema import ACTIONS, PREVIEWS_DIR
from .video import read_video

def _label(img: np.ndarray, text: str, line: int = 0) -> np.ndarray:
    """``img`` with ``text`` in white on a black outline, on caption line ``line`` from the top."""
    return caption(img, [text], first_line=line)


def _tile(img: np.ndarray, width: int) -> np.ndarray:
    return annotate.tile(img, width)


def frame_strip(frames: np.ndarray, n: int = 6, width: int = 240, onset: int | None = None,
                flat: np.ndarray | None = None) -> np.ndarray:
    """``n`` evenly spaced frames side by side, each labelled with its index (and contact state); with the
    sensor's ``flat`` gel (uint8 (H, W, 3)), a second row below: each frame minus it, contrast stretched with
    each frame's gain in its caption (:func:`gelsim.annotate.stretched_differences`)."""
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    tiles = []
    for i in idx:
        tag = f"t={i}" + ("" if onset is None else (" contact" if i >= onset >= 0 else " pre"))
        tiles.append(_label(_tile(frames[i], width), tag))
    strip = np.concatenate(tiles, axis=1)
    if flat is None:
        return strip
    diffs, gains = stretched_differences(frames[idx], flat)
    below = [_label(_tile(d, width), f"minus flat gel x{g:.0f}") for d, g in zip(diffs, gains)]
    return np.concatenate([strip, np.concatenate(below, axis=1)], axis=0)


def centre_crop(frame: np.ndarray, width: int, height: int) -> np.ndarray:
    """The central ``height x width`` px of ``frame`` at its own pixels (the whole frame if it is smaller)."""
    h, w = frame.shape[:2]
    th, tw = min(height, h), min(width, w)
    y0, x0 = (h - th) // 2, (w - tw) // 2
    return frame[y0:y0 + th, x0:x0 + tw]


class FlatFrames:
    """The flat gel of each sensor unit of a dataset, ``flat(sequence)`` (uint8 (H, W, 3); the dataset's:
    :func:`gelsim.dataset.dataset_flat_frame`) called once per unit."""

    def __init__(self, flat):
        self.flat = flat
        self._flat: dict[int, np.ndarray] = {}

    def __call__(self, sequence: dict) -> np.ndarray:
        unit = int(sequence.get("unit", -1))
        if unit not in self._flat:
            self._flat[unit] = self.flat(sequence)
        return self._flat[unit]


def write_previews(root: Path, manifest: dict, flat, *, tile_px: int = 160) -> list[Path]:
    """Write ``previews/<action>.png`` strips (frames above, each minus the flat gel below),
    ``previews/contact_sheet.png`` (per fabric, its peak-force frame scaled to ``tile_px`` wide, above the
    same minus the flat gel) and ``previews/texture_sheet.png`` (the same frames' central ``tile_px`` x 3/4
    ``tile_px`` pixels at their own scale, above their difference: a 960x720 frame's fine weaves vanish when
    the whole frame is scaled to 160 px), then the first look (:func:`gelsim.firstlook.write_first_look`);
    returns the paths. ``flat(sequence)``: the flat gel of ``sequence``'s sensor, uint8 (H, W, 3) (the
    dataset's: :func:`gelsim.dataset.dataset_flat_frame`)."""
    root = Path(root)
    out_dir = root / PREVIEWS_DIR
    out_dir.mkdir(exist_ok=True)
    seqs = [s for s in manifest["sequences"] if "video" in s]
    flats = FlatFrames(flat)
    written = []
    for action in ACTIONS:
        s = next((s for s in seqs if s["action"] == action), None)
        if s is None:
            continue
        frames = read_video(root / s["video"])
        strip = frame_strip(frames, onset=s.get("contact_onset"), flat=flats(s))
        p = out_dir / f"{action}.png"
        write_png(p, strip)
        written.append(p)
    # Contact sheet: per fabric, the frame of peak force of its first sequence.
    tiles, crops = [], []
    names = {f["id"]: f["name"] for f in manifest.get("fabrics", [])}
    seen = set()
    for s in seqs:
        if s["fabric_id"] in seen:
            continue
        seen.add(s["fabric_id"])
        with np.load(root / s["labels"]) as z:
            k = int(np.argmax(z["normal_force_n"]))
        frame = read_video(root / s["video"])[k]
        diff, gain = stretched_difference(frame, flats(s))
        name = f"{s['fabric_id']} {names.get(s['fabric_id'], '')}"[:28]
        th = round(tile_px * 3 / 4)
        tiles.append(np.concatenate([_label(_tile(frame, tile_px), name),
                                     _label(_tile(diff, tile_px), f"minus flat gel x{gain:.0f}")], axis=0))
        crops.append(np.concatenate([_label(centre_crop(frame, tile_px, th), name),
                                     _label(centre_crop(diff, tile_px, th), f"minus flat gel x{gain:.0f}")], axis=0))
    for sheet, parts in (("contact_sheet", tiles), ("texture_sheet", crops)):
        if parts:
            p = out_dir / f"{sheet}.png"
            write_png(p, _grid(parts, min(10, len(parts))))
            written.append(p)
    # the fabrics at 960x720 and what the contact changed; with a nuisance, its frames before contact
    written += write_first_look(out_dir, manifest, root=root, flat=flats)
    return written


def _grid(tiles: list[np.ndarray], cols: int) -> np.ndarray:
    """Equal-sized tiles in row-major order on a white sheet ``cols`` tiles wide."""
    rows = math.ceil(len(tiles) / cols)
    th, tw = tiles[0].shape[:2]
    sheet = np.full((rows * th, cols * tw, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * th:(r + 1) * th, c * tw:(c + 1) * tw] = t
    return sheet


CROP_COLOUR = (255, 220, 0)      # the stam crop: yellow, visible on the gel's grey-blue
CONTACT_COLOUR = (255, 40, 40)   # the contact's bounding box and centroid: red


def pick_across_families(manifest: dict, families: int) -> list[tuple[str, dict]]:
    """(family, {action: sequence}) for ``families`` families spread evenly over those present.

    Per family, the first fabric (by id) that has a touching sequence of every action, else the
    first touching sequence of each action in the family; per action, that fabric's first such
    sequence in manifest order. Deterministic.
    """
    fam_of = {f["id"]: f.get("family", "?") for f in manifest.get("fabrics", [])}
    seqs = [s for s in manifest["sequences"] if "labels" in s and s.get("peak_force_n", 0) > 0]
    order: list[str] = []
    for fid in sorted(fam_of):
        if fam_of[fid] not in order:
            order.append(fam_of[fid])
    if families < len(order):
        order = [order[round(k)] for k in np.linspace(0, len(order) - 1, families)]
    out = []
    for fam in order:
        in_fam = [s for s in seqs if fam_of.get(s["fabric_id"]) == fam]
        if not in_fam:
            continue
        full = [fid for fid in sorted({s["fabric_id"] for s in in_fam})
                if {s["action"] for s in in_fam if s["fabric_id"] == fid} >= set(ACTIONS)]
        pool = [s for s in in_fam if s["fabric_id"] == full[0]] if full else in_fam
        picked = {}
        for s in pool:
            picked.setdefault(s["action"], s)
        out.append((fam, picked))
    return out


# Widest tile of the action sheet, px: the cpu preset's 320 px frames tile at their own size (the
# texture as STAM gets it); 960 px frames are shown at a third, keeping six columns under 2,000 px.
ACTION_TILE_MAX_PX = 320


def action_sheet(root: Path, manifest: dict, *, families: int = 6, tile_px: int | None = None,
                 crop: float | None = None) -> np.ndarray:
    """uint8 RGB sheet: rows press, slip, twist; columns ``families`` fabric families
    (:func:`pick_across_families`). Each tile is the frame of peak force, labelled with fabric,
    action, force and contact area; the contact's bounding box and centroid (labels
    ``contact_bbox_px``, ``contact_centroid_px``, when present) in red and stam's centred crop
    (``crop``: fraction of the shorter side; default stam's cpu preset) in yellow. ``tile_px``: tile
    width, px (default: the frames' own, at most :data:`ACTION_TILE_MAX_PX`)."""
    root = Path(root)
    crop = STAM_CPU_CROP if crop is None else crop
    picks = pick_across_families(manifest, families)
    if not picks:
        raise GelsimError(f"{root} has no sequence in contact to show; generate the dataset first")
    names = {f["id"]: f["name"] for f in manifest.get("fabrics", [])}
    tiles: list[np.ndarray | None] = []
    for action in ACTIONS:
        for fam, by_action in picks:
            s = by_action.get(action)
            if s is None:
                tiles.append(None)
                continue
            with np.load(root / s["labels"]) as z:
                lab = {k: z[k] for k in z.files}
            k = int(np.argmax(lab["normal_force_n"]))
            frame = read_video(root / s["video"])[k]
            h, w = frame.shape[:2]
            width = min(w, ACTION_TILE_MAX_PX) if tile_px is None else tile_px
            tile = frame.copy() if width == w else _tile(frame, width)
            scale = tile.shape[1] / w

            def px(x: float, y: float) -> tuple[int, int]:
                # edges in source px -> tile px (pixel centres at integers in both)
                return int(round((x + 0.5) * scale - 0.5)), int(round((y + 0.5) * scale - 0.5))

            tile = _label(tile, f"{s['fabric_id']} {names.get(s['fabric_id'], '')}, {fam}"[:40])
            tile = _label(tile, f"{action} {lab['normal_force_n'][k]:.1f} N {lab['contact_area_mm2'][k]:.0f} mm2",
                          line=1)
            # the boxes over the captions: on a small tile they cross them
            x0, y0, x1, y1 = crop_box_px(w, h, crop)
            cv2.rectangle(tile, px(x0, y0), px(x1, y1), CROP_COLOUR, 1)
            if "contact_bbox_px" in lab and np.isfinite(lab["contact_bbox_px"][k]).all():
                bx0, by0, bx1, by1 = (float(v) for v in lab["contact_bbox_px"][k])
                cv2.rectangle(tile, px(bx0, by0), px(bx1, by1), CONTACT_COLOUR, 1)
                cx, cy = (float(v) for v in lab["contact_centroid_px"][k])
                cv2.drawMarker(tile, px(cx, cy), CONTACT_COLOUR, cv2.MARKER_CROSS, 9, 1)
            tiles.append(tile)
    shape = next(t.shape for t in tiles if t is not None)
    blank = np.full(shape, 255, np.uint8)
    return _grid([blank if t is None else t for t in tiles], len(picks))
