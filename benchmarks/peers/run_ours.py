"""Time gelsim's fast renderer on the shared scenes; run with the project's venv (.venv/bin/python).

Variants, each on the ``vitac`` profile at the scene's resolution and field:

* ``render``: ``Renderer(profile, "fast").render(imprint, markers)``: shading, markers,
  camera blur and noise, uint8 out; the imprint is the rigid object's penetration
  (no gel elasticity), as tacto's ``render_from_depth`` gets it;
* ``render bare``: the same without markers and noise (the peers draw no markers);
* ``press+render``: ``gel.press`` at the ``fast`` fidelity (Gaussian-pyramid imprint
  after Taxim, at half resolution) and then ``render``, like taxim, whose
  ``render`` also computes the gel's deformation from the object's height map;
* ``render (phong)``: ``render`` with the profile's ``[shading] model`` set to
  ``phong`` (shading from the profile's lights) where the profile uses another
  model (vitac uses the calibrated table, ``lut``).
"""
from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
# common and scenes sit beside this script (Python puts a script's folder first on sys.path); gelsim is
# the installed package (the project's venv).
from common import RESOLUTIONS, emit, image_stats, runner_args, time_frames, wanted
from scenes import FIELD_W_MM, SCENES, digest, imprint_mm, scene

from gelsim.atomic import write_png

HERE = Path(__file__).resolve().parent


def profile_at(w: int, h: int):
    """The vitac profile at ``w`` x ``h`` with exactly the scenes' field (0.15% from vitac's own)."""
    from gelsim.sensor import load_profile

    p = load_profile("vitac").with_resolution(w, h)
    return dataclasses.replace(p, image=dataclasses.replace(p.image, mm_per_px=FIELD_W_MM / w))


def main() -> None:
    args = runner_args(__doc__.splitlines()[0])
    from gelsim.gel import press
    from gelsim.markers import rest_markers
    from gelsim.optics import Renderer
    from gelsim.sensor import load_profile

    results = []
    for w, h in RESOLUTIONS:
        prof = profile_at(w, h)
        ren = Renderer(prof, "fast")
        markers = rest_markers(prof)
        flat = ren.render(None, None, noise=False)
        phong = None
        if prof.shading.model != "phong":
            phong = Renderer(dataclasses.replace(prof, shading=dataclasses.replace(prof.shading, model="phong")),
                             "fast")
        for name in SCENES:
            gap, depth = scene(name, h, w)
            imp = imprint_mm(gap, depth)
            protrusion = (gap.max() - gap).astype(np.float32)
            cases = {
                "render": lambda i=None: ren.render(imp, markers, seed=1),
                "render bare": lambda i=None: ren.render(imp, None, noise=False),
                "press+render": lambda i=None: ren.render(
                    press(protrusion, prof, "fast", depth_mm=depth).depth_mm, markers, seed=1),
            }
            if phong is not None:
                cases["render (phong)"] = lambda i=None: phong.render(imp, markers, seed=1)
            for variant, fn in cases.items():
                if not wanted(args, f"{w}x{h}", name, variant):
                    continue
                stats = time_frames(fn, args.warmup, args.frames)
                img = fn()
                tag = re.sub(r"[^a-z0-9]+", "-", variant).strip("-")
                png = os.path.join(args.png_dir, f"peer_ours_{name}_{tag}_{w}x{h}.png")
                write_png(png, img)
                results.append({"peer": "gelsim", "variant": variant, "scene": name, "width": w, "height": h,
                                "input_digest": digest(gap), "png": png, **image_stats(img, flat), **stats})
                print(f"gelsim {variant} {name} {w}x{h}: {stats['ms_median']:.2f} ms", file=sys.stderr)
    import cv2
    try:
        commit = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    emit(results, {"gelsim": version("gelsim"), "gelsim_commit": commit, "numpy": np.__version__,
                   "opencv": cv2.__version__, "cv2_threads": cv2.getNumThreads(),
                   "vitac_shading_model": load_profile("vitac").shading.model})


if __name__ == "__main__":
    main()
