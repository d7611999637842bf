"""A look at one sequence of a dataset (``gelsim show``): its frames, its marker field, its labels over time.

:func:`show` writes into a folder:

* ``frames.png``: evenly spaced frames, each as the dataset holds it and below it the same frame minus the
  flat gel of the dataset's sensor (:func:`gelsim.dataset.dataset_flat_frame`), contrast stretched (each
  frame's gain in its caption);
* ``markers.png``: the markers' displacement from rest as arrows (magnified, the magnification in the
  caption) over the frame minus the flat gel, at the first contact frame and the frames of peak force,
  shear and twist;
* ``labels.png``: the labels over time: normal and tangential force (N), shear (mm), twist (degrees),
  contact area (mm^2), the contact onset and the slipping frames marked; and the nuisance applied to each
  frame when the dataset has a per-frame nuisance record for the sequence
  (:func:`gelsim.annotate.nuisance_record`);
* ``video.mp4`` (``video=True``): the sequence slowed down, each frame beside its difference with the
  marker arrows and the labels written on it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .annotate import (arrow_gain, caption, draw_arrows, nuisance_record, read_frames, stretched_differences, tile,
                       varying_nuisance)
from .errors import GelsimError

#: Frames in the strip of ``frames.png`` (the first, the last, and evenly between).
DEFAULT_FRAMES = 8
#: Widest tile of the strip, px: 320 px frames at their own size; 960 px frames at a third.
STRIP_TILE_MAX_PX = 320
#: Panels of ``markers.png`` and the video are drawn at least this wide, px (small frames enlarged, so
#: that the arrows and captions stay legible).
PANEL_MIN_PX = 480
#: Playback rate of ``video.mp4``, frames per second: the 30 Hz camera slowed about three times, so
#: that a 1 s press lasts long enough to follow.
VIDEO_FPS = 10.0
@dataclass(frozen=True)
class SequenceLook:
    """What :func:`show` draws of one sequence: its manifest entry, uint8 RGB ``frames`` (T, H, W, 3), its
    ``labels`` (key -> array, :data:`gelsim.schema.LABELS`), the flat gel ``flat`` (H, W, 3), the sensor's
    frame rate (Hz) and the nuisance record (key -> per-frame array, or None)."""
    root: Path
    sequence: dict
    frames: np.ndarray
    labels: dict
    flat: np.ndarray
    fps_hz: float
    nuisance: dict | None

    @property
    def onset(self) -> int | None:
        """The first contact frame (None: no contact)."""
        onset = self.sequence.get("contact_onset")
        return None if onset is None or onset < 0 else int(onset)


def load_look(root: str | Path, sequence_id: str | None = None) -> SequenceLook:
    """The :class:`SequenceLook` of ``sequence_id`` in the dataset at ``root`` (None: the first sequence with a
    contact), its video and labels read and its flat gel rendered."""
    from .dataset import dataset_flat_frame
    from .schema import load_manifest

    root = Path(root)
    m = load_manifest(root)
    done = [s for s in m.get("sequences", []) if "video" in s and "labels" in s]
    if not done:
        raise GelsimError(f"{root} holds no finished sequence yet; finish it with the gelsim generate command "
                          "that made it")
    if sequence_id is None:
        seq = next((s for s in done if (s.get("contact_onset") if s.get("contact_onset") is not None else -1) >= 0),
                   done[0])
    else:
        seq = next((s for s in done if s["id"] == sequence_id), None)
        if seq is None:
            listed = any(s.get("id") == sequence_id for s in m.get("sequences", []))
            why = "is not finished yet" if listed else "is not in its manifest"
            raise GelsimError(f"sequence {sequence_id!r} of {root} {why}; give one of its ids, e.g. {done[0]['id']} "
                              f"(ids: {root / 'manifest.json'}, sequences[].id)")
    frames = read_frames(root, seq)
    try:
        with np.load(root / seq["labels"]) as z:
            labels = {k: np.asarray(z[k]) for k in z.files}
    except Exception as e:
        raise GelsimError(f"cannot read the labels {root / seq['labels']} ({type(e).__name__}); check the dataset "
                          f"with `gelsim verify {root}`") from None
    fps = float((m.get("profile") or {}).get("fps_hz") or 30.0)
    return SequenceLook(root, seq, frames, labels, dataset_flat_frame(m, seq), fps, nuisance_record(root, seq))


def pick_frames(count: int, n: int) -> list[int]:
    """``n`` frame indices evenly spaced over ``count`` frames, the first and the last included."""
    n = max(1, min(int(n), count))
    return sorted({int(round(v)) for v in np.linspace(0, count - 1, n)})


def _state(look: SequenceLook, t: int) -> str:
    lab = look.labels
    force = f", {float(lab['normal_force_n'][t]):.2f} N" if "normal_force_n" in lab else ""
    if "in_contact" in lab:
        where = " contact" if bool(lab["in_contact"][t]) else (" before contact" if look.onset is None or t < look.onset
                                                                else " released")
    else:
        where = "" if look.onset is None else (" contact" if t >= look.onset else " before contact")
    return f"t={t} ({t / look.fps_hz:.2f} s){force}{where}"


def frame_strip(look: SequenceLook, n: int = DEFAULT_FRAMES) -> np.ndarray:
    """uint8 RGB: ``n`` frames side by side (:func:`pick_frames`), the frame above, minus the flat gel below."""
    idx = pick_frames(len(look.frames), n)
    diffs, gains = stretched_differences(look.frames[idx], look.flat)
    width = min(look.frames.shape[2], STRIP_TILE_MAX_PX)
    top, bottom = [], []
    for k, t in enumerate(idx):
        top.append(caption(tile(look.frames[t], width), _state(look, t).split(", ", 1)))
        bottom.append(caption(tile(diffs[k], width), ["minus the flat gel", f"stretched x{gains[k]:.0f}"]))
    return np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)


def marker_frames(look: SequenceLook, limit: int = 4) -> list[int]:
    """The frames ``markers.png`` shows: the first contact frame and those of peak force, shear and twist
    (each once, in order), at most ``limit``; the last frame when nothing touches."""
    lab = look.labels
    onset = look.onset
    if onset is None:
        return [len(look.frames) - 1]
    picks = [onset]
    for key in ("normal_force_n", "shear_mm", "twist_deg"):
        if key in lab:
            v = np.asarray(lab[key], float).reshape(len(look.frames), -1)
            picks.append(int(np.argmax(np.hypot.reduce(v, axis=1) if v.shape[1] > 1 else np.abs(v[:, 0]))))
    return sorted(dict.fromkeys(picks))[:limit]


def _enlarge(img: np.ndarray) -> tuple[np.ndarray, float]:
    """``img`` enlarged to at least :data:`PANEL_MIN_PX` wide (whole-number factor), and the factor."""
    k = max(1, math.ceil(PANEL_MIN_PX / img.shape[1]))
    if k == 1:
        return img, 1.0
    import cv2

    return cv2.resize(img, (img.shape[1] * k, img.shape[0] * k), interpolation=cv2.INTER_NEAREST), float(k)


def marker_panel(look: SequenceLook, t: int, diff: np.ndarray, gain: float, arrows: float) -> np.ndarray:
    """Frame ``t``'s difference image ``diff`` (uint8) enlarged, with the markers' displacement from rest as
    arrows ``arrows`` times their length, captioned."""
    lab = look.labels
    img, k = _enlarge(diff)
    lines = [_state(look, t)]
    if "markers_xy_px" in lab and "markers_rest_px" in lab:
        rest = np.asarray(lab["markers_rest_px"], float)
        now = np.asarray(lab["markers_xy_px"][t], float)
        # pixel centres at integers in both images: x_big = (x + 0.5) k - 0.5
        img = draw_arrows(img, (rest + 0.5) * k - 0.5, (now + 0.5) * k - 0.5, arrows)
        moved = np.hypot(*(now - rest).T)
        lines.append(f"markers moved up to {np.nanmax(moved):.2f} px; arrows x{arrows:.0f}")
    else:
        lines.append("no marker labels in this dataset")
    lines.append(f"frame minus the flat gel, x{gain:.0f}")
    return caption(img, lines)


def marker_sheet(look: SequenceLook) -> np.ndarray:
    """uint8 RGB: :func:`marker_panel` at each of :func:`marker_frames`, side by side, one arrow scale."""
    idx = marker_frames(look)
    diffs, gains = stretched_differences(look.frames[idx], look.flat)
    lab = look.labels
    arrows = 1.0
    if "markers_xy_px" in lab and "markers_rest_px" in lab:
        arrows = arrow_gain(np.asarray(lab["markers_xy_px"], float)[idx] - np.asarray(lab["markers_rest_px"], float))
    return np.concatenate([marker_panel(look, t, d, g, arrows) for t, d, g in zip(idx, diffs, gains)], axis=1)


#: The panels of ``labels.png``: (title, unit, [(label key, column or None, line name)]).
LABEL_PANELS = (
    ("normal force", "N", [("normal_force_n", None, "normal")]),
    ("tangential force", "N", [("tangential_force_n", 0, "x"), ("tangential_force_n", 1, "y")]),
    ("gel shear", "mm", [("shear_mm", 0, "x"), ("shear_mm", 1, "y")]),
    ("gel twist", "degrees", [("twist_deg", None, "twist")]),
    ("contact area", "mm^2", [("contact_area_mm2", None, "area")]),
)


def labels_figure(look: SequenceLook, path: Path) -> Path:
    """Write the labels over time (:data:`LABEL_PANELS`, and a panel per nuisance record value that changes
    over the sequence, :func:`varying_nuisance`) to ``path`` (PNG, atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .atomic import write_figure

    lab, count = look.labels, len(look.frames)
    panels = [p for p in LABEL_PANELS if any(key in lab for key, _, _ in p[2])]
    nuisance = varying_nuisance(look.nuisance, count)
    rows = len(panels) + len(nuisance)
    fig, axes = plt.subplots(rows, 1, figsize=(8, 1.6 * rows + 0.8), sharex=True, squeeze=False)
    t = np.arange(count)
    for ax, (title, unit, lines) in zip(axes[:, 0], panels):
        for key, col, name in lines:
            if key in lab:
                v = np.asarray(lab[key], float)
                ax.plot(t, v if col is None else v[:, col], label=name, lw=1.5)
        ax.set_ylabel(f"{title}\n({unit})", fontsize=8)
        if len(lines) > 1:
            ax.legend(fontsize=7, loc="upper right")
    for ax, (key, v) in zip(axes[len(panels):, 0], nuisance.items()):
        if v.ndim == 1:
            ax.plot(t, v, lw=1.5, color="tab:purple")
        else:
            for c in range(v.shape[1]):
                ax.plot(t, v[:, c], lw=1.2, label="RGB"[c] if v.shape[1] == 3 else f"[{c}]")
            ax.legend(fontsize=7, loc="upper right")
        ax.set_ylabel(f"nuisance:\n{key}", fontsize=8)
    slipping = np.asarray(lab.get("slipping", np.zeros(count, bool)), bool)
    for ax in axes[:, 0]:
        if look.onset is not None:
            ax.axvline(look.onset, color="k", ls="--", lw=1)
        for k in np.flatnonzero(slipping):
            ax.axvspan(k - 0.5, k + 0.5, color="orange", alpha=0.15, lw=0)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(f"frame ({look.fps_hz:g} per second)")
    s = look.sequence
    onset = "no contact" if look.onset is None else f"contact from frame {look.onset} (dashed)"
    extra = "; slipping frames shaded" if slipping.any() else ""
    if look.nuisance is not None and not nuisance:
        extra += "; nuisance record: nothing applied"
    fig.suptitle(f"{s['id']}: {s.get('action', '')} on fabric {s.get('fabric_id')}, {onset}{extra}", fontsize=9)
    fig.tight_layout()
    return write_figure(path, fig, dpi=100)


def video_frames(look: SequenceLook):
    """The frames of ``video.mp4``: each frame (enlarged as :func:`marker_panel`) beside its difference with
    the marker arrows, captioned; uint8 RGB, even sizes (H.264's 4:2:0 needs them)."""
    diffs, gains = stretched_differences(look.frames, look.flat)
    lab = look.labels
    arrows = 1.0
    if "markers_xy_px" in lab and "markers_rest_px" in lab:
        arrows = arrow_gain(np.asarray(lab["markers_xy_px"], float) - np.asarray(lab["markers_rest_px"], float))
    for t in range(len(look.frames)):
        left, _ = _enlarge(look.frames[t])
        left = caption(left, [f"{look.sequence['id']} {look.sequence.get('action', '')}", _state(look, t)])
        right = marker_panel(look, t, diffs[t], gains[t], arrows)
        both = np.concatenate([left, right], axis=1)
        h, w = both.shape[:2]
        yield both[:h - h % 2, :w - w % 2]


def show(root: str | Path, sequence_id: str | None = None, out: str | Path | None = None, *,
         frames: int = DEFAULT_FRAMES, video: bool = False, look: SequenceLook | None = None) -> dict:
    """Write the pictures of one sequence (see the module docstring) into ``out`` (default
    ``ROOT/previews/<sequence id>``); returns ``{"sequence", "out", "files", "frames", "contact_onset",
    "nuisance_record"}``."""
    from .atomic import write_png

    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise GelsimError(f"--frames {frames!r} is invalid; give how many frames the strip shows, 1 or more")
    look = look or load_look(root, sequence_id)
    folder = Path(out) if out is not None else Path(root) / "previews" / look.sequence["id"]
    files = [write_png(folder / "frames.png", frame_strip(look, frames)),
             write_png(folder / "markers.png", marker_sheet(look)),
             labels_figure(look, folder / "labels.png")]
    if video:
        from .video import write_video

        files.append(write_video(folder / "video.mp4", video_frames(look), fps=VIDEO_FPS))
    return {"sequence": look.sequence["id"], "out": str(folder), "files": [str(f) for f in files],
            "frames": len(look.frames), "contact_onset": look.onset, "nuisance_record": look.nuisance is not None}
