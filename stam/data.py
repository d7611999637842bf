"""Reader for ``gelsim generate`` datasets: manifest checks, frame cache, contact onset,
windows of n consecutive frames.

Layout read (:mod:`gelsim.schema`, written by gelsim.dataset): ``DIR/manifest.json`` of the format
and version gelsim.schema names, ``complete == true``, ``fabrics`` (id, name, family) and
``sequences`` (at least gelsim.schema.READ_FIELDS: id, fabric_id, num_frames, split, video; also
action and contact_onset when present). Videos are read with :func:`gelsim.video.read_video`.

Decoded frames are resized (squashed) to ``S x S`` px with area averaging and cached as
``uint8 (T, S, S, 3)`` ``.npy`` files under ``DIR/.stam-cache/`` (or a user cache directory
when DIR is read-only), written atomically, so that only the first pass decodes video. A cache
file's name holds the sequence id and :meth:`TactileDataset.cache_key` (the video's checksum, size
and modification time), so a video changed since is decoded again.
Beside them per-frame contact scores (``float32 (T, 2)``) and the sequence's noise level are
cached (``.npz``) for onset detection.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from gelsim import schema
from gelsim.atomic import atomic_open
from gelsim.errors import check_choice
from gelsim.schema import SPLITS

from .errors import StamError
from .stats import wilson_interval

STARTS = ("contact", "zero")
ONSETS = ("detected", "true")
# Input normalisation: tactile frames are not ImageNet photos and no ImageNet statistics
# apply to a backbone pretrained on tactile frames; a fixed affine map of [0, 1] to about
# [-2, 2] keeps activations of the order of 1 for every channel.
NORM_MEAN = 0.5
NORM_STD = 0.25
# Contact onset from the images. Each frame is shrunk with area averaging to thumbnails
# THUMB_WIDTH_PX wide (the same relative scale at any render resolution: 2 x 2 px averaged at
# 320x240, 6 x 6 at 960x720; at least 2 x 2 below 320 px, where whole-DN codec steps in single
# pixels reach 5.2 DN). The change between two thumbnails is the SCORE_PERCENTILE over
# pixels of the per-pixel RGB distance |a - b| (L2 over the three channels, DN 0-255): the three
# LEDs light the gel from 120 degrees apart, so a slope brightens one channel and darkens
# another and a grey average cancels much of a light first touch. The 99.9th percentile is the
# top ~19 of 160 x 120 thumbnail pixels, about 0.3 mm^2 of gel: a first touch (2-25 mm^2) fills it.
# The onset is the first frame t >= 1 whose change from frame t - 1 exceeds the threshold (a touch
# appears within one frame interval), or whose change from frame 0 exceeds ONSET_DRIFT_FACTOR
# times it (a contact that builds up more slowly than the threshold per frame).
#
# The bar is the larger of a floor in DN and NOISE_FACTOR times the sequence's own noise level
# (see noise_level). In gelsim's H.264 video (CRF 18) the noise left in still frames is the
# codec's (whole-DN block shifts; most pixels of consecutive pre-contact frames are bit-identical,
# so the noise level measures 0) and the floor decides; in lossless video (--format ffv1) the
# camera's noise is there (0.74 DN at 320x240) and still below the floor; a noisier camera raises
# the bar with its noise. A bar proportional to the noise alone cannot work on H.264 video (it
# would be 0), nor one proportional to a typical frame-to-frame change (the 25th percentile of
# the sequence's changes, times 1.2-6: at best 104/200 and 25/40 within one frame on the sets below).
THUMB_WIDTH_PX = 160
SCORE_PERCENTILE = 99.9
# Chosen on `gelsim generate --preset cpu --fabrics 20` (seed 0, 200 sequences, 320x240) and
# `--resolution 960x720 --sequences-per-fabric 2 --fabrics 20` (seed 0, 40 sequences), where every
# threshold from 4.5 to 6.0 DN agreed within one frame on >= 199/200 and 40/40: there the largest
# pre-contact frame-to-frame change was 4.3 DN (320x240) and 3.5 DN (960x720), the smallest change
# into a contact frame 7.9 and 18.0 DN. Held out (other seeds), within one frame of the true onset:
# 399/400 at 320x240 (`--preset cpu --fabrics 40 --seed 1`; 95% CI 98.6-100%) and 178/180 at 960x720
# (`--fabrics 20 --sequences-per-fabric 3 --seed 1` and `--fabrics 40 ... --seed 2`; 96.0-99.7%);
# the grey detector before it: 349/400 and 160/180. More in docs/stam.md.
DEFAULT_ONSET_THRESHOLD = 5.0
# The change from frame 0 accumulates the codec's drift over a long approach (up to 5.2 DN by
# frame 12 on the 320x240 set above, 3.8 DN at 960x720), so it needs a higher bar than one
# frame-to-frame step; any factor from 1.6 to 4 gave the same detections on the tuning sets.
ONSET_DRIFT_FACTOR = 2.0
# Pure noise of per-channel standard deviation s gives RGB distances distributed as s x chi(3 dof),
# whose 99.9th percentile is 4.0 s; 6 s leaves a margin of 1.5 so that noise alone stays below the
# bar. On lossless 320x240 video (noise level 0.74 DN) the largest pre-contact change was 3.8 s.
NOISE_FACTOR = 6.0


def centre_square(frame: np.ndarray, crop: float) -> np.ndarray:
    """The centred square of side ``round(crop * min(H, W))`` of ``frame`` (a view); the whole frame at crop 1
    (``gelsim.stats.crop_box_px`` draws the same box on the previews)."""
    if crop == 1.0:
        return frame
    h, w = frame.shape[:2]
    side = max(1, round(crop * min(h, w)))
    y0, x0 = (h - side) // 2, (w - side) // 2
    return frame[y0:y0 + side, x0:x0 + side]


def model_input(frame: np.ndarray, size: int, crop: float = 1.0) -> np.ndarray:
    """What the models see of a ``uint8 (H, W, 3)`` frame: :func:`centre_square` at ``crop``, squashed to
    ``size x size`` px by area averaging."""
    return cv2.resize(centre_square(frame, crop), (size, size), interpolation=cv2.INTER_AREA)


def load_manifest(data_dir: str | Path) -> dict:
    """Read and check ``DIR/manifest.json`` (:func:`gelsim.schema.load_manifest`); raise StamError for a
    missing, foreign or incomplete dataset, or one a sequence of which lacks what stam reads."""
    return schema.load_manifest(data_dir, complete=True, error=StamError)


_said: set[str] = set()


def _say_once(line: str) -> None:
    """``line`` on stderr once per process, when a person watches (stderr a terminal): what a first run does
    before its first epoch (a dataset of 2,000 sequences takes minutes to decode)."""
    import sys

    if line not in _said and sys.stderr.isatty():
        _said.add(line)
        print(line, file=sys.stderr, flush=True)


def _writable(d: Path) -> bool:
    """Whether files can be written in folder ``d``, or in the folder that would hold it (``d`` is made
    when the first file is cached: a command that stops before leaves nothing behind)."""
    target = d if d.exists() else d.parent
    try:
        probe = target / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def default_cache_dir(data_dir: Path) -> Path:
    """``DIR/.stam-cache`` if writable, else ``$XDG_CACHE_HOME/stam/<hash of DIR>``."""
    d = data_dir / ".stam-cache"
    if d.parent.is_dir() and _writable(d):
        return d
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "stam"
    return base / hashlib.sha256(str(data_dir.resolve()).encode()).hexdigest()[:16]


def _save_atomic(path: Path, arr: np.ndarray | None = None, **arrays: np.ndarray) -> None:
    """Write ``arr`` as .npy, or ``arrays`` as (uncompressed) .npz, atomically (gelsim.atomic)."""
    with atomic_open(path) as f:
        if arrays:
            np.savez(f, **arrays)
        else:
            np.save(f, arr)


def thumbnails(frames: np.ndarray) -> np.ndarray:
    """``uint8 (T, H, W, 3)`` frames -> ``float32 (T, h, w, 3)`` thumbnails THUMB_WIDTH_PX wide
    (area averaging; frames narrower than that are kept at their size)."""
    t, h, w = frames.shape[:3]
    tw = max(1, min(w // 2, THUMB_WIDTH_PX))
    size = (tw, max(1, round(h * tw / w)))
    # Float before shrinking: averaging in uint8 would quantise the score to whole DN.
    return np.stack([cv2.resize(f.astype(np.float32), size, interpolation=cv2.INTER_AREA) for f in frames])


def change_score(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Change between thumbnails ``a`` and ``b`` (``float32 (..., h, w, 3)``, broadcast): the
    SCORE_PERCENTILE over pixels of the RGB distance ``|a - b|``, DN; shape ``a.shape[:-3]``."""
    d = np.sqrt(np.square(a - b).sum(-1))
    return np.percentile(d.reshape(*d.shape[:-2], -1), SCORE_PERCENTILE, axis=-1).astype(np.float32)


def noise_level(thumbs: np.ndarray) -> float:
    """Noise of a sequence's thumbnails ``float32 (T, h, w, 3)``, DN: the per-channel standard
    deviation of frame-to-frame differences, 1.4826 x their median absolute deviation over
    pixels and channels (robust to a contact covering less than half the gel), for the quietest
    pair of consecutive frames (a still sensor, whenever it occurs); 0 for a single frame."""
    if thumbs.shape[0] < 2:
        return 0.0
    d = (thumbs[1:] - thumbs[:-1]).reshape(thumbs.shape[0] - 1, -1)
    mad = np.median(np.abs(d - np.median(d, axis=1, keepdims=True)), axis=1)
    return float(1.4826 * mad.min())  # 1.4826: MAD to standard deviation for Gaussian noise


def contact_scores(frames: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-frame contact scores of ``uint8 (T, H, W, 3)`` frames: ``float32 (T, 2)``, DN, column 0
    the change from frame 0, column 1 the change from the previous frame (0 for frame 0; see
    :func:`change_score`), and the sequence's noise level in DN (:func:`noise_level`)."""
    th = thumbnails(frames)
    out = np.zeros((th.shape[0], 2), np.float32)
    out[:, 0] = change_score(th, th[:1])
    out[1:, 1] = change_score(th[1:], th[:-1])
    return out, noise_level(th)


def onset_bar(threshold: float, noise_dn: float) -> float:
    """The frame-to-frame change, DN, above which a frame counts as a touch."""
    return max(threshold, NOISE_FACTOR * noise_dn)


def detect_onset(scores: np.ndarray, threshold: float = DEFAULT_ONSET_THRESHOLD, noise_dn: float = 0.0) -> int | None:
    """First contact frame from :func:`contact_scores`' ``(T, 2)`` scores and noise level: the
    first frame ``t >= 1`` whose change from frame ``t - 1`` exceeds the bar (``threshold`` DN,
    or NOISE_FACTOR x ``noise_dn`` if larger) or whose change from frame 0 exceeds
    ONSET_DRIFT_FACTOR x the bar; None when there is none. Frame 0 is the reference, so a contact
    already under way there is reported at frame 1 at the earliest."""
    s = np.asarray(scores, np.float64)
    if s.ndim != 2 or s.shape[1] != 2:
        raise StamError(f"contact scores must have shape (T, 2), got {s.shape}; compute them with contact_scores")
    bar = onset_bar(threshold, noise_dn)
    hit = (s[:, 1] > bar) | (s[:, 0] > ONSET_DRIFT_FACTOR * bar)
    hit[0] = False
    above = np.flatnonzero(hit)
    return int(above[0]) if above.size else None


@dataclass
class Sequence:
    id: str
    label: int
    num_frames: int
    split: str
    action: str
    true_onset: int | None
    video: Path


class TactileDataset:
    """A checked ``gelsim generate`` dataset: class labels, sequences, cached frames."""

    def __init__(self, data_dir: str | Path, cache_dir: str | Path | None = None, crop: float = 1.0):
        if not 0.05 <= crop <= 1.0:
            raise StamError(f"crop {crop} is out of range; give the kept fraction of the frame, 0.05-1")
        # crop: side of a centred square kept from each frame, as a fraction of the frame's shorter
        # side (1.0 = the whole frame squashed to a square, as the paper resized 960x720 to 224x224).
        # A smaller crop trades field of view for texture resolution at a given input size.
        self.crop = float(crop)
        self.dir = Path(data_dir)
        self.manifest = load_manifest(self.dir)
        self.fabric_ids = sorted(f["id"] for f in self.manifest["fabrics"])
        names = {f["id"]: f.get("name", str(f["id"])) for f in self.manifest["fabrics"]}
        self.class_names = [names[i] for i in self.fabric_ids]
        label_of = {fid: i for i, fid in enumerate(self.fabric_ids)}
        self.sequences = [
            Sequence(s["id"], label_of[s["fabric_id"]], int(s["num_frames"]), s["split"], s.get("action", ""),
                     s.get("contact_onset"), self.dir / s["video"])
            for s in self.manifest["sequences"]]
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir(self.dir)
        self._video_sha = {s["id"]: str((s.get("sha256") or {}).get("video", "")) for s in self.manifest["sequences"]}

    @property
    def num_classes(self) -> int:
        return len(self.fabric_ids)

    def split(self, name: str) -> list[Sequence]:
        check_choice("split", name, SPLITS, StamError)
        return [s for s in self.sequences if s.split == name]

    def cache_key(self, seq: Sequence) -> str:
        """What ``seq``'s cached frames and scores were made from: the manifest's checksum of its video and
        the video's size and modification time (ns; for a directory of PNGs, over its files), hashed to 16
        hex digits. A video regenerated or copied over since gets another key, so its stale cache is not
        read (the cache was keyed by the sequence id alone)."""
        v = seq.video
        try:
            if v.is_dir():
                stats = [f.stat() for f in sorted(v.iterdir())]
                size, mtime = sum(st.st_size for st in stats), max((st.st_mtime_ns for st in stats), default=0)
            else:
                st = v.stat()
                size, mtime = st.st_size, st.st_mtime_ns
        except FileNotFoundError:
            raise StamError(f"video {v} listed in the manifest is missing; regenerate the dataset") from None
        text = f"{self._video_sha.get(seq.id, '')}:{size}:{mtime}"
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def check_video(self, seq: Sequence) -> None:
        """StamError naming ``seq``'s video when it does not match the manifest's checksum (changed or
        truncated since it was written: it might still decode, into other frames). Called before the one
        decode whose frames are cached: a video changed since gets another cache key (:meth:`cache_key`),
        so it is checked again."""
        want = self._video_sha.get(seq.id)
        if want and schema.sha256_of(seq.video) != want:
            raise StamError(f"video {seq.video} does not match the manifest's checksum (changed or truncated since "
                            f"it was written); regenerate it (rerun gelsim generate with the same options after "
                            f"deleting it) or see `gelsim verify {self.dir}`")

    def _paths(self, seq: Sequence, size: int) -> tuple[Path, Path]:
        d = self.cache_dir / (f"{size}px" if self.crop == 1.0 else f"{size}px-crop{self.crop:g}")
        key = f"{seq.id}-{self.cache_key(seq)}"
        return d / f"{key}.npy", self.cache_dir / "scores-v4" / f"{key}.npz"

    def prepare(self, seq: Sequence, size: int) -> None:
        """Decode ``seq`` once and cache its resized frames and contact scores."""
        fpath, spath = self._paths(seq, size)   # (a missing video is said here)
        if fpath.is_file() and spath.is_file():
            return
        from gelsim.video import read_video

        self.check_video(seq)
        _say_once(f"stam: decoding {self.dir}'s videos into the frame cache {self.cache_dir} (first read of each only) ...")
        frames = read_video(seq.video)
        if frames.shape[0] < 1:
            raise StamError(f"video {seq.video} has no frames; regenerate the dataset")
        fpath.parent.mkdir(parents=True, exist_ok=True)
        spath.parent.mkdir(parents=True, exist_ok=True)
        if not spath.is_file():
            scores, noise = contact_scores(frames)
            _save_atomic(spath, scores=scores, noise_dn=np.float32(noise))
        if not fpath.is_file():
            small = np.stack([model_input(f, size, self.crop) for f in frames])
            _save_atomic(fpath, small)

    def frames(self, seq: Sequence, size: int) -> np.ndarray:
        """``uint8 (T, size, size, 3)`` RGB frames of ``seq`` (memory-mapped from the cache)."""
        self.prepare(seq, size)
        return np.load(self._paths(seq, size)[0], mmap_mode="r")

    def scores(self, seq: Sequence, size: int) -> tuple[np.ndarray, float]:
        """Cached :func:`contact_scores` of ``seq``: ``float32 (T, 2)`` and the noise level, DN."""
        self.prepare(seq, size)
        with np.load(self._paths(seq, size)[1]) as z:
            return z["scores"], float(z["noise_dn"])

    def onset(self, seq: Sequence, size: int, mode: str = "detected",
              threshold: float = DEFAULT_ONSET_THRESHOLD) -> int | None:
        """First contact frame: detected from the images (the paper's way) or the manifest's."""
        if mode == "true":
            return seq.true_onset
        scores, noise = self.scores(seq, size)
        return detect_onset(scores, threshold, noise)

    def onset_agreement(self, size: int, threshold: float = DEFAULT_ONSET_THRESHOLD) -> dict:
        """How often the detected onset matches the manifest's ``contact_onset``: counts, rates
        with 95% Wilson intervals, the histogram of detected - true (frames), the same for
        sequences whose true onset is frame 0 (detectable at frame 1 at the earliest) and
        later, and the confusion of true (rows) against detected onsets."""
        errors: dict[int, int] = {}
        by_start = {"true_onset_0": [0, 0, 0], "true_onset_1_plus": [0, 0, 0]}  # sequences, exact, within 1
        confusion: dict[int, dict[str, int]] = {}
        exact = within1 = missed = total = 0
        for s in self.sequences:
            if s.true_onset is None:
                continue
            d = self.onset(s, size, "detected", threshold)
            total += 1
            row = confusion.setdefault(int(s.true_onset), {})
            key = "none" if d is None else str(d)
            row[key] = row.get(key, 0) + 1
            group = by_start["true_onset_0" if s.true_onset == 0 else "true_onset_1_plus"]
            group[0] += 1
            if d is None:
                missed += 1
                continue
            e = d - int(s.true_onset)
            errors[e] = errors.get(e, 0) + 1
            exact += e == 0
            within1 += abs(e) <= 1
            group[1] += e == 0
            group[2] += abs(e) <= 1
        return {"sequences": total, "exact": exact, "within_1": within1, "not_detected": missed,
                "exact_rate": exact / total if total else None,
                "within_1_rate": within1 / total if total else None,
                "exact_ci95": wilson_interval(exact, total), "within_1_ci95": wilson_interval(within1, total),
                "mean_error_frames": (sum(e * c for e, c in errors.items()) / sum(errors.values())
                                      if errors else None),
                "error_histogram": {str(e): errors[e] for e in sorted(errors)},
                "by_true_onset": {k: {"sequences": v[0], "exact": v[1], "within_1": v[2]} for k, v in by_start.items()},
                "confusion": {str(t): {k: confusion[t][k] for k in sorted(confusion[t], key=_detected_order)}
                              for t in sorted(confusion)},
                "threshold_dn": threshold, "drift_factor": ONSET_DRIFT_FACTOR,
                "thumb_width_px": THUMB_WIDTH_PX, "score_percentile": SCORE_PERCENTILE}


def _detected_order(key: str) -> tuple[bool, int]:
    return key == "none", 0 if key == "none" else int(key)


def normalise(frames: np.ndarray) -> torch.Tensor:
    """``uint8 (..., S, S, 3)`` -> ``float32 (..., 3, S, S)`` normalised with NORM_MEAN/NORM_STD."""
    x = torch.from_numpy(np.array(frames, copy=True)).float().div_(255.0)  # copy: cache is a read-only mmap
    x = x.movedim(-1, -3)
    return (x - NORM_MEAN) / NORM_STD


class WindowDataset(Dataset):
    """Windows of ``n_frames`` consecutive frames of one split, with fabric labels.

    ``start="contact"``: the window starts at the first contact frame (detected from the
    images, or the manifest's with ``onset="true"``), shifted back when fewer than n frames
    remain; a sequence where no contact is detected uses its last n frames.
    ``start="zero"``: the window starts at frame 0 (pre-contact frames included).
    Items: ``(float32 n x 3 x S x S, int label)``, or backbone features ``n x C x h x w``
    when ``features`` (seq id -> ``T x C x h x w`` tensor) is given.
    """

    def __init__(self, data: TactileDataset, split: str, n_frames: int, start: str = "contact",
                 image_size: int = 224, onset: str = "detected",
                 threshold: float = DEFAULT_ONSET_THRESHOLD, features: dict | None = None):
        check_choice("start", start, STARTS, StamError)
        check_choice("onset", onset, ONSETS, StamError)
        self.data, self.n, self.size, self.features = data, n_frames, image_size, features
        seqs = data.split(split)
        if not seqs:
            raise StamError(f"dataset {data.dir} has no {split!r} sequences; regenerate it with a larger preset")
        shortest = min(s.num_frames for s in seqs)
        if not 1 <= n_frames <= shortest:
            raise StamError(f"n_frames={n_frames} is outside 1..{shortest} (the shortest {split} sequence); "
                              "choose a smaller n")
        self.items: list[tuple[Sequence, int]] = []
        self.shifted = self.undetected = 0
        for s in seqs:
            if start == "zero":
                first = 0
            else:
                o = data.onset(s, image_size, onset, threshold)
                if o is None:
                    self.undetected += 1
                    o = s.num_frames - n_frames
                first = min(o, s.num_frames - n_frames)
                self.shifted += first != o
            self.items.append((s, first))

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int):
        seq, first = self.items[i]
        if self.features is not None:
            return self.features[seq.id][first:first + self.n].float(), seq.label
        frames = self.data.frames(seq, self.size)
        if frames.shape[0] < first + self.n:
            raise StamError(f"video of {seq.id} has {frames.shape[0]} frames, the manifest says "
                              f"{seq.num_frames}; regenerate the dataset")
        return normalise(frames[first:first + self.n]), seq.label


class FrameDataset(Dataset):
    """Single frames of one split (for backbone pretraining): every ``stride``-th frame from
    the first detected contact onwards, or from frame 0 with ``contact_only=False``."""

    def __init__(self, data: TactileDataset, split: str, image_size: int, contact_only: bool = True,
                 threshold: float = DEFAULT_ONSET_THRESHOLD, stride: int = 1):
        self.data, self.size = data, image_size
        self.items = []
        for s in data.split(split):
            o = data.onset(s, image_size, "detected", threshold) if contact_only else 0
            # Neighbouring frames are near-duplicates: a stride > 1 costs little information.
            for t in range(0 if o is None else o, s.num_frames, max(1, stride)):
                self.items.append((s, t))

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int):
        seq, t = self.items[i]
        return normalise(self.data.frames(seq, self.size)[t]), seq.label


@torch.no_grad()
def backbone_features(backbone: torch.nn.Module, data: TactileDataset, seqs: list[Sequence],
                      image_size: int, batch_frames: int = 64) -> dict[str, torch.Tensor]:
    """Backbone features of every frame: seq id -> ``float16 T x C x h x w`` (frozen backbone)."""
    backbone.eval()
    out = {}
    for s in seqs:
        frames = data.frames(s, image_size)
        parts = [backbone(normalise(frames[i:i + batch_frames])).half()
                 for i in range(0, frames.shape[0], batch_frames)]
        out[s.id] = torch.cat(parts)
    return out
