"""Reference shading backend: the deformed gel as a mesh, lit by spot lights with shadows (pyrender).

The membrane becomes a ``trimesh`` height-field mesh (the depth map area-averaged
to at most :data:`MAX_GRID` vertices along a side), seen through an orthographic
camera that matches ``mm_per_px`` exactly. Each LED is a pyrender spot light at
its rim position (:func:`gelsim.optics.field.led_position_mm`) aimed at the gel
centre; pyrender casts shadows from spot lights only (point lights cast none).

The renderer outputs gamma-encoded 8-bit colour; we undo the gamma and express
the deformed gel's radiance relative to the flat gel's, ``R / R_flat - 1`` per
channel and pixel. That relative change times the fast model's flat shading and
``gain_dn`` gives the DN change, so both backends share one photometric scale
and the LEDs' spatial fall-off (inverse-square here, exponential in the
profile) cancels out of the comparison.

World frame here: ``X`` = image x, ``Y`` = -image y (OpenGL's y is up), ``Z``
towards the camera; mm.
"""
from __future__ import annotations

import math

import numpy as np

from ..compat import gl_color, gl_unavailable_message, import_pyrender
from ..errors import GelsimError
from .field import LightMaps, flat_shading_rgb, led_position_mm, vignetting_map
from .ops.box import imprint_roi
from .shader import Shader

#: Most vertices along one side of the gel mesh: 320 x 240 at 960x720 rendered in
#: 178 ms (OSMesa); a finer mesh costs more than it changes at the 3 px step.
MAX_GRID = 320
#: pyrender writes sRGB-like gamma 1/2.2 (mesh.frag); we linearise with the same exponent.
GAMMA = 2.2
#: Flat-gel linear radiance per channel that the light intensities are set to, at the
#: centre: low enough that a slope facing an LED (about 2.4x brighter at a 25 degree
#: elevation) stays below saturation, high enough for 8-bit resolution.
FLAT_LINEAR = 0.22
#: Camera height above the gel, mm: any value works for an orthographic camera;
#: the near/far planes bracket the gel with room for a 10 mm deep imprint.
CAMERA_Z_MM = 50.0

#: pyrender's shadow-map size (pyrender.constants.SHADOW_TEX_SZ).
SHADOW_MAP_PX = 2048
#: Depth bias of the shadow test in shadow-map texels: the 3x3 PCF filter compares
#: across +-1 texel, so a surface must clear about 2 texels of its own slope not to
#: shadow itself; below that, striped "shadow acne" appeared on a smooth dent.
SHADOW_BIAS_TEXELS = 2.0

_GL_OK: bool | None = None


def gl_available() -> bool:
    """Whether a headless GL context can be made (tried once per process)."""
    global _GL_OK
    if _GL_OK is None:
        try:
            pr = import_pyrender()
            r = pr.OffscreenRenderer(16, 16)
            r.delete()
            _GL_OK = True
        except Exception:  # any failure means "not available": the caller skips or falls back
            _GL_OK = False
    return _GL_OK


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 pose whose -z axis points from ``eye`` to ``target`` (pyrender lights shine along -z)."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, true_up, -fwd, eye
    return pose


def _roughness(shininess: float) -> float:
    """pyrender (GGX) roughness matching a Phong exponent: alpha = sqrt(2 / (n + 2)) (Walter et al. 2007), r = sqrt(alpha)."""
    return float(math.sqrt(math.sqrt(2.0 / (shininess + 2.0))))


class PyrenderShader(Shader):
    """Shading change of the membrane in image DN, rendered with pyrender.

    ``profile``: sensor profile at the rendered resolution; ``maps``: its light maps.
    """

    name = "pyrender"

    def __init__(self, profile, maps: list[LightMaps]):
        self.pr = pr = import_pyrender()
        import trimesh
        self.trimesh = trimesh
        self.profile = profile
        h, w = profile.shape
        mm = profile.image.mm_per_px
        self.step = max(1, math.ceil(max(h, w) / MAX_GRID))
        self.gh, self.gw = math.ceil(h / self.step), math.ceil(w / self.step)
        # vertex positions of area-averaged cells, outermost ones pushed to the image edge
        gx = (np.arange(self.gw) + 0.5) * (w / self.gw) - 0.5
        gy = (np.arange(self.gh) + 0.5) * (h / self.gh) - 0.5
        gx[0], gx[-1], gy[0], gy[-1] = -0.5, w - 0.5, -0.5, h - 0.5
        X = (gx - (w - 1) / 2.0) * mm
        Y = -(gy - (h - 1) / 2.0) * mm
        self.XY = np.stack(np.meshgrid(X, Y), axis=-1).reshape(-1, 2)
        self.dX, self.dY = np.gradient(X), np.gradient(Y)
        idx = np.arange(self.gh * self.gw).reshape(self.gh, self.gw)
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        # counter-clockwise seen from +Z (the camera): rows go down in Y, columns right in X
        self.faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                                     np.stack([b, c, d], -1).reshape(-1, 3)])
        sh = profile.shading
        self.material = pr.MetallicRoughnessMaterial(baseColorFactor=gl_color((1.0, 1.0, 1.0), alpha=1.0),
                                                     metallicFactor=0.0, roughnessFactor=_roughness(sh.shininess))
        self.scene = pr.Scene(bg_color=gl_color((0.0, 0.0, 0.0), alpha=1.0),
                              ambient_light=gl_color((0.0, 0.0, 0.0)))
        cam = pr.OrthographicCamera(xmag=w * mm / 2.0, ymag=h * mm / 2.0, znear=1.0, zfar=2 * CAMERA_Z_MM)
        cam_pose = np.eye(4)
        cam_pose[2, 3] = CAMERA_Z_MM
        self.scene.add(cam, pose=cam_pose)
        fw, fh = profile.field_mm
        corners = np.array([[x, y, 0.0] for x in (-fw / 2, 0, fw / 2) for y in (-fh / 2, 0, fh / 2)])
        for light, m in zip(profile.lights, maps):
            p = led_position_mm(light, profile)
            eye = np.array([p[0], -p[1], p[2]])
            axis = -eye / np.linalg.norm(eye)
            dirs = corners - eye
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            # nearest gel point to the LED lies on the field's rim: cover it too
            near = np.array([np.clip(p[0], -fw / 2, fw / 2), -np.clip(p[1], -fh / 2, fh / 2), 0.0]) - eye
            dirs = np.vstack([dirs, near / np.linalg.norm(near)])
            spread = float(np.arccos(np.clip(dirs @ axis, -1, 1)).max())
            # full intensity over the whole field; pyrender caps the outer cone at 90 degrees
            outer = min(math.pi / 2, spread + math.radians(8))
            inner = min(spread + math.radians(2), outer - math.radians(1))
            d_centre = float(np.linalg.norm(eye))
            sin_e = max(math.sin(math.radians(light.elevation_deg)), 1e-3)
            # pyrender: radiance = intensity / d^2; Lambertian BRDF = base / pi
            intensity = FLAT_LINEAR * math.pi * d_centre ** 2 / sin_e * light.intensity / len(maps)
            dist = np.linalg.norm(corners - eye, axis=1)
            fov = min(2 * spread + math.radians(4), math.radians(170))
            # pyrender's depth bias is 0.001 (1 - n.l) / w in the shadow map's [0, 1] depth, which is
            # about 0.001 (1 - n.l) d / znear in mm at distance d: pick znear so that it is
            # SHADOW_BIAS_TEXELS shadow-map texels (at the gel centre), stretched by the grazing angle.
            texel = 2 * d_centre * math.tan(fov / 2) / SHADOW_MAP_PX
            bias_mm = SHADOW_BIAS_TEXELS * texel / max(math.tan(math.radians(light.elevation_deg)), 0.1)
            znear = 0.001 * d_centre / bias_mm
            spot = _fitted_spot_light(pr, fov, znear, 2.0 * float(dist.max()), color=gl_color(light.color_rgb),
                                      intensity=intensity, innerConeAngle=max(0.0, inner), outerConeAngle=outer)
            self.scene.add(spot, pose=_look_at(eye, np.zeros(3)))
        self.flags = pr.RenderFlags.SHADOWS_SPOT
        try:
            self.renderer = pr.OffscreenRenderer(w, h)
        except Exception as e:
            raise GelsimError(gl_unavailable_message(f"{type(e).__name__}: {e}".splitlines()[0])) from None
        self.mesh_node = None
        self.vignetting = vignetting_map(profile)
        self.flat_rgb = flat_shading_rgb(maps)
        self.gain = profile.shading.gain_dn
        self.flat_linear = self._render_linear(np.zeros((h, w), np.float32))

    def _mesh(self, depth_mm: np.ndarray):
        import cv2
        z = cv2.resize(depth_mm, (self.gw, self.gh), interpolation=cv2.INTER_AREA).astype(np.float64)
        dz_dx = np.gradient(z, axis=1) / self.dX[None, :]
        dz_dy = np.gradient(z, axis=0) / self.dY[:, None]
        normals = np.stack([-dz_dx, -dz_dy, np.ones_like(z)], -1).reshape(-1, 3)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        verts = np.column_stack([self.XY, z.reshape(-1)])
        tm = self.trimesh.Trimesh(vertices=verts, faces=self.faces, vertex_normals=normals, process=False)
        return self.pr.Mesh.from_trimesh(tm, material=self.material, smooth=True)

    def _render_linear(self, depth_mm: np.ndarray) -> np.ndarray:
        """Linear radiance of the gel with imprint ``depth_mm``: float32 ``(H, W, 3)``."""
        if self.mesh_node is not None:
            self.scene.remove_node(self.mesh_node)
        self.mesh_node = self.scene.add(self._mesh(depth_mm))
        color, _ = self.renderer.render(self.scene, flags=self.flags)
        lin = (color.astype(np.float32) / 255.0) ** GAMMA
        return lin

    def delta(self, depth_mm: np.ndarray, margin_px: int = 0):
        """``(roi, delta)``: whole-frame slices and float32 ``(H, W, 3)`` DN change; None if flat.
        ``margin_px`` is accepted for the backend interface; the whole frame is always shaded."""
        if imprint_roi(depth_mm, 0) is None:
            return None
        # whole frame: shadows fall outside the imprint (0.8 mm relief at 25 degrees: 1.7 mm away)
        roi = (slice(None), slice(None))
        lin = self._render_linear(depth_mm)
        flat = self.flat_linear
        # dark flat pixels (shadowed rim) carry no usable ratio: a 1/255 floor keeps it finite
        ratio = lin / np.maximum(flat, 1.0 / 255.0) - 1.0
        out = (self.gain * self.flat_rgb[roi] * ratio * self.vignetting[roi][..., None]).astype(np.float32)
        return roi, out

    def close(self) -> None:
        """Delete the GL context (once)."""
        if getattr(self, "renderer", None) is not None:
            self.renderer.delete()
            self.renderer = None


def _fitted_spot_light(pr, fov: float, znear: float, zfar: float, **light):
    """A pyrender spot light (``light``: its keywords) whose shadow-map camera just covers the gel.

    pyrender's default spans twice the outer cone plus 11 degrees between 0.01x and 10x the scene size: for a
    grazing LED that spreads the 2048^2 shadow map and the depth range so thin that the gel shadows itself in
    stripes ("shadow acne"). A tight frustum (``fov`` rad, ``znear`` to ``zfar`` mm) gives about twice the texel
    density and a 20x finer depth step. pyrender asks its light for that camera through a method, which this
    subclass overrides (rather than replacing it on pyrender's object)."""

    class FittedSpotLight(pr.SpotLight):
        def _get_shadow_camera(self, scene_scale):
            return pr.PerspectiveCamera(yfov=fov, znear=znear, zfar=zfar, aspectRatio=1.0)

    return FittedSpotLight(**light)
