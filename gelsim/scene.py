"""What the sensor touches: one typed object, from a catalog fabric to a sphere or a mesh.

The pipeline's first stage. A :class:`TouchedObject` says everything the later stages need of the
thing under the sensor:

* ``heights(x0_mm, y0_mm, width_px, height_px, mm_per_px, seed=, rotation_deg=)``: its surface above
  the base plane over any region of its own frame, at any resolution (mm, ``float32 (H, W)``, >= 0;
  pixel (i, j) at ``(x0 + j p, y0 + i p)``), continuous across regions;
* ``friction``: Coulomb's coefficient against the gel;
* ``support()``: its compliance under a pressing gel (a fabric's cloth compression and yarn
  flattening, :class:`gelsim.gel.FabricSupport`), or None for a rigid object;
* ``texture_mm``: the scale of its texture, over which the imprint separates crowns from valleys
  (None: a smooth object);
* ``macro_valley_mm`` (optional; None if absent): the width of the narrowest valley that its crown
  envelope keeps, mm (a corduroy's gap between wales), which the imprint's contact-scale grid must
  resolve (:func:`macro_valley_mm`).

:func:`travel_patch` builds its heights over a motion's travel for the physics (:func:`physics_surface`,
a :class:`gelsim.contact.Surface`) and for the images (a :class:`HeightPatch` the sequence samples per
frame). The contact simulation deals only in surfaces; nothing after this module knows about fabrics.

Objects: :class:`FabricObject` (a catalog :class:`~gelsim.fabrics.Fabric`; a bare Fabric is accepted
wherever an object is, see :func:`as_object`), :class:`Sphere`, :class:`Cylinder`, :class:`Mesh`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np
from numba import njit

from .errors import GelsimError
from .optics.ops.readout import fma32

# Physics sees the object at this cell size; finer texture is the gel model's business (MuJoCo's
# heightfield contacts are capped at 50 per pair, so finer cells buy nothing). contact.simulate
# max-pools it further for speed (PHYSICS_CELL_MM there).
PHYSICS_MM_PER_PX = 0.2
# Files trimesh reads that an indenter may be given as (units mm).
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")
# Friction of the smooth test objects against silicone: assumed, the middle of the 0.4-1.0 range
# of materials on silicone rubber (REFERENCES).
DEFAULT_FRICTION = 0.6
# HeightPatch.sample takes a map as a pure translation about the frame's centre when the rest of it
# departs from one by at most this over the frame (px; a pixel then moves by at most half of it:
# 1/16 px, a tenth of the camera blur's sigma and twice the step to which OpenCV's warp rounds its
# coordinates). A hand's tremor turns the sensor by 1e-4 to 4e-3 degrees (0.003-0.12 px at 960x720):
# 87% of a sample dataset's pressed frames; the twists and slips turn further and are warped. The
# labels keep the pose as simulated.
NEAR_TRANSLATION_PX = 1.0 / 8.0


@runtime_checkable
class TouchedObject(Protocol):
    """What the sensor touches (see the module docstring)."""
    name: str
    friction: float
    texture_mm: float | None

    def heights(self, x0_mm: float, y0_mm: float, width_px: int, height_px: int, mm_per_px: float, *,
                seed: int = 0, rotation_deg: float = 0.0) -> np.ndarray: ...

    def support(self): ...


@dataclass(frozen=True)
class FabricObject:
    """A catalog fabric lying flat on a table."""
    fabric: object

    @property
    def name(self) -> str:
        return f"fabric {self.fabric.id} ({self.fabric.name})"

    @property
    def friction(self) -> float:
        return float(self.fabric.friction)

    @property
    def texture_mm(self) -> float:
        return self.fabric.texture_mm

    @property
    def macro_valley_mm(self) -> float | None:
        return self.fabric.macro_valley_mm

    def support(self):
        return self.fabric.support()

    def heights(self, x0_mm, y0_mm, width_px, height_px, mm_per_px, *, seed=0, rotation_deg=0.0):
        from .fabrics import heightfield

        return heightfield(self.fabric, x0_mm=x0_mm, y0_mm=y0_mm, width_px=width_px, height_px=height_px,
                           mm_per_px=mm_per_px, seed=seed, rotation_deg=rotation_deg)

    def heights_parts(self, x0_mm, y0_mm, width_px, height_px, mm_per_px, *, seed=0, rotation_deg=0.0):
        """:meth:`heights`, or a rotated patch before its resampling
        (:func:`gelsim.fabrics.render.heightfield_parts`: a device may finish it)."""
        from .fabrics.render import heightfield_parts

        return heightfield_parts(self.fabric, x0_mm=x0_mm, y0_mm=y0_mm, width_px=width_px, height_px=height_px,
                                 mm_per_px=mm_per_px, seed=seed, rotation_deg=rotation_deg)


def _grid(x0_mm, y0_mm, width_px, height_px, mm_per_px, center_mm, rotation_deg):
    """Coordinates (x row vector, y column vector, or full arrays when rotated) relative to
    ``center_mm``, in the object's own (unrotated) frame."""
    x = x0_mm + np.arange(width_px) * mm_per_px - center_mm[0]
    y = y0_mm + np.arange(height_px) * mm_per_px - center_mm[1]
    if not rotation_deg:
        return x[None, :], y[:, None]
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    X, Y = np.meshgrid(x, y)
    return c * X + s * Y, -s * X + c * Y


class _Rigid:
    """A smooth rigid object: no compliance of its own (``support()`` is None), no texture scale."""
    texture_mm = None
    macro_valley_mm = None

    def support(self):
        return None


def macro_valley_mm(obj) -> float | None:
    """``obj.macro_valley_mm`` (mm), or None for an object that does not give one (it is optional in
    :class:`TouchedObject`: an object made before it existed still works)."""
    v = getattr(obj, "macro_valley_mm", None)
    return None if v is None else float(v)


def press_properties(obj) -> dict:
    """What :func:`gelsim.gel.press` takes of the object (or a bare catalog Fabric) as keywords: its
    ``support`` (compliance), ``texture_mm`` and ``valley_mm`` (:func:`macro_valley_mm`)."""
    return {"support": obj.support(), "texture_mm": obj.texture_mm, "valley_mm": macro_valley_mm(obj)}


def positive_mm(name: str, value) -> float:
    """``value`` as a float if it is a finite length > 0 mm; else a GelsimError naming ``name``."""
    if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise GelsimError(f"{name} = {value!r} is not a positive number; give a value > 0 mm")
    return float(value)


#: The largest sphere or cylinder diameter, mm (10 m). Heights are float32: at a 5 m radius one step of
#: float32 is 0.3 um, a hundredth of a light press's depth; from about 1 km of diameter the cap is one
#: constant to float32, nothing touches and the press has no contact to solve. A ball this size is a
#: flat plate to any sensor's field.
MAX_DIAMETER_MM = 10_000.0


def diameter_mm_of(name: str, value) -> float:
    """``value`` as a float if it is a diameter > 0 and at most :data:`MAX_DIAMETER_MM`; else a GelsimError."""
    d = positive_mm(name, value)
    if d > MAX_DIAMETER_MM:
        raise GelsimError(f"{name} = {value!r} is larger than {MAX_DIAMETER_MM:g} mm, where the shape is flat to "
                          f"the sensor; give a diameter up to {MAX_DIAMETER_MM:g} mm")
    return d


@dataclass(frozen=True)
class Sphere(_Rigid):
    """A rigid ball of ``diameter_mm`` resting on the base plane at ``center_mm``."""
    diameter_mm: float
    center_mm: tuple[float, float] = (0.0, 0.0)
    friction: float = DEFAULT_FRICTION

    def __post_init__(self):
        diameter_mm_of("diameter_mm", self.diameter_mm)

    @property
    def name(self) -> str:
        return f"sphere {self.diameter_mm:g} mm"

    def heights(self, x0_mm, y0_mm, width_px, height_px, mm_per_px, *, seed=0, rotation_deg=0.0):
        r = self.diameter_mm / 2.0
        x, y = _grid(x0_mm, y0_mm, width_px, height_px, mm_per_px, self.center_mm, 0.0)
        return np.sqrt(np.maximum(r * r - (x * x + y * y), 0.0)).astype(np.float32)


@dataclass(frozen=True)
class Cylinder(_Rigid):
    """A rigid cylinder lying on its side, axis through ``center_mm`` at ``angle_deg`` from +x;
    ``length_mm`` None is longer than any field."""
    diameter_mm: float
    length_mm: float | None = None
    angle_deg: float = 0.0
    center_mm: tuple[float, float] = (0.0, 0.0)
    friction: float = DEFAULT_FRICTION

    def __post_init__(self):
        diameter_mm_of("diameter_mm", self.diameter_mm)
        if self.length_mm is not None:
            positive_mm("length_mm", self.length_mm)

    @property
    def name(self) -> str:
        return f"cylinder {self.diameter_mm:g} mm"

    def heights(self, x0_mm, y0_mm, width_px, height_px, mm_per_px, *, seed=0, rotation_deg=0.0):
        r = self.diameter_mm / 2.0
        x, y = _grid(x0_mm, y0_mm, width_px, height_px, mm_per_px, self.center_mm, self.angle_deg + rotation_deg)
        out = np.sqrt(np.maximum(r * r - y * y, 0.0))
        if self.length_mm is not None:
            out = np.where(np.abs(x) <= self.length_mm / 2.0, out, 0.0)
        return np.ascontiguousarray(np.broadcast_to(out, (height_px, width_px)), dtype=np.float32)


@dataclass(frozen=True)
class Mesh(_Rigid):
    """Any mesh trimesh reads (units mm), its lowest side facing the gel, its x-y bounding box
    centred on ``center_mm``: heights are how far its lower surface stands below its top."""
    path: str
    center_mm: tuple[float, float] = (0.0, 0.0)
    friction: float = DEFAULT_FRICTION

    @property
    def name(self) -> str:
        return f"mesh {Path(self.path).name}"

    def heights(self, x0_mm, y0_mm, width_px, height_px, mm_per_px, *, seed=0, rotation_deg=0.0):
        from .meshes import load_mesh, mesh_heights

        xs = x0_mm + np.arange(width_px) * mm_per_px - self.center_mm[0]
        ys = y0_mm + np.arange(height_px) * mm_per_px - self.center_mm[1]
        return mesh_heights(load_mesh(self.path), xs, ys, rotation_deg)


def indenter(name: str, *, diameter_mm: float | None = None, length_mm: float | None = None,
             angle_deg: float = 0.0) -> TouchedObject:
    """The indenter ``name`` centred under the sensor: ``"sphere"`` or ``"cylinder"`` (of ``diameter_mm``;
    the cylinder on its side, ``length_mm`` long, None = longer than any field, its axis ``angle_deg``
    from +x towards +y) or the path of a mesh file (MESH_SUFFIXES, units mm)."""
    name = str(name)
    if name == "sphere":
        return Sphere(diameter_mm_of("diameter_mm", diameter_mm))
    if name == "cylinder":
        if not isinstance(angle_deg, (int, float)) or not math.isfinite(angle_deg):
            raise GelsimError(f"angle_deg = {angle_deg} is not finite; give an angle in degrees")
        return Cylinder(diameter_mm_of("diameter_mm", diameter_mm),
                        None if length_mm is None else positive_mm("length_mm", length_mm), float(angle_deg))
    if Path(name).suffix.lower() in MESH_SUFFIXES:
        return Mesh(name)
    raise GelsimError(f"unknown indenter {name!r}; use sphere, cylinder or a mesh file ({', '.join(MESH_SUFFIXES)})")


def sensor_field(profile, scale: float = 1.0) -> tuple[float, float, int, int, float]:
    """``(x0_mm, y0_mm, width_px, height_px, mm_per_px)`` of the sensor's field of view at ``scale``
    times its image resolution (0 < scale <= 8), in the sensor frame: origin at the image centre,
    ``(x0, y0)`` the first pixel's centre."""
    if not (0 < scale <= 8 and math.isfinite(scale)):
        raise GelsimError(f"scale {scale} is out of range; give 0 < scale <= 8")
    h, w = profile.shape
    hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
    mm = profile.image.mm_per_px
    # At the image's own size the pitch is the profile's exactly (mm * w / w may differ in the last bit).
    dx = mm if ws == w else mm * w / ws
    return -(ws - 1) / 2.0 * dx, -(hs - 1) / 2.0 * dx, ws, hs, dx


def field_heights(obj: TouchedObject, profile, *, scale: float = 1.0, seed: int = 0) -> np.ndarray:
    """``obj``'s heights over the sensor's field of view, the sensor centred over the object's origin
    and unturned: float32 ``(H, W)`` mm at ``scale`` times the image resolution (:func:`sensor_field`),
    the protrusion map :func:`gelsim.gel.press` takes."""
    x0, y0, w, h, dx = sensor_field(profile, scale)
    return obj.heights(x0, y0, w, h, dx, seed=seed)


def as_object(obj) -> TouchedObject:
    """``obj`` as a TouchedObject: a catalog Fabric is wrapped, an object passes through."""
    from .fabrics import Fabric

    if isinstance(obj, Fabric):
        return FabricObject(obj)
    if isinstance(obj, TouchedObject):
        return obj
    raise GelsimError(f"{type(obj).__name__} is not something the sensor can touch; give a catalog fabric "
                      "or a gelsim.scene object (Sphere, Cylinder, Mesh, FabricObject)")


@dataclass
class HeightPatch:
    """An object's heights over a region of its frame: ``heights_mm`` float32 (h, w), pixel (i, j)
    at ``origin_mm + (j, i) * mm_per_px``."""
    heights_mm: np.ndarray
    origin_mm: tuple[float, float]
    mm_per_px: float

    def sample(self, shape: tuple[int, int], sensor_mm_per_px: float, x_mm: float, y_mm: float,
               yaw_deg: float, tilt_deg: tuple[float, float] = (0.0, 0.0),
               box: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Protrusion map ``float32 shape`` (H, W) seen by a sensor at (x, y, yaw), mm >= 0; with ``box`` =
        (r0, r1, c0, c1), only its rows r0:r1 and columns c0:c1 (the same values up to float rounding:
        on the box's last row and column, and a turned frame's map offset).

        Sensor pixel (u, v) sits at sensor-frame point ((u - (W-1)/2) s, (v - (H-1)/2) s);
        rotating by yaw and translating by (x, y) gives the world point, which maps to
        patch pixel ((xw - x0)/p, (yw - y0)/p). warpAffine with WARP_INVERSE_MAP takes
        exactly that dst->src affine map.
        """
        H, W = shape
        r0, r1, c0, c1 = (0, H, 0, W) if box is None else box
        s, p = sensor_mm_per_px, self.mm_per_px
        c, sn = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        cu, cv = (W - 1) / 2.0, (H - 1) / 2.0
        x0, y0 = self.origin_mm
        a11, a12 = c * s / p, -sn * s / p
        a21, a22 = sn * s / p, c * s / p
        b1 = (x_mm - x0) / p - a11 * cu - a12 * cv
        b2 = (y_mm - y0) / p - a21 * cu - a22 * cv
        h, w = r1 - r0, c1 - c0
        plane = _tilt_plane(tilt_deg, c0, c1, r0, r1, cu, cv, s)
        # The map's departure from a translation, at worst over the frame, px.
        off = (abs(a11 - 1.0) + abs(a21)) * W + (abs(a12) + abs(a22 - 1.0)) * H
        if off <= NEAR_TRANSLATION_PX:
            # The translation at the frame's centre (the neglected turn then moves no pixel by more
            # than half the bound): a 2 x 2 filter over a crop, one pass (warpAffine's general map
            # took 1.3 ms per 960x720 frame, the filter 0.25).
            tx = a11 * cu + a12 * cv + b1 - cu
            ty = a21 * cu + a22 * cv + b2 - cv
            out = _shifted(self.heights_mm, tx, ty, h, w, r0, c0, plane)
            if out is not None:
                return out
        # (the box's pixel (0, 0) is the frame's (c0, r0): the map's offset moves by A (c0, r0))
        M = np.array([[a11, a12, b1 + a11 * c0 + a12 * r0], [a21, a22, b2 + a21 * c0 + a22 * r0]], dtype=np.float64)
        out = cv2.warpAffine(self.heights_mm, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        if plane is not None:
            _add_plane(out, *plane)
        return out


def _tilt_plane(tilt_deg, c0: int, c1: int, r0: int, r1: int, cu: float, cv: float, s: float):
    """The plane a tilted sensor adds to the heights of frame columns ``c0:c1`` and rows ``r0:r1`` (centre
    ``(cu, cv)`` px, ``s`` mm per px) as :func:`_add_plane`'s ``(ax, xs, ay, ys)``; None untilted. A tilted
    sensor meets one side of the object first: it appears raised on the side the gel leans towards (small
    angles: a plane of slope tan(tilt))."""
    if not (tilt_deg[0] or tilt_deg[1]):
        return None
    xs = (np.arange(c0, c1, dtype=np.float32) - cu) * s
    ys = (np.arange(r0, r1, dtype=np.float32) - cv) * s
    return (np.float32(math.tan(math.radians(tilt_deg[1]))), xs, np.float32(math.tan(math.radians(tilt_deg[0]))), ys)


def _shifted(src: np.ndarray, tx: float, ty: float, h: int, w: int, r0: int = 0, c0: int = 0,
             plane=None) -> np.ndarray | None:
    """``src`` (float32 (rows, cols)) read bilinearly at pixel ``(j + c0 + tx, i + r0 + ty)`` for output pixel
    ``(i, j)``: float32 ``(h, w)``, C-contiguous; None when that reaches past ``src``'s last pixels
    (the caller's warp replicates the edge there). (The whole offsets r0, c0 apart from the shift: a
    box of a frame reads the frame's pixels with the frame's weights.) ``plane``: :func:`_tilt_plane`'s, added
    in the same pass (as :func:`_add_plane` adds it), or None."""
    x0, y0 = math.floor(tx), math.floor(ty)
    fx, fy = np.float32(tx - x0), np.float32(ty - y0)
    x0, y0 = x0 + c0, y0 + r0
    if x0 < 0 or y0 < 0 or x0 + w + 1 > src.shape[1] or y0 + h + 1 > src.shape[0]:
        return None
    one = np.float32(1.0)
    k = np.array([[(one - fx) * (one - fy), fx * (one - fy)], [(one - fx) * fy, fx * fy]], np.float32)
    out = np.empty((h, w), np.float32)
    if plane is None:
        zero = np.zeros(1, np.float32)
        plane = (np.float32(0.0), zero, np.float32(0.0), zero)
        _shift_rows(src, y0, x0, k, out, False, *plane)
    else:
        _shift_rows(src, y0, x0, k, out, True, *plane)
    return out


# The lanes of OpenCV's vector loop in filter2D on float32 (its AVX2 code): the columns it leaves to its
# scalar tail round differently (see _shift_rows).
_FILTER_LANES = 8


@njit(cache=True, nogil=True, error_model="numpy")
def _shift_rows(src, y0: int, x0: int, k, out, tilted: bool, ax, xs, ay, ys) -> None:
    """``out`` (float32 (h, w)) = the 2 x 2 filter ``k`` (float32) over ``src[y0:y0 + h + 1, x0:x0 + w + 1]``,
    anchored at its top-left tap, plus (``tilted``) :func:`_add_plane`'s plane: one pass where OpenCV's
    filter2D, two numpy fixes of the crop's last row and column and the plane's pass took four (0.16 against
    0.24 ms per tilted 960x720 frame), with their arithmetic. Off the crop's last row and column a pixel is what
    filter2D computes with this wheel's vector code (AVX2, 8 lanes with FMA; measured bit for bit): the
    taps in row-major order, a chain of fused multiply-adds in its first ``8 * (w // 8)`` columns, the
    scalar tail's plain products and sums beyond; on them, numpy's sum of the four products left to right.
    The plane then adds as :func:`_add_plane` does."""
    h, w = out.shape
    k00, k01, k10, k11 = k[0, 0], k[0, 1], k[1, 0], k[1, 1]
    body = min(w - 1, _FILTER_LANES * (w // _FILTER_LANES))
    for i in range(h):
        a = src[y0 + i, x0:x0 + w + 1]
        b = src[y0 + i + 1, x0:x0 + w + 1]
        o = out[i]
        start = 0
        if i < h - 1:
            for j in range(body):
                o[j] = fma32(k11, b[j + 1], fma32(k10, b[j], fma32(k01, a[j + 1], k00 * a[j])))
            start = body
        for j in range(start, w):
            o[j] = ((k00 * a[j] + k01 * a[j + 1]) + k10 * b[j]) + k11 * b[j + 1]
        if tilted:
            by = ay * ys[i]
            for j in range(w):
                o[j] = (o[j] + ax * xs[j]) + by


@njit(cache=True, nogil=True, error_model="numpy")
def _add_plane(out, ax, xs, ay, ys) -> None:
    """``out += ax * xs[None, :] + ay * ys[:, None]`` in place, in one pass (numpy took two, 5x the
    time at 960x720), with numpy's float32 rounding and order: (out + ax x) + ay y."""
    for i in range(out.shape[0]):
        by = ay * ys[i]
        row = out[i]
        for j in range(out.shape[1]):
            row[j] = (row[j] + ax * xs[j]) + by


@dataclass
class PatchParts:
    """:func:`travel_patch`'s patch before its last steps (:func:`travel_patch_parts`): ``heights`` a finished
    float32 ``(h, w)`` array (mm) or a rotated fabric's :class:`gelsim.fabrics.render.RotatedHeights`; origin and
    cell as :class:`HeightPatch`. :meth:`finish` makes the patch on the host (the same bytes as
    :func:`travel_patch`); :func:`gelsim.scene_torch.PatchBank.from_patches` on a device."""
    heights: object
    origin_mm: tuple[float, float]
    mm_per_px: float

    def finish(self) -> HeightPatch:
        h = self.heights
        return HeightPatch(h if isinstance(h, np.ndarray) else h.finish(), self.origin_mm, self.mm_per_px)


def travel_patch(obj: TouchedObject, motion, profile, mm_per_px: float, *, seed: int,
                 snap: bool = False, poses: tuple[np.ndarray, np.ndarray] | None = None) -> HeightPatch:
    """``obj``'s heights over the region the sensor's field sweeps in ``motion``, plus two cells, at
    ``mm_per_px``, turned by the motion's ``fabric_rotation_deg``.

    ``poses``: the frames' sensor positions (T, >= 2) mm and yaws (T,) degrees when known (after the
    contact simulation): the region is then what the field's rectangle covers at those poses (a
    press's patch is about half the area of the circle a twist needs, and the heights are its
    costliest per-sequence step). Without them: the motion's travel plus the field's circumscribed
    circle (so any twist and tilt stay covered). ``snap``: put the origin on the object's own grid
    of ``mm_per_px`` cells (the physics grid: a max-pool then sees the same cells wherever the
    sensor goes)."""
    return travel_patch_parts(obj, motion, profile, mm_per_px, seed=seed, snap=snap, poses=poses).finish()


def travel_patch_parts(obj: TouchedObject, motion, profile, mm_per_px: float, *, seed: int, snap: bool = False,
                       poses: tuple[np.ndarray, np.ndarray] | None = None) -> PatchParts:
    """:func:`travel_patch`'s patch, a rotated fabric's left before its resampling (``obj.heights_parts``, where the
    object has one): what the host must make of it, the rest for a device (``--stages all``)."""
    x0, y0, w, h = _travel_region(motion, profile, mm_per_px, snap, poses)
    parts = getattr(obj, "heights_parts", obj.heights)
    hf = parts(x0, y0, w, h, mm_per_px, seed=seed, rotation_deg=motion.fabric_rotation_deg)
    return PatchParts(hf if hasattr(hf, "finish") else np.asarray(hf, dtype=np.float32), (x0, y0), mm_per_px)


def _travel_region(motion, profile, mm_per_px: float, snap: bool, poses) -> tuple[float, float, int, int]:
    """:func:`travel_patch`'s region: its first pixel's centre (x0, y0) mm and its size (w, h) px."""
    fw, fh = profile.field_mm
    margin = 2 * mm_per_px
    if poses is not None:
        xy, yaw = np.asarray(poses[0], np.float64)[:, :2], np.radians(np.asarray(poses[1], np.float64))
        # Centres of the image's corner pixels (see HeightPatch.sample) at every pose.
        s = profile.image.mm_per_px
        h_px, w_px = profile.shape
        hx, hy = (w_px - 1) / 2.0 * s, (h_px - 1) / 2.0 * s
        cu = np.array([-hx, hx, -hx, hx])[None, :]
        cv = np.array([-hy, -hy, hy, hy])[None, :]
        c, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        xs = xy[:, :1] + c * cu - sn * cv
        ys = xy[:, 1:2] + sn * cu + c * cv
        xmin, xmax = float(xs.min()) - margin, float(xs.max()) + margin
        ymin, ymax = float(ys.min()) - margin, float(ys.max()) + margin
    else:
        xmin, ymin, xmax, ymax = motion.travel_bounds_mm()
        r = 0.5 * math.hypot(fw, fh) + margin
        xmin, ymin, xmax, ymax = xmin - r, ymin - r, xmax + r, ymax + r
    if snap:
        x0 = math.floor(xmin / mm_per_px) * mm_per_px
        y0 = math.floor(ymin / mm_per_px) * mm_per_px
        w = int(math.ceil((xmax - x0) / mm_per_px)) + 1
        h = int(math.ceil((ymax - y0) / mm_per_px)) + 1
    else:
        x0, y0 = xmin, ymin
        w = int(math.ceil((xmax - xmin) / mm_per_px)) + 1
        h = int(math.ceil((ymax - ymin) / mm_per_px)) + 1
    return x0, y0, w, h


def physics_surface(obj: TouchedObject, motion, profile, *, seed: int):
    """The :class:`gelsim.contact.Surface` of ``obj`` over ``motion``'s travel (PHYSICS_MM_PER_PX cells,
    heights shifted to be >= 0)."""
    from .contact import Surface

    p = travel_patch(obj, motion, profile, PHYSICS_MM_PER_PX, seed=seed, snap=True)
    hf = p.heights_mm
    return Surface(np.maximum(hf - min(float(hf.min()), 0.0), 0.0), float(PHYSICS_MM_PER_PX), p.origin_mm,
                   float(obj.friction))
