"""A small synthetic dataset in ``gelsim generate``'s exact layout (gelsim.schema), for tests and benchmarks.

Each fabric is a class-dependent grating (orientation, period, colour tint) that appears
inside a growing contact disk from ``contact_onset`` on, over a smooth background with
Gaussian sensor noise; frames before the onset show only the background. It is a stand-in
for real `gelsim generate` output, not a simulation: its labels hold only ``in_contact`` and
``normal_force_n`` (there is no contact mechanics to label), so ``gelsim verify`` reports the
other label keys as missing; everything stam reads is there.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SYNTH_FPS_HZ = 30.0


def make_synthetic_dataset(out: str | Path, num_fabrics: int = 4, seqs_per_fabric: int = 10,
                           num_frames: int = 12, size: tuple[int, int] = (96, 72), seed: int = 0,
                           noise_grey: float = 0.8, fmt: str = "h264", complete: bool = True) -> Path:
    """Write a dataset to ``out``; ``size`` is (width, height) px. Returns ``out``.

    Splits are 7:2:1 by sequence within each fabric (for 10 sequences per fabric: 7, 2, 1).
    """
    from gelsim import schema
    from gelsim.atomic import atomic_write_json, atomic_write_npz
    from gelsim.video import video_path, write_video

    rng = np.random.default_rng(seed)
    out = Path(out)
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    background = (120 + 30 * (xx / w) + 20 * (yy / h))[..., None] * np.array([0.9, 1.0, 1.1], np.float32)
    fabrics, sequences = [], []
    for f in range(1, num_fabrics + 1):
        theta = np.pi * (f - 1) / num_fabrics
        period = 5.0 + 3.0 * ((f - 1) % 3)
        tint = np.array([1.0 + 0.15 * np.cos(theta), 1.0, 1.0 + 0.15 * np.sin(theta)], np.float32)
        fabrics.append({"id": f, "name": f"synthetic-{f:03d}", "family": "synthetic", "material": "synthetic"})
        grating = np.sin(2 * np.pi * (xx * np.cos(theta) + yy * np.sin(theta)) / period)
        n_train = round(0.7 * seqs_per_fabric)
        n_val = round(0.2 * seqs_per_fabric)
        for k in range(seqs_per_fabric):
            split = schema.SPLITS[0 if k < n_train else 1 if k < n_train + n_val else 2]
            sid = schema.sequence_id(f, k)
            onset = int(rng.integers(1, max(2, num_frames // 3)))
            cx, cy = w * rng.uniform(0.35, 0.65), h * rng.uniform(0.35, 0.65)
            phase = rng.uniform(0, 2 * np.pi)
            frames, in_contact, force = [], [], []
            for t in range(num_frames):
                img = background.copy()
                touching = t >= onset
                if touching:
                    radius = min(w, h) * min(0.45, 0.15 + 0.06 * (t - onset))
                    disk = np.clip(radius - np.hypot(xx - cx, yy - cy), 0, 3) / 3
                    tex = 35 * np.sin(np.arcsin(np.clip(grating, -1, 1)) + phase)
                    img = img * (1 - 0.3 * disk[..., None] * (1 - tint)) + (disk * tex)[..., None]
                img = img + rng.normal(0, noise_grey, img.shape)
                frames.append(np.clip(img, 0, 255).astype(np.uint8))
                in_contact.append(touching)
                force.append(0.5 * max(0, t - onset + 1) if touching else 0.0)
            vpath = write_video(video_path(out / schema.video_stem(f, sid), fmt), frames, fps=SYNTH_FPS_HZ, fmt=fmt)
            lpath = atomic_write_npz(out / schema.labels_path(f, sid), in_contact=np.array(in_contact),
                                     normal_force_n=np.array(force, np.float32))
            sequences.append(schema.sequence_entry({
                "id": sid, "fabric_id": f, "action": schema.ACTIONS[k % 3], "num_frames": num_frames,
                "contact_onset": onset, "precontact_frames": onset, "split": split,
                "video": vpath.relative_to(out).as_posix(), "labels": lpath.relative_to(out).as_posix(),
                "seed": int(seed * 100000 + f * 1000 + k),
                "sha256": {"video": schema.sha256_of(vpath), "labels": schema.sha256_of(lpath)},
                "peak_force_n": float(max(force))}))
    from gelsim.dataset import library_versions

    manifest = schema.make_manifest(
        complete=complete, generator_version="stam-synthetic", seed=seed,
        options={"synthetic": {"num_fabrics": num_fabrics, "seqs_per_fabric": seqs_per_fabric,
                               "num_frames": num_frames, "size": [w, h], "noise_grey": noise_grey, "format": fmt}},
        catalog_version="synthetic",
        profile={"name": "synthetic", "width_px": w, "height_px": h, "mm_per_px": 0.0197, "fps_hz": SYNTH_FPS_HZ},
        fabrics=fabrics, libraries=library_versions(), sequences=sequences)
    atomic_write_json(out / schema.MANIFEST, manifest)
    return out
