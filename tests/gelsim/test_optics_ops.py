"""Each optics primitive's numpy kernel against its torch kernel (on the CPU), op by op (gelsim/optics/ops).

Inputs are random, drawn fresh on every run (the seed is in every failure's message; set
``GELSIM_OPS_SEED`` to replay one), over several shapes and parameters. Each op states its tolerance:
the two kernels compute the same float32 arithmetic in another order (OpenCV's vector code, fused
multiply-adds), so most agree to a few float32 steps of their output's scale (``EPS`` = 2^-23 of it);
the table lookup differs by OpenCV remap's fixed-point weights (1/32 of a bin), bounded by the table's
steepest step between bins. Each test also checks that the tolerance is tight: the same op with one
input or parameter changed by a little (a thousandth, a hundredth of a pixel) falls outside it, so a
change of either kernel that moves its output by as much is caught here, op by op.
"""
from __future__ import annotations

import dataclasses
import os

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim.optics.ops import box, coarse, filters, markers, phong, readout, resample, shadows, table  # noqa: E402

EPS = float(np.finfo(np.float32).eps)
SEED = int(os.environ.get("GELSIM_OPS_SEED", np.random.SeedSequence().entropy % (1 << 63)))
SHAPES = [(17, 23), (48, 64), (9, 130)]


@pytest.fixture
def rng(request):
    """A generator for this test, from the run's seed and the test's name (reproducible with GELSIM_OPS_SEED)."""
    return np.random.default_rng([SEED, *request.node.name.encode()])


def t(a):
    """A numpy array as a CPU tensor."""
    return torch.from_numpy(np.ascontiguousarray(a))


def n(x):
    """A tensor as a float64 array."""
    return x.detach().cpu().numpy().astype(np.float64)


def err(ref, got) -> float:
    return float(np.abs(np.asarray(ref, np.float64) - np.asarray(got, np.float64)).max())


def agree(ref, got, tol: float, perturbed=None, what: str = ""):
    """``got`` within ``tol`` (absolute) of ``ref``; and ``perturbed`` (the numpy op with an input changed by a
    little), if given, outside it: the tolerance is tight enough to see such a change."""
    e = err(ref, got)
    assert e <= tol, f"{what}: numpy and torch differ by {e:.3g} > {tol:.3g} (GELSIM_OPS_SEED={SEED})"
    if perturbed is not None:
        p = err(perturbed, got)
        assert p > tol, f"{what}: a perturbed kernel differs by {p:.3g}, within {tol:.3g}: the test is blind"


def field(rng, shape, lo=0.0, hi=1.0, smooth=1.5):
    """A random float32 field of ``shape`` (H, W[, C]) in ``lo``-``hi``: noise blurred by ``smooth`` px."""
    f = rng.random(shape).astype(np.float32)
    if smooth > 0:
        f = cv2.GaussianBlur(f, (0, 0), smooth)
        f = (f - f.min()) / max(float(f.max() - f.min()), 1e-6)
    return (lo + (hi - lo) * f).astype(np.float32)


def imprint(rng, shape, mm_per_px):
    """A random imprint, float32 (H, W) mm >= 0: a few balls pressed in (zero around them), the first a
    steep one (it casts shadows), on a weave."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) * mm_per_px
    d = np.zeros(shape, np.float32)
    for i in range(int(rng.integers(1, 4))):
        cx, cy = rng.uniform(0.2, 0.8) * w * mm_per_px, rng.uniform(0.2, 0.8) * h * mm_per_px
        r, depth = (rng.uniform(0.8, 1.2), rng.uniform(0.5, 0.7)) if i == 0 else (rng.uniform(0.6, 2.5),
                                                                              rng.uniform(0.1, 0.6))
        d = np.maximum(d, np.sqrt(np.maximum(r * r - (xx - cx) ** 2 - (yy - cy) ** 2, 0.0)) - (r - depth))
    weave = 0.03 * np.sin(2 * np.pi * xx / rng.uniform(0.3, 0.9)) * np.cos(2 * np.pi * yy / rng.uniform(0.3, 0.9))
    return np.maximum(d + np.where(d > 0, weave, 0.0), 0.0).astype(np.float32)


# ---------------------------------------------------------------- filters

# A weighted sum of K float32 terms in two orders (OpenCV sums symmetric taps first, with fused
# multiply-adds): each differs from the exact sum by at most K EPS times its largest term.
BLUR_TOL = 16 * EPS


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("channels", [0, 3])
def test_camera_blur(rng, shape, channels):
    sigma = float(rng.uniform(0.4, 2.5))
    x = field(rng, shape + ((channels,) if channels else ()), -40.0, 300.0, smooth=0)
    ref = filters.gaussian_blur(x, sigma)
    got = filters.gaussian_blur_torch(t(np.moveaxis(x, -1, 0) if channels else x), sigma)
    got = np.moveaxis(n(got), 0, -1) if channels else n(got)
    agree(ref, got, BLUR_TOL * 300.0, filters.gaussian_blur(x, sigma * 1.001), "camera blur")


@pytest.mark.parametrize("border", ["replicate", "constant"])
def test_smooth(rng, border):
    for shape in SHAPES:
        sigma = float(rng.uniform(0.5, 4.0))
        x = field(rng, shape, -1.0, 2.0, smooth=0)
        agree(filters.smooth(x, sigma, border), n(filters.smooth_torch(t(x), sigma, border)), BLUR_TOL * 2.0,
              filters.smooth(x, sigma * 1.001, border), f"smooth {border}")


@pytest.mark.parametrize("shape", SHAPES)
def test_slopes(rng, shape):
    mm = float(rng.uniform(0.015, 0.08))
    d = field(rng, shape, 0.0, 0.5, smooth=1.0)
    gx, gy = filters.slopes(d, mm)
    tx, ty = filters.slopes_torch(t(d)[None], mm)
    scale = 0.5 / mm                                       # the largest slope a 0.5 mm step can make
    px, py = filters.slopes(d, mm * 1.001)
    agree(gx, n(tx)[0], 8 * EPS * scale, px, "slope x")
    agree(gy, n(ty)[0], 8 * EPS * scale, py, "slope y")


@pytest.mark.parametrize("k", [1, 2, 3, 4, 6])
def test_mix_channels(rng, k):
    shape = SHAPES[int(rng.integers(len(SHAPES)))]
    stack = field(rng, shape + (k,), -30.0, 30.0, smooth=0)
    matrix = rng.uniform(-5.0, 5.0, (3, k)).astype(np.float32)
    ref = filters.mix_channels(stack[..., 0] if k == 1 else stack, matrix)
    got = np.moveaxis(n(filters.mix_channels_torch([t(stack[..., i])[None] for i in range(k)], matrix))[0], 0, -1)
    agree(ref, got, 2 * k * EPS * 30.0 * 5.0, filters.mix_channels(stack * np.float32(1.0001), matrix), "mix")


# ---------------------------------------------------------------- resampling

@pytest.mark.parametrize("f", [2, 3, 4])
def test_area_mean(rng, f):
    for shape in SHAPES + [(12, 16, 3)]:
        x = field(rng, shape, -20.0, 280.0, smooth=0)
        ref = resample.area_mean(x, f)
        xt = t(np.moveaxis(x, -1, 0)) if x.ndim == 3 else t(x)
        got = n(resample.area_mean_torch(xt, f))
        got = np.moveaxis(got, 0, -1) if x.ndim == 3 else got
        # the mean of f^2 terms: a few steps of 280 DN
        agree(ref, got, 4 * EPS * 280.0, resample.area_mean(np.roll(x, 1, axis=1), f), f"area mean {shape}")


@pytest.mark.parametrize("f", [1, 2, 3, 5, 6])
def test_upsample(rng, f):
    for hs, ws in ((5, 7), (24, 32), (3, 40)):
        g = field(rng, (hs, ws, 3), -50.0, 50.0, smooth=0)
        shape = (hs * f - int(rng.integers(0, f)), ws * f - int(rng.integers(0, f)))
        ref = resample.upsample(g, f, shape)
        got = np.moveaxis(n(resample.upsample_torch(t(np.moveaxis(g, -1, 0)), f, shape)), 0, -1)
        perturbed = resample.upsample(g * np.float32(1.001), f, shape)
        agree(ref, got, 4 * EPS * 50.0, perturbed, f"upsample by {f}")


# ---------------------------------------------------------------- the shading's box

def test_box_mask(rng):
    for shape in SHAPES:
        d = np.zeros(shape, np.float32)
        if rng.random() < 0.8:
            y, x = int(rng.integers(shape[0])), int(rng.integers(shape[1]))
            d[y:y + int(rng.integers(1, 6)), x:x + int(rng.integers(1, 9))] = 0.1
        margin = int(rng.integers(0, 5))
        want = np.zeros(shape, bool)
        roi = box.imprint_roi(d, margin)
        if roi is not None:
            want[roi] = True
        got = box.box_mask_torch(t(d > 0)[None], margin)[0, 0].numpy()
        np.testing.assert_array_equal(got, want, err_msg=f"GELSIM_OPS_SEED={SEED}")


# ---------------------------------------------------------------- Phong shading

def _phong_profile(vitac, width, specular):
    p = vitac.with_resolution(width)
    return dataclasses.replace(p, shading=dataclasses.replace(p.shading, model="phong", specular=specular))


@pytest.mark.parametrize("width", [64, 160])
@pytest.mark.parametrize("specular", [0.0, 0.3])
def test_phong(rng, vitac, width, specular):
    from gelsim.optics.field import light_maps

    prof = _phong_profile(vitac, width, specular)
    lights = phong.phong_lights(prof, light_maps(prof))
    h, w = prof.shape
    gx, gy = field(rng, (h, w), -1.5, 1.5), field(rng, (h, w), -1.5, 1.5)
    bufs = {}

    def buffer(name, shape):
        return bufs.setdefault(name, np.empty(shape, np.float32))

    full = (slice(0, h), slice(0, w))
    ref = phong.phong_change(gx, gy, lights, full, buffer).copy()
    got = np.moveaxis(n(phong.phong_change_torch(t(gx)[None], t(gy)[None], lights.to_torch("cpu")))[0], 0, -1)
    bufs.clear()
    perturbed = phong.phong_change(gx * np.float32(1.001), gy, lights, full, buffer).copy()
    # a few float32 steps of the largest change (OpenCV's pow against a float64 power rounded once)
    agree(ref, got, 64 * EPS * float(np.abs(ref).max()), perturbed, "phong")


# ---------------------------------------------------------------- the table's lookup

def _table_profile(name, width):
    from gelsim.sensor import load_profile

    return load_profile(name).with_resolution(width)


@pytest.mark.parametrize("name", ["vitac", "gelsight-mini"])         # the tile mosaic, the exact lookup
@pytest.mark.parametrize("width", [96, 200])
def test_table_lookup(rng, name, width):
    from gelsim.optics.lut import table_model

    prof = _table_profile(name, width)
    model = table_model(prof)
    lut = model.lookup
    assert lut.exact == (name == "gelsight-mini")
    mm = prof.image.mm_per_px
    d = imprint(rng, prof.shape, mm)
    h, w = prof.shape
    bufs = {}

    def buffer(name_, shape):
        if name_ not in bufs or bufs[name_].shape != shape:
            bufs[name_] = np.empty(shape, np.float32)
        return bufs[name_]

    def numpy_lookup(depth):
        out = np.empty((h, w, 3), np.float32)
        full = (slice(0, h), slice(0, w))
        table.lookup_rows(depth, 0, h, lut.offx, lut.offy, out, lut, mm, buffer, lut.band_weights(full, 0, h))
        return out

    ref = numpy_lookup(d)
    got = np.moveaxis(n(table.lookup_torch(t(d)[None], table.lookup_to_torch(lut, "cpu"), mm))[0], 0, -1)
    # The bin coordinates (up to the mosaic's width) are computed in another order: a couple of float32
    # steps of their size, times the table's steepest step between bins, plus a few steps of its values.
    # The exact form's remap rounds them to 1/32 of a bin (OpenCV's fixed point, copied by the torch
    # kernel): where a coordinate lies on a rounding boundary the two may round apart, at rare pixels,
    # by 1/32 of a step in each of the three basis terms.
    tab = model.table.reshape(model.table.shape[0], model.table.shape[1], 3, 3)
    step = max(float(np.abs(np.diff(tab, axis=0)).max()), float(np.abs(np.diff(tab, axis=1)).max()))
    tol = 2 * EPS * float(lut.offx.max() + lut.offy.max()) * step + 16 * EPS * float(np.abs(model.table).max())

    def outside(a) -> float:
        e = np.abs(a - got)
        return float((e > tol).mean()) if (not lut.exact or e.max() <= 3 * step / 32 + tol) else 1.0

    assert outside(ref) <= (1e-3 if lut.exact else 0.0), \
        f"table lookup {name}: {outside(ref):.2%} of the pixels differ by more than {tol:.3g} (GELSIM_OPS_SEED={SEED})"
    assert outside(numpy_lookup(d * np.float32(1.001))) > 1e-3                 # a slope 0.1% off is seen


# ---------------------------------------------------------------- shadows

def _shadow_spec(width):
    from gelsim.optics.lut import table_model

    prof = _table_profile("vitac", width)
    return prof, table_model(prof).shadows


def test_occlusion(rng):
    seen = 0
    for shape in SHAPES * 2:
        hg = field(rng, shape, 0.0, float(rng.uniform(0.05, 0.6)), smooth=2.0)
        hg[hg < np.quantile(hg, 0.3)] = 0.0
        phi, rise = float(rng.uniform(-180, 180)), float(rng.uniform(0.002, 0.05))
        ref = shadows.occlusion_grid(hg, phi, rise)
        span = float(hg.max()) - min(float(hg.min()), 0.0)
        got = n(shadows.occlusion_torch(t(hg)[None], phi, rise, span))[0]
        seen += ref.max() > 0
        # mm: a few float32 steps of the heights (bilinear shifts, OpenCV's fused addWeighted)
        agree(ref, got, 16 * EPS * float(hg.max()),
              shadows.occlusion_grid(hg, phi, rise * 1.01) if ref.max() > 0 else None, "occlusion")
    assert seen >= 2                                                # most of these fields occlude


@pytest.mark.parametrize("width", [96, 200, 960])                  # grids of 1 x 1 and 4 x 4 pixels
def test_shadow_grid(rng, width):
    prof, spec = _shadow_spec(width)
    mm = prof.image.mm_per_px
    assert spec.grid_factor(mm) == (4 if width == 960 else 1)
    d = imprint(rng, prof.shape, mm)
    blur = float(rng.uniform(0.0, 1.5))
    ref = shadows.shadow_grid(d, spec, mm, blur)
    got = np.moveaxis(n(shadows.shadow_grid_torch(t(d)[None], spec, mm, blur))[0], 0, -1)
    ref = np.zeros_like(got) if ref is None else ref[0]
    scale = float(np.abs(spec.mix).max())                       # DN of full darkness
    perturbed = shadows.shadow_grid(d, dataclasses.replace(spec, sat_mm=spec.sat_mm * 1.01), mm, blur)
    perturbed = np.zeros_like(got) if perturbed is None else perturbed[0]
    assert np.abs(ref).max() > 0.1 * scale                          # shadows are cast
    agree(ref, got, 64 * EPS * scale, perturbed, "shadows")


# ---------------------------------------------------------------- depth and halo terms

@pytest.mark.parametrize("width", [96, 320])
def test_coarse_terms(rng, width):
    from gelsim.optics.lut import table_model

    prof = _table_profile("vitac", width)
    spec = table_model(prof).coarse
    mm = prof.image.mm_per_px
    d = imprint(rng, prof.shape, mm)
    ref, _ = coarse.coarse_small(d, spec, mm, prof.field_mm)
    if np.abs(ref).max() < coarse.COARSE_SKIP_DN:
        ref = np.zeros_like(ref)                                # skipped, as the numpy renderer skips it
    got = np.moveaxis(n(coarse.coarse_small_torch(t(d)[None], spec, mm, prof.field_mm))[0], 0, -1)
    perturbed, _ = coarse.coarse_small(d * np.float32(1.001), spec, mm, prof.field_mm)
    # DN: float32 steps of the largest feature times its colour, summed over the features
    scale = float(np.abs(spec.rgb).sum(axis=0).max()) * max(float(d.max()), 1.0)
    agree(ref, got, 16 * EPS * scale, perturbed if np.abs(ref).max() > 0 else None, "depth and halo terms")


# ---------------------------------------------------------------- markers

def _quads(rng, n_, shape, size):
    """``n_`` random convex quadrilaterals (sheared, turned squares), some beyond the frame: (N, 4, 2) px."""
    h, w = shape
    c = np.stack([rng.uniform(-size, w + size, n_), rng.uniform(-size, h + size, n_)], axis=1)
    ang = rng.uniform(0, np.pi / 2, n_)
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64) * size / 2
    rot = np.stack([np.stack([np.cos(ang), -np.sin(ang)], -1), np.stack([np.sin(ang), np.cos(ang)], -1)], -2)
    quads = c[:, None] + np.einsum("nij,kj->nki", rot, sq) + rng.normal(0, 0.15 * size, (n_, 4, 2))
    return quads.astype(np.float32)


@pytest.mark.parametrize("shape", SHAPES)
def test_marker_factors(rng, shape):
    darkness, sigma = float(rng.uniform(0.3, 0.9)), float(rng.choice([0.0, 0.6, 1.7]))
    corners = _quads(rng, int(rng.integers(1, 12)), shape, float(rng.uniform(2.0, 6.0)))

    def numpy_factor(c):
        frame = np.ones(shape + (1,), np.float32)
        markers.apply_marker_factors(frame, markers.marker_factors(c, darkness, sigma, frame.shape))
        return frame[..., 0]

    ref = numpy_factor(corners)
    got = n(markers.marker_factor_torch(t(corners)[None], shape, darkness, sigma))[0]
    # products of a few factors in 0-1, each a blurred coverage: float32 steps of 1
    agree(ref, got, 64 * EPS, numpy_factor(corners + np.float32(0.01)) if ref.min() < 1 else None, "markers")


# ---------------------------------------------------------------- readout

@pytest.mark.parametrize("shot_gain", [0.0, 0.05])
def test_readout(rng, shot_gain):
    for h, w in SHAPES:
        bank = readout.NoiseBank((h, w), float(rng.uniform(0.5, 3.0)), shot_gain, int(rng.integers(1 << 30)))
        frame = field(rng, (h, w, 3), -20.0, 280.0, smooth=0)
        frame[::3] = np.floor(frame[::3]) + np.float32(0.5)              # exact ties
        offsets = [bank.offsets(int(rng.integers(1 << 30))), None]
        noisy = np.empty((h, w, 3), np.uint8)
        bank.apply_rows(frame, offsets[0], noisy, 0)
        ref = [noisy, readout.to_uint8(frame)]
        frames = t(np.stack([frame, frame]).transpose(0, 3, 1, 2))
        got = readout.readout_torch(frames, bank.to_torch("cpu"), bank, offsets).numpy()
        for i in range(2):
            diff = np.abs(ref[i].astype(int) - got[i].astype(int))
            # the same float32 sums (a fused multiply-add in the shot noise's variance: one step more
            # moves a pixel across a rounding tie, rarely)
            assert diff.max() <= (1 if shot_gain and i == 0 else 0) and (diff > 0).mean() < 1e-3, \
                f"readout: {diff.max()} DN at {(diff > 0).mean():.2%} (GELSIM_OPS_SEED={SEED})"
        other = bank.offsets(int(rng.integers(1 << 30)))
        moved = readout.readout_torch(frames[:1], bank.to_torch("cpu"), bank, [other]).numpy()[0]
        assert other == offsets[0] or (moved != ref[0]).mean() > 0.1       # the field's draw is seen
