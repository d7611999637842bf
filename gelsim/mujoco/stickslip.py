"""The gel surface's stick and slip on a MuJoCo pad: one pad's contact history as a public object.

The gel's shear and torsion springs (:func:`gelsim.contact.gel_stiffness`, :class:`GelSprings`) carry the tangential
load MuJoCo puts on the pad plus the pad's motion relative to the touched object since first contact, up to
Coulomb's limit ``mu N`` (``mu N r_eff`` in torsion); past it the gel slips and stays at the limit (the dataset
pipeline's model, :mod:`gelsim.contact`). :class:`StickSlip` is what one pad remembers between frames (where it
first touched the body, how far it has slipped); :class:`gelsim.mujoco.GelSightSensor` keeps one, and
:class:`gelsim.mujoco.batch.BatchGelSightSensor` one per pad, each passing its own to :meth:`StickSlip.step`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..contact import gel_stiffness
from .rays import MM


@dataclass(frozen=True)
class GelSprings:
    """The gel's springs as the stick/slip model uses them: ``k_shear_n_mm`` N per mm of shear,
    ``k_tors_nmm_rad`` N mm per radian of twist, ``r_eff_mm`` the lever arm of Coulomb's torsion limit, mm."""
    k_shear_n_mm: float
    k_tors_nmm_rad: float
    r_eff_mm: float

    @classmethod
    def of(cls, profile) -> "GelSprings":
        """The springs of ``profile``'s gel (:func:`gelsim.contact.gel_stiffness`, SI, converted to mm)."""
        k_shear, k_tors, r_eff = gel_stiffness(profile)
        return cls(k_shear * MM, k_tors / MM, r_eff / MM)


@dataclass
class StickSlip:
    """One pad's contact history: ``anchor`` (the body pressing it, and the pad's position (3,) m and rotation
    (3, 3) in that body's frame at first contact; None: no contact yet or any more), ``slip_mm`` float64 (2,) and
    ``slip_deg`` how far the gel has slipped since then (sensor frame). A fresh object is a pad never touched."""
    anchor: tuple | None = None
    slip_mm: np.ndarray = field(default_factory=lambda: np.zeros(2))
    slip_deg: float = 0.0

    def release(self) -> None:
        """Nothing presses the pad: the next contact anchors anew."""
        self.anchor = None

    def step(self, springs: GelSprings, body: int, pad_pose: tuple[np.ndarray, np.ndarray],
             body_pose: tuple[np.ndarray, np.ndarray], normal_n: float, tang_n: np.ndarray, torque_nmm: float,
             mu: float) -> tuple[np.ndarray, float, bool]:
        """This frame's gel shear (float64 (2,) mm) and twist (degrees, +x towards +y) relative to the pad, and
        whether it slips, from the pad's and the pressing body's poses (position (3,) m, rotation (3, 3), world),
        the objects' normal force ``normal_n`` (N), in-plane force ``tang_n`` ((2,) N) and torque ``torque_nmm``
        (N mm, about the normal) on the gel and the friction coefficient ``mu``. Updates the history."""
        p_pad, R_pad = pad_pose
        p_b, R_b = body_pose
        if self.anchor is None or self.anchor[0] != body:
            self.anchor = (body, R_b.T @ (p_pad - p_b), R_b.T @ R_pad)
            self.slip_mm[:] = 0.0
            self.slip_deg = 0.0
        _, p_rel, R_rel = self.anchor
        p_a, R_a = p_b + R_b @ p_rel, R_b @ R_rel      # where the pad would be had it stuck to the body
        moved = R_pad.T @ (p_pad - p_a) / MM           # pad's motion over the object, sensor frame, mm
        turn = R_a.T @ R_pad
        turned = math.degrees(math.atan2(turn[1, 0], turn[0, 0]))
        # The gel surface stays on the object: relative to the pad it moves the other way.
        shear = tang_n / springs.k_shear_n_mm - moved[:2] + self.slip_mm
        twist = math.degrees(torque_nmm / springs.k_tors_nmm_rad) - turned + self.slip_deg
        slipping = False
        lim = mu * normal_n / springs.k_shear_n_mm
        size = float(np.hypot(*shear))
        if size > lim:
            new = shear * (lim / size)
            self.slip_mm += new - shear
            shear, slipping = new, True
        lim_t = math.degrees(mu * normal_n * springs.r_eff_mm / springs.k_tors_nmm_rad)
        if abs(twist) > lim_t:
            new_t = math.copysign(lim_t, twist)
            self.slip_deg += new_t - twist
            twist, slipping = new_t, True
        return shear, twist, slipping
