"""The first look: a few fabric families pressed into the gel at 960x720, each frame beside what the contact
changed in it (the frame minus the flat gel's, contrast stretched), so that a newcomer sees the weave, the
contact and the markers move where a frame alone shows a few DN of texture on a grey gel.

``gelsim generate`` writes it with its previews (:func:`write_first_look`): ``previews/first_look.png``
(every family at half scale, one row each) and ``previews/first_look/fNNN-<family>.png`` (each at
full 960x720, the frame and its difference side by side). The README shows the sheet.
"""
from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

from .annotate import caption, stretched_difference, stretched_differences, tile
from .atomic import write_png
from .sensor import SensorProfile, load_profile

#: One fabric per family, chosen to show unlike surfaces: a twill's diagonal, a knit's loops, a
#: corduroy's wales, a leather's grain (catalog ids; any id of gelsim/assets/fabrics works).
FABRICS = (21, 58, 65, 88)
#: The press, N: the middle of the dataset's hand-held 1-4 N (gelsim/assets/motions.toml).
FORCE_N = 2.5
#: The camera's resolution, px (the ViTac camera's 960x720).
RESOLUTION = (960, 720)
FIRST_LOOK_DIR = "first_look"
#: With a nuisance level: how many of a sequence's first frames the first look shows (the webcam's
#: exposure and white balance settle over its first frames, gelsim/assets/nuisance.toml).
NUISANCE_FRAMES = 4


def _label(img: np.ndarray, lines: list[str], scale: float) -> np.ndarray:
    """``img`` with ``lines`` in white on a black outline from its top-left corner."""
    return caption(img, lines, scale)


def first_look_frames(fabrics=FABRICS, profile: str | Path | SensorProfile = "vitac", *, force_n: float = FORCE_N,
                      fidelity: str = "balanced", seed: int = 0) -> list[dict]:
    """Per fabric: ``{"fabric", "name", "family", "frame", "difference", "gain", "force_n"}``; ``frame`` is
    the uint8 RGB camera frame at :data:`RESOLUTION` of the fabric pressed with ``force_n`` N, and
    ``difference`` that frame minus the flat gel's (same sensor unit, markers and noise draw: what the
    contact changed), stretched by ``gain`` (:func:`stretched_difference`)."""
    from .cli.render_cmd import make_object
    from .frame import render_frame

    prof = profile if isinstance(profile, SensorProfile) else load_profile(profile)
    prof = prof.with_resolution(*RESOLUTION)
    flat, _ = render_frame(make_object(None, "sphere", None), prof, fidelity, force_n=0.0, seed=seed)
    out = []
    for fid in fabrics:
        obj = make_object(int(fid), None, None)
        rgb, info = render_frame(obj, prof, fidelity, force_n=force_n, seed=seed)
        diff, gain = stretched_difference(rgb, flat)
        out.append({"fabric": int(fid), "name": obj.fabric.name, "family": obj.fabric.family, "frame": rgb,
                    "difference": diff, "gain": gain, "force_n": info["imprint"]["normal_force_n"]})
    return out


#: The per-fabric values a cached first look keeps beside its frames.
_LOOK_KEYS = ("fabric", "name", "family", "gain", "force_n")


def looks_cache_path(fabrics: tuple[int, ...], profile: str) -> Path:
    """Where :func:`_cached_looks` keeps the first look of ``fabrics`` on ``profile`` between runs: under the
    user cache (``$GELSIM_CACHE`` or ``~/.cache/gelsim``), named by the gelsim code and assets that render it
    (:func:`gelsim.provenance.source_digest`), so that other code renders it anew."""
    from .provenance import source_digest
    from .realism import cache_dir

    return cache_dir() / FIRST_LOOK_DIR / f"{profile}-{'-'.join(map(str, fabrics))}-{source_digest()[:16]}.npz"


@functools.lru_cache(maxsize=4)
def _cached_looks(fabrics: tuple[int, ...], profile: str) -> list[dict]:
    """:func:`first_look_frames` of a shipped profile: rendered once per machine and code version (4-8 s at
    960x720; every `gelsim generate` paid it), then read from :func:`looks_cache_path` (its arrays read only).
    A cache that cannot be read or written is passed by: the looks are rendered."""
    from .atomic import atomic_open

    path = looks_cache_path(fabrics, profile)
    try:
        with np.load(path) as z:
            return [{**{k: z[f"{i}_{k}"].item() for k in _LOOK_KEYS}, "frame": z[f"{i}_frame"],
                     "difference": z[f"{i}_difference"]} for i in range(len(fabrics))]
    except (OSError, KeyError, ValueError):
        pass
    looks = first_look_frames(fabrics, profile)
    arrays = {f"{i}_{k}": np.asarray(look[k]) for i, look in enumerate(looks) for k in _LOOK_KEYS + ("frame", "difference")}
    try:
        for old in path.parent.glob(f"{profile}-{'-'.join(map(str, fabrics))}-*.npz"):
            old.unlink()                          # other code's looks: never read again
        with atomic_open(path) as f:
            np.savez(f, **arrays)
    except (OSError, ValueError):   # a read-only home, a full disk (a GelsimError): made anyway, next time too
        pass
    return looks


def panels(look: dict, scale: float = 1.0) -> np.ndarray:
    """One fabric's frame and its labelled difference side by side, scaled by ``scale``."""
    def size(img):
        return cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)),
                          interpolation=cv2.INTER_AREA) if scale != 1.0 else img

    text = 0.8 * max(scale, 0.5)
    left = _label(size(look["frame"]), [f"{look['fabric']} {look['name']} ({look['family']}), {look['force_n']:.1f} N",
                                        "camera frame, as in the dataset"], text)
    right = _label(size(look["difference"]), ["frame minus the flat gel (same noise),",
                                              f"contrast stretched x{look['gain']:.0f}"], text)
    return np.concatenate([left, right], axis=1)


def nuisance_shown(root: Path, sequence: dict) -> list[str]:
    """The values of ``sequence``'s per-frame nuisance record (:func:`gelsim.annotate.nuisance_record`) that
    change over its first :data:`NUISANCE_FRAMES` frames: what a level did there (empty without a record)."""
    from .annotate import nuisance_record, varying_nuisance

    record = nuisance_record(root, sequence) or {}
    n = min(NUISANCE_FRAMES, int(sequence["num_frames"]))
    first = {k: np.asarray(v)[:n] for k, v in record.items()
             if np.asarray(v).ndim in (1, 2) and len(v) == sequence["num_frames"]}
    return sorted(varying_nuisance(first, n))


def nuisance_rows(root: Path, manifest: dict, flat) -> np.ndarray | None:
    """With a nuisance level (the manifest's options): uint8 RGB rows :data:`RESOLUTION`'s half width
    wide showing the first :data:`NUISANCE_FRAMES` frames of one sequence, as the dataset holds them and
    minus the flat gel (``flat(sequence)``: uint8 (H, W, 3)), captioned; None without a level. The sequence
    is the first whose nuisance record changes most over those frames (:func:`nuisance_shown`: a level may
    touch few recordings), then the one with the most frames before contact."""
    level = (manifest.get("options") or {}).get("nuisance") or "none"
    seqs = [s for s in manifest.get("sequences", []) if "video" in s]
    if level == "none" or not seqs:
        return None
    from .video import read_video

    shown = {s["id"]: nuisance_shown(root, s) for s in seqs}
    seq = max(seqs, key=lambda s: (len(shown[s["id"]]), s.get("precontact_frames") or 0))   # the first of the most
    frames = read_video(Path(root) / seq["video"])[:NUISANCE_FRAMES]
    diffs, gains = stretched_differences(frames, flat(seq))
    width = RESOLUTION[0] // NUISANCE_FRAMES   # the sheet's: two half-scale panels side by side
    onset = seq.get("contact_onset")
    severity = (manifest.get("options") or {}).get("nuisance_severity")
    what = f"--nuisance {level}" + ("" if severity is None else f" --nuisance-severity {severity:g}")
    top, bottom = [], []
    for t, (f, d, gain) in enumerate(zip(frames, diffs, gains)):
        state = "before contact" if onset is None or onset < 0 or t < onset else "contact"
        head = [f"{seq['id']} with {what}"] if t == 0 else []
        if t == 1 and shown[seq["id"]]:
            head = ["record: " + ", ".join(shown[seq["id"]])]
        top.append(caption(tile(f, width), head + [f"frame {t}, {state}"]))
        bottom.append(caption(tile(d, width), [f"minus the flat gel x{gain:.0f}"]))
    return np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)


def write_first_look(previews_dir: Path, manifest: dict | None = None, *, fabrics=FABRICS, root: Path | None = None,
                     flat=None) -> list[Path]:
    """Write the first look into ``previews_dir`` (see the module docstring) for the dataset's sensor
    (``manifest``'s profile when it is a shipped one, else vitac); with a nuisance level and the dataset's
    ``root`` and ``flat`` (its flat gel per sequence, :class:`gelsim.previews.FlatFrames`), the sheet ends
    with that level's first frames (:func:`nuisance_rows`). Returns the paths written."""
    from .sensor import list_profiles

    name = ((manifest or {}).get("profile") or {}).get("name")
    prof = name if name in list_profiles() else "vitac"
    looks = _cached_looks(tuple(int(f) for f in fabrics), prof)
    previews_dir = Path(previews_dir)
    folder = previews_dir / FIRST_LOOK_DIR
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for look in looks:
        p = folder / f"f{look['fabric']:03d}-{look['family']}.png"
        write_png(p, panels(look))
        written.append(p)
    rows = [panels(look, 0.5) for look in looks]
    extra = None if root is None or flat is None or manifest is None else nuisance_rows(root, manifest, flat)
    if extra is not None:
        rows.append(extra)
    p = previews_dir / "first_look.png"
    write_png(p, np.concatenate(rows, axis=0))
    return [p, *written]
