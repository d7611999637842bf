"""The yardstick cache: the reference's (and a sweep's finest value's) runs kept on disk, keyed by
everything they depend on (:class:`RunCache`), and :func:`measured_run`, a run with its texture measured
that reads and fills it."""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_npz
from ..contact import ContactFrames
from ..fidelity import Fidelity
from ..motion import Motion
from ..provenance import source_digest
from ..sensor import SensorProfile
from .runs import LevelRun, load_avg, run_level
from .scenes import BenchConfig, Scene
from .texture import SceneTexture, measure_texture


def _array_digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k} {a.dtype} {a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class RunCache:
    """Yardstick results on disk (``root/<key>.npz``), so that the seconds-per-frame reference is paid
    once per scene and source version; ``root`` None or '': nothing is kept. A key covers the
    caller's description of the run and :func:`source_digest`: any change to a gelsim module (but
    the bench's) or an asset makes a new key."""

    def __init__(self, root: str | Path | None):
        self.root = Path(root) if root else None

    def key(self, parts: dict) -> str:
        doc = json.dumps({**parts, "source": source_digest()}, sort_keys=True, default=str)
        return hashlib.sha256(doc.encode()).hexdigest()[:24]

    def load(self, key: str) -> dict | None:
        """The arrays stored under ``key`` (``meta``: a JSON document), or None."""
        path = None if self.root is None else self.root / f"{key}.npz"
        if path is None or not path.exists():
            return None
        with np.load(path) as z:
            d = {k: z[k] for k in z.files}
        d["meta"] = json.loads(str(d["meta"])) if "meta" in d else {}
        return d

    def save(self, key: str, arrays: dict, meta: dict) -> None:
        if self.root is None:
            return
        meta = {**meta, "date": datetime.datetime.now().isoformat(timespec="seconds"), "load_avg": load_avg()}
        atomic_write_npz(self.root / f"{key}.npz", **arrays, meta=np.array(json.dumps(meta)))

    def run_key(self, scene: Scene, config: BenchConfig, profile: SensorProfile, fid: Fidelity,
                contact: ContactFrames | None, outputs=("frames", "imprint", "markers")) -> str:
        return self.key({"scene": dataclasses.asdict(scene), "frames": config.frames,
                         "precontact": config.precontact,
                         "profile": hashlib.sha256(repr(profile).encode()).hexdigest(),
                         "fidelity": {**dataclasses.asdict(fid), "name": ""}, "seed": config.seed,
                         "video_format": config.video_format, "outputs": sorted(outputs),
                         "contact": None if contact is None else _array_digest(contact.to_dict())})

    def get_run(self, key: str) -> tuple[LevelRun, SceneTexture | None] | None:
        d = self.load(key)
        if d is None:
            return None
        meta = d.pop("meta")
        pick = lambda prefix: {k[len(prefix):]: v for k, v in d.items() if k.startswith(prefix)}  # noqa: E731
        contact = ContactFrames(**pick("contact__"), **meta["contact_scalars"])
        imprints = None
        if "imp_frames" in d:
            imprints = {int(i): (d["imp_depth"][k], d["imp_mask"][k]) for k, i in enumerate(d["imp_frames"])}
        run = LevelRun(d.get("frames"), pick("label__"), contact, meta["seconds"], meta["cpu_s"], meta["wall_s"],
                       imprints=imprints, cached=True)
        tex = None if "tex_frames" not in d else SceneTexture(d["tex_frames"], d["tex_gel"], d["tex_img"],
                                                             d.get("tex_region"), d.get("tex_patch"),
                                                             d.get("tex_img_fast"))
        return run, tex

    def put_run(self, key: str, run: LevelRun, tex: SceneTexture | None) -> None:
        arrays = {f"contact__{k}": v for k, v in run.contact.to_dict().items()}
        arrays.update({f"label__{k}": np.asarray(v) for k, v in run.labels.items()})
        if run.frames is not None:
            arrays["frames"] = run.frames
        if run.imprints:
            # The imprints themselves (a metric added later is measured from them, not re-solved).
            order = sorted(run.imprints)
            arrays.update(imp_frames=np.array(order), imp_depth=np.stack([run.imprints[i][0] for i in order]),
                          imp_mask=np.stack([run.imprints[i][1] for i in order]))
        if tex is not None:
            arrays.update(tex_frames=tex.frames, tex_gel=tex.gel_rms, tex_img=tex.img_rms)
            for name, value in (("tex_img_fast", tex.img_fast_rms), ("tex_region", tex.region), ("tex_patch", tex.patch)):
                if value is not None:
                    arrays[name] = value
        self.save(key, arrays, {"seconds": run.seconds, "cpu_s": run.cpu_s, "wall_s": run.wall_s,
                                "contact_scalars": {"first_contact_frame": int(run.contact.first_contact_frame),
                                                    "contact_time_s": float(run.contact.contact_time_s)}})


def measured_run(scene: Scene, motion: Motion, profile: SensorProfile, fid: Fidelity, *, catalog, renderer,
                 contact: ContactFrames | None, config: BenchConfig, yardstick: SceneTexture | None = None,
                 cache: RunCache | None = None, encode: str | None = None, shader=None,
                 outputs=("frames", "imprint", "markers")) -> tuple[LevelRun, SceneTexture | None]:
    """``run_level`` with the texture measured (``yardstick`` None: this run is the yardstick, read
    from and written to ``cache``; a cached run whose texture lacks a measure is measured again from
    its stored imprints). ``shader``: see :func:`measure_texture`. Outputs without frames: no
    texture (None)."""
    textured = "frames" in outputs
    fabric = None if scene.object == "sphere" else catalog[int(scene.object)]
    key = None
    if yardstick is None and cache is not None and cache.root is not None:
        key = cache.run_key(scene, config, profile, fid, contact, outputs)
        hit = cache.get_run(key)
        if hit is not None:
            run, tex = hit
            if textured and (tex is None or tex.img_fast_rms is None) and run.imprints is not None:
                tex = measure_texture(run, fabric, profile, renderer, shader=shader)
                cache.put_run(key, run, tex)
            if not textured or (tex is not None and tex.img_fast_rms is not None):
                run.imprints = None
                return run, tex
    run = run_level(scene, motion, profile, fid, catalog=catalog, renderer=renderer, contact=contact,
                    encode=encode, sensor_seed=config.seed, outputs=outputs, keep_imprints=textured)
    tex = measure_texture(run, fabric, profile, renderer, yardstick, shader) if textured else None
    if key is not None:
        cache.put_run(key, run, tex)
    run.imprints = None
    return run, tex
