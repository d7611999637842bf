"""The dataset format: one place for what ``gelsim generate`` writes and ``stam`` reads.

Its writers (:mod:`gelsim.dataset`, ``stam.synthetic``), its verifier (:func:`gelsim.dataset.verify`)
and its readers (:mod:`gelsim.dataset`, :mod:`gelsim.stats`, ``stam.data``) take the format's name and
version, the action and split names, the paths inside a dataset, the manifest's fields and the label
keys from here. docs/dataset.md's "Layout" section documents the same; ``tests/gelsim/test_schema.py``
checks that the two agree.

Layout of a dataset directory ``DIR``::

    DIR/manifest.json              the index (MANIFEST_FIELDS), replaced atomically
    DIR/videos/fNNN/<id>.mp4       one video per sequence (.mkv for FFV1, a directory of PNGs for PNG)
    DIR/labels/fNNN/<id>.npz       per-frame labels (LABELS)
    DIR/records/<id>.json          per-sequence record (checksums, timings), written last
    DIR/previews/...               figures (not part of the format: nothing reads them back)

A change that breaks a reader of ``FORMAT_VERSION`` (a field or key renamed, removed or changing
meaning) needs a new version; a new optional field or key does not.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import GelsimError

FORMAT = "gelsim-dataset"
FORMAT_VERSION = 1
ACTIONS = ("press", "slip", "twist")          # the hand's motions (gelsim.motion), in this order everywhere
SPLITS = ("train", "val", "test")

MANIFEST = "manifest.json"
VIDEOS_DIR = "videos"
LABELS_DIR = "labels"
RECORDS_DIR = "records"
NUISANCE_DIR = "nuisance"
PREVIEWS_DIR = "previews"


# ---------------------------------------------------------------- paths (relative to DIR, "/"-separated)

def sequence_id(fabric_id: int, index: int) -> str:
    """``f001-s0000``: the id of sequence ``index`` (from 0) of fabric ``fabric_id``."""
    return f"f{fabric_id:03d}-s{index:04d}"


def video_stem(fabric_id: int, seq_id: str) -> str:
    """``videos/fNNN/<id>``; the format adds its suffix (:func:`gelsim.video.video_path`)."""
    return f"{VIDEOS_DIR}/f{fabric_id:03d}/{seq_id}"


def labels_path(fabric_id: int, seq_id: str) -> str:
    """``labels/fNNN/<id>.npz``."""
    return f"{LABELS_DIR}/f{fabric_id:03d}/{seq_id}.npz"


def nuisance_path(fabric_id: int, seq_id: str) -> str:
    """``nuisance/fNNN/<id>.npz``: the sequence's per-frame nuisance record (:mod:`gelsim.nuisance.record`)."""
    return f"{NUISANCE_DIR}/f{fabric_id:03d}/{seq_id}.npz"


def record_path(seq_id: str) -> str:
    """``records/<id>.json``."""
    return f"{RECORDS_DIR}/{seq_id}.json"


def sha256_of(path: Path) -> str:
    """The checksum the manifest records: of the file, or of a PNG directory's frames in name order."""
    h = hashlib.sha256()
    files = sorted(path.glob("*.png")) if path.is_dir() else [path]
    for p in files:
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


# ---------------------------------------------------------------- manifest

#: Top-level fields of manifest.json, in the order they are written. ``libraries`` holds the versions of
#: the numeric libraries that wrote it (LIBRARIES; absent in datasets made before it existed). With
#: ``--units K`` two more follow it: ``unit_variation`` (the ranges drawn from) and ``units`` (each
#: unit's parameters).
MANIFEST_FIELDS = ("format", "format_version", "complete", "generator_version", "seed", "options",
                   "catalog_version", "profile", "fabrics", "splits", "libraries", "sequences")
#: Fields a manifest may hold between ``libraries`` and ``sequences``, added within FORMAT_VERSION 1 (older
#: datasets lack them): ``source`` (2026-11-27), the digest of the code and assets that made the dataset
#: (:func:`gelsim.provenance.source_digest`); ``render`` (2026-11-28): the backend, what ran on its device
#: (``--stages``), the devices that made the sequences and where the labels come from; ``unit_variation`` and
#: ``units`` (``--units K``).
OPTIONAL_MANIFEST_FIELDS = ("source", "render", "unit_variation", "units")
#: The ``libraries`` entry: the packages whose version changes a dataset's bytes (OpenCV 4.14 and 5.0 give
#: other fabric heightfields, so other contacts, labels and frames from the same seed).
LIBRARIES = ("numpy", "scipy", "opencv", "numba", "mujoco", "av")
#: The ``profile`` entry: the sensor the dataset was rendered for.
PROFILE_FIELDS = ("name", "width_px", "height_px", "mm_per_px", "fps_hz")
#: One ``fabrics`` entry.
FABRIC_FIELDS = ("id", "name", "family", "material")
#: One ``sequences`` entry of a finished sequence (+ ``unit`` with ``--units``): contact_onset is the
#: first frame in contact (-1: none), precontact_frames the frames before the motion's touch, video and
#: labels the paths above, sha256 ``{"video": ..., "labels": ...}``, peak_force_n in N.
SEQUENCE_FIELDS = ("id", "fabric_id", "action", "num_frames", "contact_onset", "precontact_frames", "split",
                   "video", "labels", "seed", "sha256", "peak_force_n")
#: After SEQUENCE_FIELDS where present: ``nuisance``, the per-frame nuisance record's path (every dataset made
#: from 2026-11-29; ``sha256`` then holds its checksum too), and ``unit`` (``--units``).
OPTIONAL_SEQUENCE_FIELDS = ("nuisance", "unit")
#: A sequence not generated yet has only these (the manifest of an interrupted run).
PLANNED_FIELDS = ("id", "fabric_id", "action", "num_frames", "split")
#: What a reader of frames needs of each sequence (stam).
READ_FIELDS = ("id", "fabric_id", "num_frames", "split", "video")


def make_manifest(*, complete: bool, generator_version: str, seed: int, options: dict, catalog_version: str,
                  profile: dict, fabrics: list[dict], libraries: dict, sequences: list[dict], **extra: Any) -> dict:
    """A manifest in MANIFEST_FIELDS order, ``splits`` counted from the sequences; ``extra`` fields
    (OPTIONAL_MANIFEST_FIELDS) go before ``sequences``."""
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "complete": bool(complete),
            "generator_version": generator_version, "seed": seed, "options": options,
            "catalog_version": catalog_version, "profile": {k: profile[k] for k in PROFILE_FIELDS},
            "fabrics": [{k: f[k] for k in FABRIC_FIELDS} for f in fabrics],
            "splits": {k: sum(1 for s in sequences if s.get("split") == k) for k in SPLITS},
            "libraries": {k: libraries[k] for k in LIBRARIES}, **extra, "sequences": sequences}


def sequence_entry(record: Mapping[str, Any]) -> dict:
    """The manifest's entry of a finished sequence from its record (SEQUENCE_FIELDS, ``nuisance`` and ``unit``
    if any: datasets made before the nuisance record have none; timings stay in the record: they vary from run
    to run)."""
    return {k: record[k] for k in SEQUENCE_FIELDS + tuple(k for k in OPTIONAL_SEQUENCE_FIELDS if k in record)}


def manifest_problem(m: Any) -> str | None:
    """Why ``m`` (a parsed manifest.json) is not this format, or None: a reader's first check."""
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        found = m.get("format") if isinstance(m, dict) else None
        return f"not a gelsim dataset (manifest format {found!r}, not {FORMAT!r})"
    if m.get("format_version") != FORMAT_VERSION:
        return f"format_version {m.get('format_version')!r}, this reader knows {FORMAT_VERSION}"
    return None


def load_manifest(root: str | Path, *, complete: bool = False, error: type[GelsimError] = GelsimError) -> dict:
    """The manifest of the dataset under ``root``, checked to be this format and version; the one loader
    of every reader (gelsim's commands, ``stam``).

    ``complete``: also require a finished dataset whose every sequence a reader of frames can use (its
    READ_FIELDS, a fabric the manifest lists, a known split), as ``stam`` needs. ``error``: the
    GelsimError subclass raised, one line naming the problem and the fix (``stam`` raises its own).
    """
    root = Path(root)
    path = root / MANIFEST
    if not root.is_dir():
        what = "is a file, not a dataset directory" if root.exists() else "does not exist"
        raise error(f"dataset directory {root} {what}; give the --out directory of gelsim generate")
    if not path.is_file():
        raise error(f"{root} is not a gelsim dataset (no {MANIFEST}); give a directory made by gelsim generate")
    try:
        m = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise error(f"cannot read {path} ({e}); regenerate the dataset") from None
    problem = manifest_problem(m)
    if problem:
        raise error(f"{path}: {problem}; give a directory made by this version of gelsim generate")
    if complete:
        _check_complete(m, root, path, error)
    return m


def _check_complete(m: dict, root: Path, path: Path, error: type[GelsimError]) -> None:
    """:func:`load_manifest`'s checks of a finished dataset (``complete=True``)."""
    if m.get("complete") is not True:
        raise error(f"dataset {root} is incomplete (complete: false); rerun gelsim generate to finish it")
    for key in ("fabrics", "sequences"):
        if not isinstance(m.get(key), list) or not m[key]:
            raise error(f"{path} has no {key}; regenerate the dataset")
    ids = {f["id"] for f in m["fabrics"]}
    for s in m["sequences"]:
        for key in READ_FIELDS:
            if key not in s:
                raise error(f"sequence {s.get('id', '?')} in {path} lacks {key!r}; regenerate the dataset")
        if s["fabric_id"] not in ids:
            raise error(f"sequence {s['id']} names unknown fabric {s['fabric_id']}; regenerate the dataset")
        if s["split"] not in SPLITS:
            raise error(f"sequence {s['id']} has split {s['split']!r}, expected one of {SPLITS}")


# ---------------------------------------------------------------- labels

@dataclass(frozen=True)
class LabelKey:
    """One array of a sequence's labels .npz: ``shape`` in terms of T (frames) and N (markers),
    ``kind`` the numpy dtype kind ("f" float, "b" bool), ``unit`` and meaning. ``optional``: added
    within FORMAT_VERSION 1 (2026-11-23), so datasets made before lack it."""
    name: str
    shape: tuple[str | int, ...]
    kind: str
    unit: str
    doc: str
    optional: bool = False


LABELS: tuple[LabelKey, ...] = (
    LabelKey("time_s", ("T",), "f", "s", "camera time, frame 0 at 0"),
    LabelKey("position_mm", ("T", 3), "f", "mm", "sensor centre in the fabric frame; z above the fabric's base plane"),
    LabelKey("yaw_deg", ("T",), "f", "degrees", "sensor rotation about the normal, +x towards +y"),
    LabelKey("tilt_deg", ("T", 2), "f", "degrees", "roll, pitch"),
    LabelKey("normal_force_n", ("T",), "f", "N", "normal force on the gel, >= 0"),
    LabelKey("tangential_force_n", ("T", 2), "f", "N", "in-plane force on the gel, sensor frame"),
    LabelKey("in_contact", ("T",), "b", "bool", "object and gel in contact"),
    LabelKey("slipping", ("T",), "b", "bool", "the gel surface slides over the object"),
    LabelKey("shear_mm", ("T", 2), "f", "mm", "gel shear: contact surface relative to the sensor base"),
    LabelKey("twist_deg", ("T",), "f", "degrees", "gel torsion: contact surface relative to the sensor base"),
    LabelKey("indentation_mm", ("T",), "f", "mm", "approach past first touch"),
    LabelKey("contact_area_mm2", ("T",), "f", "mm^2", "area in contact"),
    LabelKey("contact_centroid_px", ("T", 2), "f", "px",
             "centroid of the contact mask (x = column, y = row); NaN without contact", optional=True),
    LabelKey("contact_bbox_px", ("T", 4), "f", "px",
             "bounding box of the contact mask (x0, y0, x1, y1: pixel edges); NaN without contact", optional=True),
    LabelKey("markers_xy_px", ("T", "N", 2), "f", "px", "marker centres (x = column, y = row)"),
    LabelKey("markers_rest_px", ("N", 2), "f", "px", "marker centres on the flat gel"),
)
LABEL_KEYS = tuple(k.name for k in LABELS)


def label_problems(arrays: Mapping[str, np.ndarray], num_frames: int) -> list[str]:
    """What is wrong with a sequence's labels (``arrays``: key -> array, e.g. an open .npz) for
    ``num_frames`` frames: missing keys (optional ones aside), wrong shapes or dtype kinds, a marker
    count that differs between keys. Empty when sound; unknown extra keys are allowed."""
    out = []
    dims: dict[str, int] = {"T": num_frames}
    for key in LABELS:
        if key.name not in arrays:
            if not key.optional:
                out.append(f"labels lack {key.name!r}")
            continue
        a = np.asarray(arrays[key.name])
        if a.dtype.kind != key.kind:
            out.append(f"labels {key.name!r} have dtype {a.dtype}, expected kind {key.kind!r}")
        want = tuple(dims.setdefault(d, a.shape[i]) if isinstance(d, str) and i < a.ndim else d
                     for i, d in enumerate(key.shape))
        if a.shape != want:
            shown = ", ".join(f"{d}={dims[d]}" if isinstance(d, str) and d in dims else str(d) for d in key.shape)
            out.append(f"labels {key.name!r} have shape {a.shape}, expected ({shown})")
    return out
