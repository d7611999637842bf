"""Procedural fabrics: the 100-fabric catalog and their surface heightfields.

::

    from gelsim.fabrics import load_catalog, heightfield
    cat = load_catalog()                 # gelsim/assets/fabrics/*.toml, validated, cached
    h = heightfield(cat[12], x0_mm=0, y0_mm=0, width_px=960, height_px=720, mm_per_px=0.0197)

Modules: :mod:`.catalog` (data model, loading, validation), :mod:`.noise`
(hashed lattice noise), :mod:`.families` (one renderer per family),
:mod:`.render` (:func:`heightfield`, rotation), :mod:`.preview` (hillshade
images and the contact sheet).
"""
from .catalog import CATALOG_DIR, FAMILY_GROUPS, FAMILY_KEYS, Catalog, Fabric, load_catalog, parse_catalog
from .render import heightfield

__all__ = ["CATALOG_DIR", "FAMILY_GROUPS", "FAMILY_KEYS", "Catalog", "Fabric", "heightfield", "load_catalog",
           "parse_catalog"]
