"""Preview images of a generated dataset: a frame strip per action and a contact sheet."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from .video import read_video

LABEL_SCALE = 0.4  # OpenCV Hershey font scale for 160-320 px tiles


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _tile(img: np.ndarray, width: int) -> np.ndarray:
    h = round(img.shape[0] * width / img.shape[1])
    return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)


def frame_strip(frames: np.ndarray, n: int = 6, width: int = 240, onset: int | None = None) -> np.ndarray:
    """``n`` evenly spaced frames side by side, each labelled with its index (and contact state)."""
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    tiles = []
    for i in idx:
        tag = f"t={i}" + ("" if onset is None else (" contact" if i >= onset >= 0 else " pre"))
        tiles.append(_label(_tile(frames[i], width), tag))
    return np.concatenate(tiles, axis=1)


def write_previews(root: Path, manifest: dict, *, tile_px: int = 160) -> list[Path]:
    """Write ``previews/<action>.png`` strips and ``previews/contact_sheet.png``; returns the paths."""
    root = Path(root)
    out_dir = root / "previews"
    out_dir.mkdir(exist_ok=True)
    seqs = [s for s in manifest["sequences"] if "video" in s]
    written = []
    for action in ("press", "slip", "twist"):
        s = next((s for s in seqs if s["action"] == action), None)
        if s is None:
            continue
        frames = read_video(root / s["video"])
        strip = frame_strip(frames, onset=s.get("contact_onset"))
        p = out_dir / f"{action}.png"
        _write_png(p, strip)
        written.append(p)
    # Contact sheet: per fabric, the frame of peak force of its first sequence.
    tiles = []
    names = {f["id"]: f["name"] for f in manifest.get("fabrics", [])}
    seen = set()
    for s in seqs:
        if s["fabric_id"] in seen:
            continue
        seen.add(s["fabric_id"])
        with np.load(root / s["labels"]) as z:
            k = int(np.argmax(z["normal_force_n"]))
        frames = read_video(root / s["video"])
        tiles.append(_label(_tile(frames[k], tile_px), f"{s['fabric_id']} {names.get(s['fabric_id'], '')}"[:28]))
    if tiles:
        cols = min(10, len(tiles))
        rows = math.ceil(len(tiles) / cols)
        th, tw = tiles[0].shape[:2]
        sheet = np.full((rows * th, cols * tw, 3), 255, np.uint8)
        for i, t in enumerate(tiles):
            r, c = divmod(i, cols)
            sheet[r * th:(r + 1) * th, c * tw:(c + 1) * tw] = t
        p = out_dir / "contact_sheet.png"
        _write_png(p, sheet)
        written.append(p)
    return written


def _write_png(path: Path, rgb: np.ndarray) -> None:
    tmp = path.with_name(f".{path.stem}.partial.png")
    cv2.imwrite(str(tmp), rgb[:, :, ::-1])
    tmp.replace(path)
