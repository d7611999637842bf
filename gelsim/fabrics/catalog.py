"""The fabric catalog: TOML entries under ``gelsim/assets/fabrics/`` into frozen :class:`Fabric` records.

Each ``*.toml`` file in the catalog folder holds ``[[fabric]]`` entries (one file
per family group). Adding a fabric is adding an entry: every geometric
parameter is data, the renderer is chosen by ``family``. Loading validates
every entry with :func:`gelsim.params.build` (unknown or missing key, wrong
type, out-of-range value) and then the catalog as a whole (known family, the
family's own keys present and no foreign ones, ids unique and 1..N).
"""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from ..errors import GelsimError
from ..params import ASSETS_DIR, build, load_toml, param

CATALOG_DIR = ASSETS_DIR / "fabrics"

# Geometric keys each family needs (and may have); the common keys of Fabric with
# defaults (hairiness, waviness, jitter, slubs, orientation) are allowed for all.
_WOVEN = ("warp_pitch_mm", "weft_pitch_mm", "warp_width_mm", "weft_width_mm", "crimp")
_KNIT = ("warp_pitch_mm", "weft_pitch_mm", "warp_width_mm")
_MESH = ("warp_pitch_mm", "warp_width_mm", "mesh_angle_deg", "mesh_third_set")
FAMILY_KEYS: dict[str, tuple[str, ...]] = {
    # woven: warp yarns run along v (image rows), spaced warp_pitch_mm along u
    "plain": _WOVEN,
    "twill": _WOVEN + ("twill_over", "twill_under"),
    "satin": _WOVEN + ("satin_harness", "satin_step"),
    "basket": _WOVEN + ("basket_group",),
    "herringbone": _WOVEN + ("twill_over", "twill_under", "herringbone_warps"),
    "ripstop": _WOVEN + ("ripstop_every",),
    # knitted: warp_pitch = wale spacing, weft_pitch = course spacing, warp_width = yarn width
    "jersey": _KNIT,
    "interlock": _KNIT,
    "purl": _KNIT,
    "rib": _KNIT + ("rib_face_wales", "rib_back_wales"),
    # pile
    "corduroy": ("warp_pitch_mm", "warp_width_mm", "weft_pitch_mm"),
    "velvet": ("feature_mm",),
    "terry": ("warp_pitch_mm", "weft_pitch_mm", "warp_width_mm"),
    # non-woven and leather
    "felt": ("feature_mm", "anisotropy"),
    "fleece": ("feature_mm", "anisotropy"),
    "leather": ("feature_mm", "pore_spacing_mm", "pore_diameter_mm"),
    "suede": ("feature_mm", "pore_spacing_mm", "pore_diameter_mm"),
    # open
    "mesh": _MESH,
    "lace": _MESH + ("motif_mm", "motif_fill"),
}
FAMILY_GROUPS: dict[str, tuple[str, ...]] = {
    "woven": ("plain", "twill", "satin", "basket", "herringbone", "ripstop"),
    "knitted": ("jersey", "interlock", "purl", "rib"),
    "pile": ("corduroy", "velvet", "terry"),
    "non-woven": ("felt", "fleece"),
    "leather": ("leather", "suede"),
    "open": ("mesh", "lace"),
}


@dataclass(frozen=True)
class Fabric:
    """One catalog fabric: identity, material properties and the family's geometry (mm).

    Coordinates: ``u`` across the warp (image columns at rotation 0), ``v`` along the warp.
    """
    id: int = param(lo=1, doc="1-based catalog id, contiguous")
    name: str = param(doc="human name, e.g. 'cotton poplin'")
    family: str = param(doc="renderer family, one of FAMILY_KEYS")
    material: str = param(doc="fibre, e.g. 'cotton'")
    friction: float = param(lo=0.4, hi=1.0, doc="coefficient of friction on silicone rubber")
    thickness_mm: float = param(lo=0.05, hi=6.0, doc="uncompressed fabric thickness, mm")
    compressibility: float = param(lo=0.0, hi=0.9,
                                   doc="Kawabata EMC: share of the thickness lost between 49 Pa and 4.9 kPa")
    surface_modulus_mpa: float = param(lo=0.01, hi=1000.0,
                                       doc="transverse modulus of the surface yarns, loops, pile or grain, MPa")
    relief_mm: float = param(lo=0.005, hi=2.0, doc="peak-to-base height of the surface texture, mm")
    # Irregularity and fuzz, for every family.
    hairiness: float = param(0.0, lo=0.0, hi=0.6, doc="share of the relief given to fibre fuzz, 0-0.6")
    fibre_mm: float = param(0.03, lo=0.005, hi=0.5, doc="size of the fuzz features (fibre scale), mm")
    waviness: float = param(0.0, lo=0.0, hi=0.6, doc="share of the relief given to low-frequency undulation")
    waviness_mm: float = param(3.0, lo=0.1, hi=50.0, doc="wavelength of that undulation, mm")
    spacing_jitter: float = param(0.0, lo=0.0, hi=0.45, doc="random yarn/loop position error, fraction of pitch")
    slub: float = param(0.0, lo=0.0, hi=1.5, doc="slub strength: relative thickening of yarns at thick spots")
    slub_length_mm: float = param(2.0, lo=0.1, hi=50.0, doc="typical length of a slub along the yarn, mm")
    orientation_deg: float = param(0.0, lo=-180.0, hi=180.0, doc="rotation of the weave in the fabric plane, degrees")
    description: str = param("", doc="free text")
    # Family geometry (see FAMILY_KEYS for which family uses which).
    warp_pitch_mm: float | None = param(None, lo=0.02, hi=20.0, lo_open=True,
                                        doc="spacing of warp yarns / wales / ridges / loops across u, mm")
    weft_pitch_mm: float | None = param(None, lo=0.02, hi=20.0, lo_open=True,
                                        doc="spacing of weft yarns / courses / tuft rows along v, mm")
    warp_width_mm: float | None = param(None, lo=0.005, hi=20.0, doc="width of a warp yarn / knit yarn / ridge / loop, mm")
    weft_width_mm: float | None = param(None, lo=0.005, hi=20.0, doc="width of a weft yarn, mm")
    crimp: float | None = param(None, lo=0.0, hi=1.0, doc="yarn undulation at interlacings, relative to yarn thickness")
    twill_over: int | None = param(None, lo=1, hi=8, doc="wefts a warp floats over in a twill")
    twill_under: int | None = param(None, lo=1, hi=8, doc="wefts a warp passes under in a twill")
    satin_harness: int | None = param(None, lo=4, hi=16, doc="satin repeat (shafts)")
    satin_step: int | None = param(None, lo=1, hi=15, doc="satin counter (move number)")
    basket_group: int | None = param(None, lo=2, hi=6, doc="yarns woven together as one in a basket weave")
    herringbone_warps: int | None = param(None, lo=2, hi=64, doc="warps per herringbone stripe before the twill reverses")
    ripstop_every: int | None = param(None, lo=3, hi=64, doc="a reinforcement yarn every this many yarns")
    rib_face_wales: int | None = param(None, lo=1, hi=6, doc="face wales per rib")
    rib_back_wales: int | None = param(None, lo=1, hi=6, doc="back wales per rib")
    feature_mm: float | None = param(None, lo=0.02, hi=20.0, doc="size of the surface features (clumps, grain cells), mm")
    anisotropy: float | None = param(None, lo=1.0, hi=8.0, doc="elongation of the features along v (brushing direction)")
    pore_spacing_mm: float | None = param(None, lo=0.05, hi=5.0, doc="spacing of leather pores, mm")
    pore_diameter_mm: float | None = param(None, lo=0.0, hi=1.0, doc="diameter of leather pores (0: none), mm")
    mesh_angle_deg: float | None = param(None, lo=15.0, hi=90.0, doc="angle of the two yarn sets of a net to u, degrees")
    mesh_third_set: bool | None = param(None, doc="add a third yarn set along u (hexagonal/tulle net)")
    motif_mm: float | None = param(None, lo=0.5, hi=50.0, doc="size of the lace motifs, mm")
    motif_fill: float | None = param(None, lo=0.05, hi=0.9, doc="fraction of the lace covered by motifs")

    def validate(self, where: str) -> None:
        if self.family not in FAMILY_KEYS:
            raise GelsimError(f"{where}.family: unknown family {self.family!r}; use one of "
                              + ", ".join(sorted(FAMILY_KEYS)))
        needed = FAMILY_KEYS[self.family]
        for k in needed:
            if getattr(self, k) is None:
                raise GelsimError(f"{where}.{k}: missing; family {self.family!r} needs "
                                  + ", ".join(needed))
        for k in _OPTIONAL_GEOMETRY:
            if k not in needed and getattr(self, k) is not None:
                raise GelsimError(f"{where}.{k}: not used by family {self.family!r}; remove it "
                                  f"(the family's keys are {', '.join(needed)})")
        if self.relief_mm > self.thickness_mm:
            raise GelsimError(f"{where}.relief_mm: {self.relief_mm} exceeds thickness_mm {self.thickness_mm}; "
                              "the texture cannot be deeper than the fabric")
        if self.hairiness + self.waviness > 0.8:
            raise GelsimError(f"{where}: hairiness + waviness = {self.hairiness + self.waviness:g} leaves too "
                              "little relief to the structure; keep the sum <= 0.8")
        for w, p in (("warp_width_mm", "warp_pitch_mm"), ("weft_width_mm", "weft_pitch_mm")):
            wv, pv = getattr(self, w), getattr(self, p)
            if wv is not None and pv is not None and wv > 2.0 * pv and self.family not in ("mesh", "lace"):
                raise GelsimError(f"{where}.{w}: {wv} mm is more than twice {p} ({pv} mm); "
                                  "yarns that wide cannot sit side by side")
        if self.family == "satin" and self.satin_step is not None and self.satin_harness is not None:
            import math
            if not 1 < self.satin_step < self.satin_harness - 1 or math.gcd(self.satin_step, self.satin_harness) != 1:
                raise GelsimError(f"{where}.satin_step: {self.satin_step} does not make a satin with harness "
                                  f"{self.satin_harness}; use a step coprime with it, between 2 and harness - 2")

    def support(self):
        """The fabric's compliance under a pressing gel (:class:`gelsim.gel.FabricSupport`): cloth
        compression (thickness, Kawabata compressibility) and yarn-scale flattening."""
        from ..gel.support import FabricSupport

        return FabricSupport(self.thickness_mm, self.compressibility, self.surface_modulus_mpa)

    @property
    def texture_mm(self) -> float:
        """The texture's scale, mm: the distance between neighbouring crowns along the coarser
        direction (a weave's or knit's larger pitch, a basket's group, a felt's clump or a grain
        cell), over which the imprint separates crowns from valleys."""
        fam = self.family
        if fam in ("velvet", "felt", "fleece", "leather", "suede"):
            return float(self.feature_mm)
        if fam == "corduroy":  # the pile tufts along a wale; the wales themselves are relief
            return float(self.weft_pitch_mm)
        pitches = [p for p in (self.warp_pitch_mm, self.weft_pitch_mm) if p is not None]
        scale = max(pitches)
        if fam == "basket":
            scale *= self.basket_group
        return float(scale)

    @property
    def macro_valley_mm(self) -> float | None:
        """The narrowest valley the fabric's crown envelope keeps, mm: a corduroy's gap between wales
        (wale spacing less ridge width), which the closing over its tuft rows leaves open and the
        imprint's contact-scale grid must resolve (:data:`gelsim.gel.twoscale.MACRO_CELLS_PER_VALLEY`).
        None for the other families: their envelope's valleys are wider than ``texture_mm``, which the
        grid resolves at every size it takes (docs/fidelity.md)."""
        if self.family == "corduroy" and self.warp_pitch_mm > self.warp_width_mm:
            return float(self.warp_pitch_mm - self.warp_width_mm)
        return None  # (wales as wide as their spacing touch: no flat-bottomed gap to resolve)

    def to_dict(self) -> dict:
        """Plain data, without the unused (None) geometry keys."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


_OPTIONAL_GEOMETRY = tuple(f.name for f in dataclasses.fields(Fabric) if f.default is None)


class Catalog:
    """The fabrics in id order: ``len(c)``, ``iter(c)``, ``c[id]``; ``c.version`` names the content."""

    def __init__(self, fabrics: list[Fabric], version: str, source: str = ""):
        self._fabrics = sorted(fabrics, key=lambda f: f.id)
        self._by_id = {f.id: f for f in self._fabrics}
        self.version = version
        self.source = source
        self.ids = [f.id for f in self._fabrics]

    def __len__(self) -> int:
        return len(self._fabrics)

    def __iter__(self) -> Iterator[Fabric]:
        return iter(self._fabrics)

    def __getitem__(self, fabric_id: int) -> Fabric:
        try:
            return self._by_id[int(fabric_id)]
        except (KeyError, TypeError, ValueError):
            lo, hi = (self.ids[0], self.ids[-1]) if self.ids else (0, 0)
            raise GelsimError(f"unknown fabric id {fabric_id}; ids run {lo}-{hi}") from None

    def by_name(self, name: str) -> Fabric:
        for f in self._fabrics:
            if f.name == name:
                return f
        raise GelsimError(f"unknown fabric name {name!r}; see `gelsim fabrics list`")

    def __repr__(self) -> str:
        return f"Catalog({len(self)} fabrics, version {self.version})"


def _catalog_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise GelsimError(f"fabric catalog {path} not found; give a folder of .toml files or one .toml file")
    files = sorted(path.glob("*.toml"))
    if not files:
        raise GelsimError(f"fabric catalog {path} has no .toml files; add [[fabric]] entries in a .toml file")
    return files


def catalog_version(files: list[Path]) -> str:
    """12 hex characters of the SHA-256 of the catalog files' names and contents."""
    h = hashlib.sha256()
    for f in files:
        h.update(f.name.encode("utf-8") + b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:12]


def parse_catalog(path: str | Path) -> Catalog:
    """Load and validate a catalog folder (or one file) without caching."""
    path = Path(path)
    files = _catalog_files(path)
    fabrics: list[Fabric] = []
    seen: dict[int, str] = {}
    names: dict[str, str] = {}
    for f in files:
        data = load_toml(f)
        unknown = sorted(set(data) - {"fabric"})
        if unknown:
            raise GelsimError(f"{f}: unknown top-level key {unknown[0]!r}; a catalog file holds only "
                              "[[fabric]] entries")
        entries = data.get("fabric", [])
        if not isinstance(entries, list):
            raise GelsimError(f"{f}: 'fabric' must be an array of tables; write each entry as [[fabric]]")
        for n, entry in enumerate(entries, 1):
            label = f"{f.name}: fabric #{n}"
            if isinstance(entry, dict) and "id" in entry:
                label += f" (id {entry['id']})"
            fab = build(Fabric, entry, where=label)
            if fab.id in seen:
                raise GelsimError(f"{label}: duplicate id {fab.id} (also {seen[fab.id]}); give each fabric "
                                  "its own id")
            if fab.name in names:
                raise GelsimError(f"{label}: duplicate name {fab.name!r} (also {names[fab.name]}); "
                                  "give each fabric its own name")
            seen[fab.id] = label
            names[fab.name] = label
            fabrics.append(fab)
    ids = sorted(seen)
    if ids != list(range(1, len(ids) + 1)):
        missing = sorted(set(range(1, len(ids) + 1)) - set(ids))
        raise GelsimError(f"{path}: fabric ids must run 1..{len(ids)} without gaps; id {missing[0]} is missing "
                          f"(highest is {ids[-1]}); renumber the entries")
    return Catalog(fabrics, catalog_version(files), source=str(path))


_CACHE: dict[tuple, Catalog] = {}


def load_catalog(path: str | Path | None = None) -> Catalog:
    """The validated catalog at ``path`` (default ``gelsim/assets/fabrics/``), cached until its files change."""
    path = Path(path) if path is not None else CATALOG_DIR
    files = _catalog_files(path)
    key = (str(path.resolve()),) + tuple((str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in files)
    cat = _CACHE.get(key)
    if cat is None:
        cat = parse_catalog(path)
        _CACHE.clear()
        _CACHE[key] = cat
    return cat
