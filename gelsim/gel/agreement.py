"""How well the fast imprint models agree with the elastic reference on fabric textures.

The cases: a 256 x 192 px patch (:data:`PATCH`: the ViTac pixel, 0.0197 mm/px, so 5.0 x 3.8 mm, on a
flat gel) of one catalog fabric of each family (:data:`FABRICS`) pressed over the whole patch at
7.5 kPa (:data:`PRESSURE_MPA`: 2 N on the full 18.9 x 14.2 mm pad, a firm press by hand; :data:`FORCE_N`
on the patch), rigid or on the fabric's own compliance (:class:`~gelsim.gel.FabricSupport`), at the
:data:`LEVELS` ("balanced", "fast") and with the elastic reference (:data:`ELASTIC`). The measures,
taken :data:`EDGE_MM` inside the patch's edge (the rim feels the edge, not the texture), on what the
camera sees of the texture (:func:`agreement`):

- ``corr``: Pearson correlation of the depth maps after removing a :data:`TEXTURE_MM` blur;
- ``slope``: RMS slope of the depth map, model over reference;
- ``contact``: fraction of the area in contact, model over reference;
- ``approach``: indentation for the same force, model over reference.

Used by tests/gelsim/test_gel_fabrics.py (which holds the tolerances) and ``benchmarks/bench_gel.py
--agreement`` (which prints the table of docs/imprint.md). Importing this module loads the ViTac
profile and the fidelity levels.
"""
from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np

from ..fabrics import load_catalog
from ..fidelity import get_fidelity
from ..scene import FabricObject, field_heights, press_properties
from ..sensor import load_profile
from . import Imprint, press

ELASTIC = dataclasses.replace(get_fidelity("reference"), imprint_model="elastic", imprint_scale=1.0)
LEVELS = {"balanced": get_fidelity("balanced"), "fast": get_fidelity("fast")}
FULL_PAD_MM2 = 18.912 * 14.184  # the ViTac field, 960 x 720 px at 0.0197 mm/px
PRESSURE_MPA = 2.0 / FULL_PAD_MM2
# One of each family the task names: plain weave, twill, knit, corduroy, felt, leather, mesh.
FABRICS = {"plain": 1, "twill": 21, "knit": 47, "corduroy": 65, "felt": 78, "leather": 86, "mesh": 95}
EDGE_MM = 0.6      # the patch's rim feels its edge, not the texture
TEXTURE_MM = 0.5   # blur removed before comparing textures: the yarn scale stays


def patch_profile():
    """The ViTac profile cut to a 256 x 192 px patch at 0.0197 mm/px on a flat gel."""
    p = load_profile("vitac")
    return dataclasses.replace(p, image=dataclasses.replace(p.image, width_px=256, height_px=192, mm_per_px=0.0197),
                               gel=dataclasses.replace(p.gel, dome_radius_mm=0.0))


PATCH = patch_profile()
FORCE_N = PRESSURE_MPA * PATCH.field_mm[0] * PATCH.field_mm[1]


@functools.cache
def fabric(name: str):
    """``(Fabric, protrusion)``: the :data:`FABRICS` fabric ``name`` and its heightfield over the
    patch, float32 (192, 256) mm, seed 0 (cached)."""
    fab = load_catalog()[FABRICS[name]]
    return fab, field_heights(FabricObject(fab), PATCH, seed=0)


@functools.cache
def imprint(name: str, supported: bool, level: str) -> Imprint:
    """The fabric ``name`` pressed with :data:`FORCE_N` on the patch, on its support or rigid, at
    ``level`` (a :data:`LEVELS` name or "elastic"); cached (the reference takes 1-9 s)."""
    fab, prot = fabric(name)
    fid = ELASTIC if level == "elastic" else LEVELS[level]
    props = press_properties(fab)
    return press(prot, PATCH, fid, force_n=FORCE_N, **{**props, "support": props["support"] if supported else None})


def inner(a: np.ndarray) -> np.ndarray:
    """The (192, 256) array ``a`` less an :data:`EDGE_MM` rim."""
    m = int(round(EDGE_MM / PATCH.image.mm_per_px))
    return a[m:-m, m:-m]


def texture(depth: np.ndarray) -> np.ndarray:
    """The depth map (mm) less its :data:`TEXTURE_MM` Gaussian blur, inside the rim, float64 mm."""
    d = depth.astype(np.float64)
    return inner(d - cv2.GaussianBlur(d, (0, 0), TEXTURE_MM / PATCH.image.mm_per_px))


def slope_rms(depth: np.ndarray) -> float:
    """RMS slope of the depth map (mm) inside the rim (mm/mm)."""
    gy, gx = np.gradient(inner(depth.astype(np.float64)), PATCH.image.mm_per_px)
    return float(np.sqrt(np.mean(gx * gx + gy * gy)))


def agreement(fast: Imprint, ref: Imprint) -> dict:
    """``{"corr", "slope", "contact", "approach"}`` of the imprint ``fast`` against ``ref`` (see above;
    the last three are ratios, 1 = agreement)."""
    ta, tb = texture(fast.depth_mm), texture(ref.depth_mm)
    return {"corr": float(np.corrcoef(ta.ravel(), tb.ravel())[0, 1]),
            "slope": slope_rms(fast.depth_mm) / slope_rms(ref.depth_mm),
            "contact": float(inner(fast.contact_mask).mean()) / float(inner(ref.contact_mask).mean()),
            "approach": fast.indentation_mm / ref.indentation_mm}
