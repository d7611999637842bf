"""The gel's kernels, numpy against torch (on the CPU), one step at a time: the layer's operator, the macro contact,
the cloth's support (the secant stiffness's fixed point, with the re-solve at the pad's travel), the texture stage
(gelsim/gel/layer.py, twoscale.py and their twins layer_torch.py, macro_torch.py, texture_torch.py).

Each pair is fed the same inputs (a catalog fabric's protrusion at the dataset's levels) and agrees within its
stated tolerance, :data:`REL` of its output's scale (measured 2026-11-29: 1e-9 to 1.3e-6 of it, float32 rounding,
the two kernels summing in another order; 3.9e-5 for a felt pressed past the pad's travel, whose solve at the
travel stops one conjugate-gradient step apart). Each test also checks that the tolerance is tight: the numpy
kernel with one input changed by :data:`NUDGE` (the force, the cell size, the pressure) falls outside it
(measured: 5e-4 of the scale and more at that nudge), so a change of either kernel that moves its output by as
much is caught here, kernel by kernel. The whole imprint's agreement over sequences
(warm starts, refined grids, stopping rules) is tests/gelsim/test_twoscale_torch.py's.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.fabrics import load_catalog  # noqa: E402
from gelsim.fidelity import get_fidelity  # noqa: E402
from gelsim.gel import gel_sag_mm, work_shape  # noqa: E402
from gelsim.gel import layer_torch, macro_torch, texture_torch  # noqa: E402
from gelsim.gel import twoscale as ts  # noqa: E402
from gelsim.gel.layer import Operator  # noqa: E402
from gelsim.gel.util import bbox  # noqa: E402
from gelsim.scene import as_object, field_heights, press_properties  # noqa: E402
from gelsim.sensor import load_profile  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")

#: Stated agreement of each kernel pair: the largest difference within this fraction of the output's largest value.
REL = 1e-4
#: How much one input is changed to show that the tolerance sees a change (relative).
NUDGE = 3e-3


def agree(ref, got, scale: float, perturbed, what: str):
    """``got`` within REL * ``scale`` of ``ref``; the ``perturbed`` numpy output outside it."""
    tol = REL * scale
    e = float(np.abs(np.asarray(ref, np.float64) - np.asarray(got, np.float64)).max())
    assert e <= tol, f"{what}: numpy and torch differ by {e:.3g} > {tol:.3g}"
    p = float(np.abs(np.asarray(perturbed, np.float64) - np.asarray(got, np.float64)).max())
    assert p > tol, f"{what}: a perturbed kernel differs by {p:.3g}, within {tol:.3g}: the test is blind"


class Press:
    """One frame's inputs to the macro contact, as press_twoscale makes them: a catalog fabric over the field."""

    def __init__(self, fabric_id: int, level: str, resolution=(160, 120), force_n: float = 3.0):
        self.profile = load_profile("vitac").with_resolution(*resolution)
        self.fid = get_fidelity(level)
        obj = as_object(load_catalog()[fabric_id])
        self.props = press_properties(obj)
        ws = work_shape(self.profile, self.fid.imprint_scale)
        self.own = field_heights(obj, self.profile.with_resolution(ws[1], ws[0]), seed=fabric_id).astype(np.float32)
        self.sag = gel_sag_mm(self.profile, ws)
        self.work = self.own if self.sag is None else self.own - self.sag
        self.dx = self.profile.image.mm_per_px * self.profile.shape[1] / ws[1]
        self.gel = self.profile.gel
        tex = ts.texture_scale_mm(self.props.get("texture_mm"), self.gel)
        self.tex = tex if tex is not None and tex >= ts.MIN_TEXTURE_PX * self.dx else None
        self.support = self.props.get("support")
        self.force = force_n
        vmax = self.gel.max_indentation_mm
        self.box = bbox(self.work > np.float32(float(self.work.max()) - vmax))
        valley, cpv = self.props.get("valley_mm"), self.fid.macro_cells_per_valley
        self.f = ts.macro_cell_px(self.box, self.fid.macro_cells, self.dx, valley, cpv)
        self.plan = macro_torch.plan_grid(self.box, self.fid.macro_cells, self.dx, valley, cpv)

    def numpy_macro(self, force_n=None):
        return ts.solve_macro(self.work, self.box, self.dx, self.gel, self.tex, self.support,
                              self.force if force_n is None else force_n, None, self.f, None, self.sag, self.own)

    def torch_macro(self):
        sag = None if self.sag is None else torch.as_tensor(np.array(self.sag))
        return macro_torch.solve_macro(torch.as_tensor(self.work)[None], torch.as_tensor(self.own)[None], sag,
                                       [self.plan], self.dx, self.gel, [self.tex], [self.support],
                                       np.array([self.force]), [None])


CASES = [(21, "balanced"), (78, "fast"), (86, "balanced")]       # a twill, a felt, a leather


@pytest.mark.parametrize("cells, cm", [((37, 45), 0.3), ((24, 64), 0.12)])
def test_layer_operator(cells, cm):
    gel = load_profile("vitac").gel
    p = np.random.default_rng(cells[0]).random(cells).astype(np.float32) * 0.01
    ref = Operator(cells, cm, gel, dtype=np.float32).gel(p)
    got = layer_torch.gel_operator([cells], [cm], gel, cells, "cpu")(torch.as_tensor(p)[None])[0].numpy()
    nudged = Operator(cells, cm * (1 + NUDGE), gel, dtype=np.float32).gel(p)
    agree(ref, got, float(np.abs(ref).max()), nudged, "layer operator")


@pytest.mark.parametrize("fabric_id, level", CASES)
def test_macro_contact(fabric_id, level):
    case = Press(fabric_id, level)
    ref = case.numpy_macro()
    got = case.torch_macro()
    ny, nx = case.plan.cshape
    assert case.plan.f == ref.f and (ny, nx) == ref.cshape
    nudged = case.numpy_macro(case.force * (1 + NUDGE))
    agree(ref.p, got.p[0, :ny, :nx].numpy(), float(ref.p.max()), nudged.p, "macro pressure")
    assert bool(got.bottomed[0]) == ref.bottomed
    if not ref.bottomed:                                    # (else both at the pad's travel exactly)
        agree(ref.delta, got.delta[0], ref.delta, nudged.delta, "macro approach")


@pytest.mark.parametrize("fabric_id, level", CASES)
@pytest.mark.parametrize("force_n", [3.0, 100.0])            # 100 N: past the pad's travel (re-solved there)
def test_cloth_support(fabric_id, level, force_n):
    case = Press(fabric_id, level)
    sol = case.numpy_macro()
    hc = ts.hc_of(sol)
    vmax = case.gel.max_indentation_mm
    p0 = np.sqrt(np.maximum(hc + max(0.05 * vmax, 1e-4), 0.0))

    def numpy_cloth(force):
        return ts.solve_on_cloth(hc, sol.cm, case.gel, case.support, force, None, p0, vmax=vmax, tol=ts.MACRO_TOL,
                                 maxit=ts.MACRO_MAXIT)

    p, delta, bottomed = numpy_cloth(force_n)
    valid = torch.ones((1,) + hc.shape, dtype=torch.bool)
    pt, dt, bt = macro_torch.solve_on_cloth(torch.as_tensor(hc)[None], valid, [hc.shape], [sol.cm], case.gel,
                                            [case.support], np.array([force_n]), torch.as_tensor(p0).float()[None],
                                            vmax=vmax, at_travel=np.array([False]), cells_pred=[None])
    assert bool(bt[0]) == bottomed and (bottomed or force_n < 10)
    pn, dn, _ = numpy_cloth(force_n * (1 + NUDGE))
    agree(p, pt[0].numpy(), float(p.max()), pn, "cloth support pressure")
    if not bottomed:
        agree(delta, dt[0], delta, dn, "cloth support approach")


@pytest.mark.parametrize("fabric_id, level", [(21, "balanced"), (21, "fast"), (86, "balanced")])
def test_texture_stage(fabric_id, level):
    case = Press(fabric_id, level, resolution=(320, 240))
    if case.tex is None:
        pytest.skip("no texture stage at this level")
    h, w = case.work.shape
    w0, w1, v0, v1 = h // 6, h - h // 5, w // 7, w - w // 6           # a window, not aligned to the cells
    sag = 0.0 if case.sag is None else case.sag[w0:w1, v0:v1]
    surface = case.work[w0:w1, v0:v1]
    env = (ts.crown_envelope(case.own, case.tex, case.dx)[w0:w1, v0:v1] - sag).astype(np.float32)
    pressure = 0.02                                                     # MPa, the local mean
    cloth = 1e-3 * (case.support.secant_stiffness_kpa_per_mm(20.0) if case.support is not None else math.inf)

    def numpy_texture(p):
        return ts.texture_depth(surface, env, lambda cs, shape: np.full((cs[1], cs[0]), p, np.float32), case.dx,
                                case.gel, case.support, case.tex, cloth)

    ref = numpy_texture(pressure)
    scale = texture_torch.TextureScale(case.tex, case.dx)
    ny, nx = surface.shape

    def window(a):      # at the top-left of the batch's array, continued by replication (batch_ops.crop's form)
        return torch.as_tensor(np.pad(a, ((0, scale.unit), (0, scale.unit)), mode="edge"))[None]

    got = texture_torch.texture_depth(window(surface), window(env), torch.tensor([ny]), torch.tensor([nx]),
                                      lambda rows, cols, NYb, NXb: torch.full((1, int(rows.max()), int(cols.max())),
                                                                              pressure),
                                      scale, case.gel, [case.support], np.array([cloth]))
    nudged = numpy_texture(pressure * (1 + NUDGE))
    g = got.g[0, :ny, :nx].numpy()
    agree(ref.g[:ny, :nx], g, float(np.abs(ref.g[:ny, :nx]).max()), nudged.g[:ny, :nx], "texture relief")
    rows, cols = ref.mean.shape
    agree(ref.mean, got.mean[0, :rows, :cols].numpy(), float(np.abs(ref.mean).max()), nudged.mean, "texture mean")
    assert np.array_equal(ref.touch[:ny, :nx], got.touch[0, :ny, :nx].numpy())
