"""One tactile sequence end to end: fabric -> contact -> gel -> optics.

:func:`render_sequence` strings the stages together for one (fabric, motion)
pair and yields frames one at a time (constant memory), then returns the
per-frame labels.

Shortcuts (``shortcuts=True``, the default) skip work a frame does not need; each
gives the full computation's result within the tolerance stated here, checked by
``tests/gelsim/test_shortcuts.py``, and ``gelsim bench`` reports what they save:

* frames out of contact reuse the flat gel: no protrusion sample, no imprint, no
  marker solve, the cached background (exact);
* the imprint, the marker fields and the shading are computed over the touched
  region only (``press(window="touched")``; pyramid model: indentation and contact area
  within 1% of the full frame's on fabric presses (0.12% measured), up to 3% on a sphere at
  work grids of 96x72 and 160x120 (equal at 320x240 and up), frames within 1 DN (3 DN on that
  sphere);
  elastic model: it cuts its 1/r tail 3 gel thicknesses from the contact, < 2% of the
  peak depth);
* shear and twist terms whose largest marker displacement is below
  :data:`NEGLIGIBLE_PX` are dropped (press sequences: the hand's tremor twists the gel
  by about 0.001 degree); markers then move by < NEGLIGIBLE_PX;
* outputs nobody asked for (``outputs``) are not computed: without ``"frames"`` no
  optics; without ``"frames"`` and ``"markers"`` no marker solve; with none of the
  three, no imprint either (exact: the labels that are computed are unchanged).

``shortcuts=False`` runs every stage on every frame over the full frame (for tests
and for measuring the savings).
"""
from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Collection, Iterator

import cv2
import numpy as np

from .contact import ContactFrames, Surface, simulate
from .errors import GelsimError
from .fabrics import Fabric, heightfield
from .fidelity import Fidelity
from .gel import FabricSupport, press
from .markers import displace, marker_grid, rest_markers
from .motion import Motion
from .optics import Renderer
from .sensor import SensorProfile

# Physics sees the fabric at this coarse cell size; finer texture is the gel model's
# business (REFERENCES: hfield contacts are capped at 50 per pair, so finer cells buy nothing).
PHYSICS_MM_PER_PX = 0.2
# Shear and twist terms that move no marker by more than this are skipped, px. A marker edge
# moving by 0.005 px changes its anti-aliased coverage by 0.5% of a pixel: at most about
# 0.6 DN (darkness 0.85 of a ~140 DN gel), below half a quantisation step.
NEGLIGIBLE_PX = 0.005
# What render_sequence can produce besides the contact labels (always computed).
OUTPUTS = frozenset({"frames", "imprint", "markers"})


# Stage clock: the thread's CPU time. A generation worker is one thread on one core, so this is its
# per-core cost whatever else the machine runs (wall time would count other processes' turns).
stage_clock = time.thread_time


@dataclass
class StageTimer:
    """Accumulates CPU time per pipeline stage (:data:`stage_clock`), in seconds."""
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    def add(self, stage: str, t0: float) -> float:
        t1 = stage_clock()
        self.seconds[stage] += t1 - t0
        return t1


@dataclass
class FabricPatch:
    """A fabric heightfield patch in the world (fabric) frame covering a sequence's travel."""
    heights_mm: np.ndarray   # float32 (h, w)
    origin_mm: tuple[float, float]
    mm_per_px: float

    @classmethod
    def for_motion(cls, fabric: Fabric, motion: Motion, profile: SensorProfile, mm_per_px: float,
                   seed: int) -> "FabricPatch":
        xmin, ymin, xmax, ymax = motion.travel_bounds_mm()
        fw, fh = profile.field_mm
        # The sensor rotates (twist) and tilts: cover its field's circumscribed circle.
        r = 0.5 * math.hypot(fw, fh) + 2 * mm_per_px
        x0, y0 = xmin - r, ymin - r
        w = int(math.ceil((xmax - xmin + 2 * r) / mm_per_px)) + 1
        h = int(math.ceil((ymax - ymin + 2 * r) / mm_per_px)) + 1
        hf = heightfield(fabric, x0_mm=x0, y0_mm=y0, width_px=w, height_px=h, mm_per_px=mm_per_px,
                         seed=seed, rotation_deg=motion.fabric_rotation_deg)
        return cls(hf.astype(np.float32, copy=False), (x0, y0), mm_per_px)

    def sample(self, shape: tuple[int, int], sensor_mm_per_px: float, x_mm: float, y_mm: float,
               yaw_deg: float, tilt_deg: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """Protrusion map ``float32 shape`` (H, W) seen by a sensor at (x, y, yaw), mm >= 0.

        Sensor pixel (u, v) sits at sensor-frame point ((u - (W-1)/2) s, (v - (H-1)/2) s);
        rotating by yaw and translating by (x, y) gives the world point, which maps to
        patch pixel ((xw - x0)/p, (yw - y0)/p). warpAffine with WARP_INVERSE_MAP takes
        exactly that dst->src affine map.
        """
        H, W = shape
        s, p = sensor_mm_per_px, self.mm_per_px
        c, sn = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        cu, cv = (W - 1) / 2.0, (H - 1) / 2.0
        x0, y0 = self.origin_mm
        a11, a12 = c * s / p, -sn * s / p
        a21, a22 = sn * s / p, c * s / p
        b1 = (x_mm - x0) / p - a11 * cu - a12 * cv
        b2 = (y_mm - y0) / p - a21 * cu - a22 * cv
        M = np.array([[a11, a12, b1], [a21, a22, b2]], dtype=np.float64)
        out = cv2.warpAffine(self.heights_mm, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderMode=cv2.BORDER_REPLICATE)
        if tilt_deg[0] or tilt_deg[1]:
            # A tilted sensor meets one side of the fabric first: the fabric appears raised
            # on the side the gel leans towards (small angles: a plane of slope tan(tilt)).
            xs = (np.arange(W, dtype=np.float32) - cu) * s
            ys = (np.arange(H, dtype=np.float32) - cv) * s
            out += np.float32(math.tan(math.radians(tilt_deg[1]))) * xs[None, :]
            out += np.float32(math.tan(math.radians(tilt_deg[0]))) * ys[:, None]
        return out


@dataclass
class SequenceOutput:
    labels: dict[str, np.ndarray]
    timings_s: dict[str, float]


def _negligible_px(shear_mm, twist_deg: float, profile: SensorProfile) -> tuple[bool, bool]:
    """Whether the shear and the twist each move every marker by less than NEGLIGIBLE_PX.

    The twist's lever arm is bounded by the image's diagonal (the centroid lies inside)."""
    mmpp = profile.image.mm_per_px
    shear_px = math.hypot(float(shear_mm[0]), float(shear_mm[1])) / mmpp
    h, w = profile.shape
    twist_px = abs(math.radians(float(twist_deg))) * math.hypot(w, h)
    return shear_px < NEGLIGIBLE_PX, twist_px < NEGLIGIBLE_PX


def contact_location(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a bool (H, W) contact mask lies, in px (x = column, y = row, pixel centres at integers).

    Returns the centroid float (2,) (x, y) and the bounding box float (4,) (x0, y0, x1, y1) of its
    pixels' edges, so a single pixel at column 5 spans x 4.5-5.5; both NaN when the mask is empty.
    """
    m = np.ascontiguousarray(mask).view(np.uint8)
    # Column and row counts by cv2.reduce: 0.16 ms in all at 960x720, against 1.4 ms for cv2.moments.
    cols = cv2.reduce(m, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.float64)
    n = cols.sum()
    if n == 0:
        return np.full(2, np.nan), np.full(4, np.nan)
    rows = cv2.reduce(m, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel().astype(np.float64)
    x, y, w, h = cv2.boundingRect(m)
    return (np.array([cols @ np.arange(cols.size) / n, rows @ np.arange(rows.size) / n]),
            np.array([x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5]))


def render_sequence(fabric: Fabric | None, motion: Motion, profile: SensorProfile, fidelity: Fidelity, *,
                    seed: int, renderer: Renderer | None = None, sensor_seed: int = 0,
                    out: SequenceOutput | None = None, shortcuts: bool = True,
                    outputs: Collection[str] = OUTPUTS, contact: ContactFrames | None = None,
                    surface: Surface | None = None, patch: FabricPatch | None = None,
                    support: FabricSupport | None = None,
                    texture_mm: float | None = None) -> Iterator[np.ndarray | None]:
    """Yield the ``uint8 (H, W, 3)`` frames of one sequence; fills ``out`` with labels and timings.

    ``seed`` drives everything random in this sequence (fabric irregularity phase, camera
    noise); ``sensor_seed`` fixes what belongs to the physical sensor and stays the same
    across a dataset (background illumination field, printed marker jitter).

    ``shortcuts``: skip work frames do not need (see the module docstring); False computes
    everything on every frame. ``outputs``: any of ``"frames"``, ``"imprint"`` (labels
    ``indentation_mm``, ``contact_area_mm2``, ``contact_centroid_px``, ``contact_bbox_px``: see
    :func:`contact_location`) and ``"markers"`` (``markers_xy_px``,
    ``markers_rest_px``); without ``"frames"`` the generator yields None per frame. The
    contact labels are always computed. ``contact``: a finished contact simulation of this
    motion to reuse (no physics run; e.g. to compare fidelity levels on the same contact).
    ``surface`` and ``patch``: the physics heightfield and the image-resolution patch of an
    object other than a catalog fabric (then ``fabric`` may be None; the object is rigid and
    smooth unless ``support`` and ``texture_mm`` are given, see :func:`gelsim.gel.press`).
    """
    outputs = frozenset(outputs)
    if not outputs <= OUTPUTS:
        raise GelsimError(f"unknown outputs {sorted(outputs - OUTPUTS)}; choose from {sorted(OUTPUTS)}")
    if fabric is None and (patch is None or (surface is None and contact is None)):
        raise GelsimError("render_sequence without a fabric needs patch= and surface= (or contact=); "
                          "pass a catalog fabric or both heightfields")
    if contact is not None and len(contact.normal_force_n) != motion.num_frames:
        raise GelsimError(f"contact has {len(contact.normal_force_n)} frames, the motion {motion.num_frames}; "
                          "simulate this motion")
    want_frames = "frames" in outputs
    want_markers = want_frames or "markers" in outputs
    want_imprint = want_markers or "imprint" in outputs
    timer = StageTimer()
    t = stage_clock()
    if want_frames:
        renderer = renderer or Renderer(profile, fidelity.render_backend, supersample=fidelity.supersample,
                                        seed=sensor_seed)
    if contact is None:
        if surface is None:
            surface = Surface.from_fabric(fabric, motion, profile, mm_per_px=PHYSICS_MM_PER_PX, seed=seed)
        t = timer.add("fabric", t)
        contact = simulate(motion, surface, profile, fidelity)
        t = timer.add("physics", t)
    if fabric is not None:
        support, texture_mm = fabric.support(), fabric.texture_mm
    # The image-resolution patch is the costliest fabric step: built only if some frame presses.
    touches = bool(np.any(contact.in_contact & (contact.normal_force_n > 0)))
    if patch is None and want_imprint and (touches or not shortcuts):
        patch = FabricPatch.for_motion(fabric, motion, profile, profile.image.mm_per_px, seed)
    t = timer.add("fabric", t)

    markers_on = profile.markers.enabled and want_markers
    rest = marker_grid(profile, seed=sensor_seed) if markers_on else None
    flat_markers = rest_markers(profile, seed=sensor_seed) if markers_on else None
    rng = np.random.default_rng(seed)
    T = motion.num_frames
    n_markers = 0 if rest is None else len(rest)
    markers_xy = np.zeros((T, n_markers, 2), np.float32)
    indentation = np.zeros(T, np.float32)
    area = np.zeros(T, np.float32)
    centroid = np.full((T, 2), np.nan, np.float32)   # NaN: no contact in that frame
    bbox = np.full((T, 4), np.nan, np.float32)
    window = "touched" if shortcuts else "full"
    prev = None  # the previous frame's imprint warm-starts the next (same result, fewer iterations)
    for i in range(T):
        force = float(contact.normal_force_n[i])
        imprint = None
        touching = bool(contact.in_contact[i]) and force > 0.0
        if want_imprint and (touching or not shortcuts):
            prot = patch.sample(profile.shape, profile.image.mm_per_px, contact.position_mm[i, 0],
                                contact.position_mm[i, 1], contact.yaw_deg[i], tuple(contact.tilt_deg[i]))
            t = timer.add("fabric", t)
            imprint = press(prot, profile, fidelity, force_n=force if touching else 0.0, support=support,
                            texture_mm=texture_mm, window=window, warm=prev)
            prev = imprint if touching else None
            indentation[i] = imprint.indentation_mm
            area[i] = imprint.contact_area_mm2
            centroid[i], bbox[i] = contact_location(imprint.contact_mask)
            t = timer.add("imprint", t)
        if rest is not None:
            if imprint is None:
                mk = flat_markers
            else:
                shear, twist = tuple(float(v) for v in contact.shear_mm[i]), float(contact.twist_deg[i])
                if shortcuts:
                    skip_shear, skip_twist = _negligible_px(shear, twist, profile)
                    shear = (0.0, 0.0) if skip_shear else shear
                    twist = 0.0 if skip_twist else twist
                mk = displace(profile, fidelity, imprint, shear_mm=shear, twist_deg=twist, rest=rest)
            markers_xy[i] = mk.xy_px
            t = timer.add("markers", t)
        else:
            mk = None
        if want_frames:
            depth = None if imprint is None else imprint.depth_mm
            frame = renderer.render(depth, mk, seed=rng)
            t = timer.add("optics", t)
        else:
            frame = None
        yield frame
        t = stage_clock()  # time spent by the consumer (encoding) is not ours

    labels = contact.to_dict()
    if want_imprint:
        labels.update(indentation_mm=indentation, contact_area_mm2=area, contact_centroid_px=centroid,
                      contact_bbox_px=bbox)
    if want_markers:
        labels.update(markers_xy_px=markers_xy,
                      markers_rest_px=(np.zeros((0, 2), np.float32) if rest is None else rest.astype(np.float32)))
    if out is not None:
        out.labels = labels
        out.timings_s = dict(timer.seconds)
