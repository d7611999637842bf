"""Time taxim (PyPI 1.4.1, JAX CPU backend) on the shared scenes; run with the taxim venv's python.

Taxim takes the object's height map in mm relative to the undeformed gel's
highest point (<= 0 where the object is in contact) and returns float RGB in
0-1. A height map of another size than its calibration (640x480) is rendered
over the same field: the background, gel map and blur widths are resized, so
960x720 is the R1.5's field at 0.0197 mm/px. Timed: ``Taxim.render`` on a
numpy array, which includes the gel deformation (Gaussian pyramid), the shading
lookup, optionally the shadows, and the copy back to numpy.
"""
from __future__ import annotations

import os
import sys
from importlib.metadata import version

import numpy as np

# common and scenes sit beside this script (Python puts a script's folder first on sys.path): this runs in
# taxim's venv, which has no gelsim (see README.md there).
from common import RESOLUTIONS, emit, image_stats, runner_args, time_frames, wanted, write_png
from scenes import SCENES, digest, scene


def gel_map(sim, h: int, w: int) -> np.ndarray:
    """taxim's undeformed gel surface at ``h`` x ``w``, mm (<= 0, 0 at its highest point); private API."""
    return np.asarray(sim._TaximJax__get_gel_map((h, w)), dtype=np.float32)


def main() -> None:
    args = runner_args(__doc__.splitlines()[0])
    import jax
    from taxim import Taxim

    sim = Taxim(backend="jax")
    results = []
    for w, h in RESOLUTIONS:
        flat = sim.render(np.full((h, w), 1.0, np.float32), with_shadow=False)  # no contact: the background
        for name in SCENES:
            gap, press = scene(name, h, w)
            hm = gap - np.float32(press)
            if name == "fabric":
                # taxim's gel is domed (gel map 0 at the centre, down to -1.4 mm at the corners): a flat
                # cloth would touch the apex only, so the cloth is draped over the dome, as when the gel is
                # pressed into cloth, giving the same imprint everywhere as in the other simulators
                hm = hm + gel_map(sim, h, w)
            hm = hm.astype(np.float32)
            tx = sim
            if name == "fabric":
                # taxim clamps pixels deeper than contact_scale x the deepest point (its press depth); draped
                # over the dome the deepest point is 1.5 mm, so rescale contact_scale to keep its threshold at
                # contact_scale x the cloth's own 0.09 mm press, as for a ball on the flat apex
                cs = sim.sim_params.contact_scale * press / float(-hm.min())
                tx = Taxim(backend="jax", params={"simulator": {"contact_scale": cs}})
            for shadow in (False, True):
                variant = "shadow" if shadow else "no-shadow"
                if not wanted(args, f"{w}x{h}", name, variant):
                    continue
                stats = time_frames(lambda: tx.render(hm, with_shadow=shadow), args.warmup, args.frames)
                img = np.clip(np.rint(tx.render(hm, with_shadow=shadow) * 255.0), 0, 255).astype(np.uint8)
                png = os.path.join(args.png_dir, f"peer_taxim_{name}_{variant}_{w}x{h}.png")
                write_png(png, img)
                flat8 = np.clip(np.rint(flat * 255.0), 0, 255).astype(np.uint8)
                results.append({"peer": "taxim", "variant": variant, "scene": name, "width": w, "height": h,
                                "input_digest": digest(gap), "png": png, **image_stats(img, flat8), **stats})
                print(f"taxim {variant} {name} {w}x{h}: {stats['ms_median']:.1f} ms", file=sys.stderr)
    emit(results, {"taxim": version("taxim"), "jax": version("jax"), "jaxlib": version("jaxlib"),
                   "numpy": np.__version__, "jax_devices": [str(d) for d in jax.devices()]})


if __name__ == "__main__":
    main()
