"""sha256 of rendered frames over a matrix of optics cases: the check that a refactor of the optics
keeps every frame's bytes.

    PYTHONPATH=. .venv/bin/python benchmarks/optics_hashes.py [--torch] > new.txt
    PYTHONPATH=/path/to/other/checkout .venv/bin/python benchmarks/optics_hashes.py > old.txt
    diff old.txt new.txt

Uses the public API only (:class:`gelsim.optics.Renderer`, profiles), so the same script runs against an
older checkout (``PYTHONPATH``). Cases: the shipped profiles (``vitac`` with its calibrated table, its
LED shadows and its depth and halo terms at 320x240 and 960x720; ``vitac`` with Phong shading and a
highlight; ``digit`` (Phong); ``gelsight-mini`` (the exact table lookup, shot noise); ``gelsight-r15``),
supersampling 1-3, with and without markers and noise; each renderer draws a sequence of frames (a
flat gel, markers at rest over several frames, a sphere, a steep sphere with shadows, a weave, a
fabric press, the markers moved) with integer seeds and a sequence's numpy Generator, so that the
renderer's caches (work arrays, markers at rest) are crossed too. One line per case: its name and the
sha256 of its frames' bytes (uint8 frames, the noiseless float32 frames, the background).
``--torch``: the torch backend's cases too (one frame at a time and batched; they agree with
``fast`` within a tolerance, not bit for bit).
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench_optics import fabric_depth, marker_corners, sphere_depth  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402


def _replace(profile, **sections):
    changes = {name: dataclasses.replace(getattr(profile, name), **fields) for name, fields in sections.items()}
    return dataclasses.replace(profile, **changes)


def _sheared(corners: np.ndarray, offset_px=(0.0, 0.0)) -> np.ndarray:
    """``corners`` moved by ``offset_px`` and sheared a little, so that the markers are not axis-aligned squares."""
    shear = np.array([[0.0, 0.0], [0.0, 0.3], [0.2, 0.3], [0.2, 0.0]], np.float32)
    return (corners + shear[None] + np.asarray(offset_px, np.float32)).astype(np.float32)


def _frames(profile):
    """The sequence of (name, depth, markers) each renderer draws."""
    grid = marker_corners(profile)
    rest, moved = _sheared(grid), _sheared(grid, (0.37, -0.61))
    sphere = sphere_depth(profile, 2.0, 0.5)
    h, w = profile.shape
    steep = np.roll(sphere_depth(profile, 1.0, 0.6), (h // 5, -w // 6), axis=(0, 1))     # shadows, off centre
    edge = np.roll(sphere_depth(profile, 2.0, 0.4), (h // 2 - 4, w // 2 - 6), axis=(0, 1))  # at a corner
    yy, xx = np.mgrid[0:h, 0:w] * profile.image.mm_per_px
    weave = (0.12 + 0.1 * np.sin(2 * np.pi * xx / 0.6) * np.cos(2 * np.pi * yy / 0.9)).astype(np.float32)
    fabric = fabric_depth(profile, 21, 3.0)
    return [("flat", None, None), ("flat+markers", None, rest), ("flat+markers again", None, rest),
            ("sphere", sphere, rest), ("steep sphere", steep, moved), ("weave", weave, moved),
            ("fabric", fabric, rest), ("flat+moved", None, moved), ("sphere no markers", sphere, None),
            ("edge", edge, moved)]


def _case(name, profile, backend="fast", supersample=1, seed=4, noise=True):
    from gelsim.optics import Renderer

    r = Renderer(profile, backend, supersample=supersample, seed=seed)
    h = hashlib.sha256(r.background().tobytes())
    h.update(r.background_float().tobytes())
    rng = np.random.default_rng(7)
    frames = _frames(profile)
    for i, (_, depth, markers) in enumerate(frames):
        h.update(r.render(depth, markers, seed=100 + i, noise=noise).tobytes())
        h.update(r.render(depth, markers, seed=rng, noise=noise).tobytes())
        if i % 3 == 0:
            h.update(r.render_float(depth, markers).tobytes())
    r.close()
    return name, h.hexdigest()


def _torch_case(name, profile, supersample=1, seed=4):
    from gelsim.optics import Renderer
    from gelsim.optics.torch_backend import BatchRenderer

    br = BatchRenderer(Renderer(profile, "torch", supersample=supersample, seed=seed))
    frames = _frames(profile)
    depths, marks = [f[1] for f in frames], [f[2] for f in frames]
    h = hashlib.sha256(br.render(depths, marks, list(range(len(frames)))).tobytes())
    h.update(br.render_float(depths, marks).tobytes())
    return name, h.hexdigest()


def cases(with_torch: bool):
    vitac = load_profile("vitac")
    v320 = vitac.with_resolution(320)
    phong = _replace(v320, shading={"model": "phong", "specular": 0.3})
    mini = load_profile("gelsight-mini").with_resolution(320)
    yield _case("vitac 320 lut", v320)
    yield _case("vitac 320 lut noiseless", v320, noise=False)
    yield _case("vitac 320 lut ss2", v320, supersample=2)
    yield _case("vitac 320 lut ss3", v320, supersample=3)
    yield _case("vitac 320 lut shot noise", _replace(v320, noise={"shot_gain": 0.4}))
    yield _case("vitac 320 lut no markers", _replace(v320, markers={"enabled": False}))
    yield _case("vitac 320 lut no blur", _replace(v320, camera={"blur_sigma_px": 0.0}))
    yield _case("vitac 960 lut", vitac)
    yield _case("vitac 320 phong", phong)
    yield _case("vitac 320 phong ss2", phong, supersample=2)
    yield _case("vitac 320 phong no noise", _replace(phong, noise={"read_sigma_dn": 0.0}))
    yield _case("digit", load_profile("digit"))
    yield _case("gelsight-mini 320 exact lut", mini)
    yield _case("gelsight-r15 320", load_profile("gelsight-r15").with_resolution(320))
    if with_torch:
        yield _torch_case("torch vitac 320 lut", v320)
        yield _torch_case("torch vitac 320 lut ss2", v320, supersample=2)
        yield _torch_case("torch vitac 320 phong", phong)
        yield _torch_case("torch vitac 320 shot noise", _replace(v320, noise={"shot_gain": 0.4}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--torch", action="store_true", help="also the torch backend's cases")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    for name, digest in cases(args.torch):
        print(f"{digest}  {name}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
