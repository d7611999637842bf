"""Time tacto (PyPI 0.0.3) on the shared scenes; run with the tacto venv's python.

Set PYOPENGL_PLATFORM (``egl`` or ``osmesa``) before starting it. tacto's
``Renderer`` is driven in its two native ways:

* ``mesh``:  the object is a mesh in its pyrender scene, pushed into the gel
  along the camera axis (the sphere by tacto's own force-to-depth rule, 10 N of
  its 0-100 N range = 0.5 mm of its 5 mm); per frame only the pose changes;
* ``depth``: ``render_from_depth(imprint_m)``, which builds the gel surface mesh
  from the height map (one vertex per pixel) every frame.

Both include tacto's per-frame post-processing (difference to its simulated
background, 7x7 blur, add to the real background, Gaussian noise sigma 7).

Its sensor config is DIGIT's (``config_digit.yml``) with the gel resized to the
R1.5's 18.88 x 14.16 mm field, made flat (a GelSight gel, not DIGIT's curved
one), and the camera's vertical field of view narrowed so that the gel fills a
4:3 image at the same 22 mm distance: the same field as taxim and gelsim.
"""
from __future__ import annotations

import math
import os
import sys
import tempfile
from importlib.metadata import version

import numpy as np

# numpy 2 removed these aliases; tacto 0.0.3 (np.float), urdfpy and pyrender (np.infty) still use them.
# Patched here, at import, instead of editing the installed packages.
if not hasattr(np, "float"):
    np.float = float
if not hasattr(np, "infty"):
    np.infty = np.inf

# common and scenes sit beside this script (Python puts a script's folder first on sys.path): this runs in
# tacto's venv, which has no gelsim (see README.md there). After the numpy aliases above, which tacto needs.
from common import RESOLUTIONS, emit, image_stats, runner_args, time_frames, wanted, write_png  # noqa: E402
from scenes import FIELD_H_MM, FIELD_W_MM, SCENES, SPHERE_RADIUS_MM, digest, imprint_mm, scene  # noqa: E402

MM = 1e-3  # tacto works in metres
# flat-gel colour for tacto's real-background slot (uint8 RGB); only the timing of the blend matters
BACKGROUND_RGB = (118, 124, 128)


def make_config(tmpdir: str) -> str:
    """DIGIT's config with a flat 18.88 x 14.16 mm gel filling a 4:3 image; path of the written YAML."""
    import tacto
    from omegaconf import OmegaConf

    conf = OmegaConf.load(tacto.get_digit_config_path())
    g = conf.sensor.gel
    g.width = FIELD_W_MM * MM
    g.height = FIELD_H_MM * MM
    g.curvature = False
    cam = conf.sensor.camera[0]
    distance = g.origin[0] - cam.position[0]            # camera on the gel's axis, 22 mm away in DIGIT
    cam.yfov = math.degrees(2 * math.atan(0.5 * g.height / distance))
    path = os.path.join(tmpdir, "tacto_gelsight_field.yml")
    OmegaConf.save(conf, path)
    return path


def main() -> None:
    args = runner_args(__doc__.splitlines()[0])
    import trimesh
    import tacto

    platform = os.environ.get("PYOPENGL_PLATFORM", "")
    tmpdir = tempfile.mkdtemp(prefix="gelsim_peers_tacto_")
    config = make_config(tmpdir)
    results = []
    for w, h in RESOLUTIONS:
        bg = np.zeros((h, w, 3), np.uint8)
        bg[:] = BACKGROUND_RGB
        for name in SCENES:
            gap, press = scene(name, h, w)
            for path in ("mesh", "depth"):
                if not wanted(args, f"{w}x{h}", name, path):
                    continue
                # tacto's set_background flips channels (it expects BGR): give it BGR
                r = tacto.Renderer(w, h, bg[:, :, ::-1].copy(), config)
                conf = r.conf
                x0 = conf.sensor.gel.origin[0]
                flat = r.render(object_poses=None, noise=False)[0][0]
                if path == "depth":
                    imp = imprint_mm(gap, press) * np.float32(MM)

                    def frame(noise=True):
                        return r.render_from_depth(imp, noise=noise)[0]
                elif name == "sphere":
                    ball = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE_RADIUS_MM * MM)
                    ball.visual = trimesh.visual.ColorVisuals()
                    touching = [x0 + SPHERE_RADIUS_MM * MM, conf.sensor.gel.origin[1], conf.sensor.gel.origin[2]]
                    r.add_object(ball, "ball", position=touching)
                    f = conf.sensor.force
                    force = press * MM / f.max_deformation * f.range_force[1]
                    poses = {"ball": (touching, [0.0, 0.0, 0.0])}

                    def frame(noise=True):
                        return r.render(object_poses=poses, normal_forces={"ball": force}, noise=noise)[0][0]
                else:
                    # the cloth as a rigid mesh, one vertex per pixel, its highest yarns press mm into the gel
                    cloth = r._generate_trimesh_from_depth(x0 + (gap.astype(np.float64) - press) * MM)
                    cloth.visual = trimesh.visual.ColorVisuals()
                    r.add_object(cloth, "cloth")

                    def frame(noise=True):
                        return r.render(object_poses=None, noise=noise)[0][0]

                stats = time_frames(frame, args.warmup, args.frames)
                img = frame(noise=False)
                png = os.path.join(args.png_dir, f"peer_tacto_{platform}_{name}_{path}_{w}x{h}.png")
                write_png(png, img[:, :, :3])
                results.append({"peer": "tacto", "variant": f"{path} ({platform})", "scene": name,
                                "width": w, "height": h, "input_digest": digest(gap), "png": png,
                                **image_stats(img[:, :, :3], flat[:, :, :3]), **stats})
                print(f"tacto {path} {platform} {name} {w}x{h}: {stats['ms_median']:.1f} ms", file=sys.stderr)
                r.r.delete()
    import OpenGL
    import pyrender
    emit(results, {"tacto": version("tacto"), "pyrender": version("pyrender"), "PyOpenGL": OpenGL.__version__,
                   "trimesh": trimesh.__version__, "numpy": np.__version__, "networkx": version("networkx"),
                   "opencv": version("opencv-python-headless"), "pyopengl_platform": platform,
                   "gl_renderer": gl_renderer(pyrender)})


def gl_renderer(pyrender) -> str:
    """The GL_RENDERER string of a throw-away context (llvmpipe on Mesa without a GPU)."""
    try:
        from OpenGL import GL
        r = pyrender.OffscreenRenderer(16, 16)
        try:
            return GL.glGetString(GL.GL_RENDERER).decode()
        finally:
            r.delete()
    except Exception as e:  # informative only
        return f"unknown ({type(e).__name__})"


if __name__ == "__main__":
    main()
