"""What a touched object adds to the gel's compliance: a fabric's two mechanisms.

A cloth lying on a table is soft in two ways that act at different length scales
(REFERENCES: "cloth-scale compression and yarn-scale flattening are different mechanisms
with different length scales"):

**Cloth-scale compression** (the whole layer gets thinner). Kawabata's compression test
(KES-FB3) measures the thickness at 0.5 gf/cm^2 (49 Pa, ``T0``) and at 50 gf/cm^2 (4.9 kPa,
``Tm``); apparel fabrics lose 20-60% of their thickness in between, ``EMC = (T0 - Tm) / T0``.
Between the two the thickness falls about linearly with log pressure (de Jong, Snaith and
Michie, Text. Res. J. 56, 1986), so the compression is taken as

    c(p) = T0 EMC ln(1 + p / p0) / ln(1 + pm / p0),   p0 = 49 Pa, pm = 4.9 kPa,

continued beyond pm on the same law and capped at ``MAX_COMPRESSION`` of T0 (the fibres'
own volume). The layer is stiff in shear over about its thickness (its yarns bridge the
voids that close), so it is a Pasternak layer of shear length ``T0`` whose stiffness is the
secant ``p / c(p)`` at the contact's mean pressure: it lets a pad conform to the cloth at the
contact's scale without flattening the texture.

**Yarn-scale flattening** (the crowns of the surface yarns, loops or fibres give). The
surface structure is a layer of thickness ``t_s`` (half the cloth: one of two yarn layers)
and transverse modulus ``E_s`` pressed point by point (a Winkler layer ``k_y = E_s / t_s``).
In series with the gel at the texture's wavenumber q (gel stiffness ``E* q / 2``), the gel
takes the share ``1 / (1 + E* q t_s / (2 E_s))`` of the relief (exact for a wave in complete
contact; the same share lowers the pressure for complete contact).

Units: mm, kPa for the support's pressures and stiffnesses, MPa for moduli.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import GelsimError

# Kawabata's two reference pressures (KES-FB3): 0.5 and 50 gf/cm^2, in kPa.
P0_KPA = 0.0490333
PM_KPA = 4.90333
# assumed: a compressed cloth keeps at least 20% of its thickness (fibre volume fractions of
# loose apparel fabrics are 0.1-0.3 and approach ~0.6-0.8 when fully packed).
MAX_COMPRESSION = 0.8
# assumed: the surface yarns (or loops, pile, grain) are about half the cloth's thickness.
SURFACE_LAYER_FRACTION = 0.5


@dataclass(frozen=True)
class FabricSupport:
    """A fabric between the gel and a rigid backing (a table).

    thickness_mm: T0, thickness at 49 Pa, mm.
    compressibility: Kawabata EMC, share of T0 lost between 49 Pa and 4.9 kPa (0-0.9).
    surface_modulus_mpa: transverse modulus of the surface structure (yarn crowns), MPa.
    """
    thickness_mm: float
    compressibility: float
    surface_modulus_mpa: float

    def __post_init__(self) -> None:
        for name, lo, hi in (("thickness_mm", 1e-3, 50.0), ("compressibility", 0.0, 0.9),
                             ("surface_modulus_mpa", 1e-3, 1e4)):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise GelsimError(f"FabricSupport.{name} = {v!r} is outside {lo}-{hi}; check the fabric's entry")

    @property
    def shear_length_mm(self) -> float:
        """Pasternak shear length of the cloth layer: its thickness, mm."""
        return self.thickness_mm

    def compression_mm(self, p_kpa: np.ndarray | float) -> np.ndarray:
        """Loss of thickness under the pressure ``p_kpa`` (kPa, >= 0), mm."""
        p = np.maximum(np.asarray(p_kpa, dtype=np.float64), 0.0)
        c = self.thickness_mm * self.compressibility * np.log1p(p / P0_KPA) / math.log1p(PM_KPA / P0_KPA)
        return np.minimum(c, MAX_COMPRESSION * self.thickness_mm)

    def secant_stiffness_kpa_per_mm(self, p_kpa: float) -> float:
        """p / c(p) at the mean contact pressure ``p_kpa``: the cloth's stiffness there, kPa/mm
        (its initial tangent for p -> 0)."""
        p = max(float(p_kpa), 1e-6)
        c = float(self.compression_mm(p))
        # An incompressible cloth, or one so barely compressible that c underflows: rigid.
        return p / c if c > 0 else math.inf

    @property
    def yarn_stiffness_mpa_per_mm(self) -> float:
        """k_y = E_s / t_s: crown flattening per unit pressure, MPa/mm."""
        return self.surface_modulus_mpa / (SURFACE_LAYER_FRACTION * self.thickness_mm)

    def texture_share(self, q_per_mm: np.ndarray, e_star_mpa: float) -> np.ndarray:
        """Share of the relief at wavenumber ``q`` (1/mm) that the gel takes: 1 / (1 + E* q / 2 k_y)."""
        q = np.asarray(q_per_mm, dtype=np.float32)
        return 1.0 / (1.0 + np.float32(e_star_mpa / (2.0 * self.yarn_stiffness_mpa_per_mm)) * q)
