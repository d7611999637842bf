"""Tests of the fabric catalog and heightfields (gelsim.fabrics)."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.fabrics import CATALOG_DIR, FAMILY_KEYS, Catalog, Fabric, heightfield, load_catalog, parse_catalog
from gelsim.fabrics.noise import hash_u32, value_noise

CAT = load_catalog()
ONE_PER_FAMILY = {}
for _f in CAT:
    ONE_PER_FAMILY.setdefault(_f.family, _f)
# Families whose structure itself is random (not only yarn jitter).
RANDOM_FAMILIES = ("felt", "fleece", "velvet", "leather", "suede", "terry", "lace")


# ----------------------------------------------------------------------------- catalog

def test_catalog_has_100_fabrics_in_id_order():
    assert len(CAT) == 100
    assert CAT.ids == list(range(1, 101))
    assert [f.id for f in CAT] == CAT.ids
    assert CAT[37].id == 37 and isinstance(CAT[37], Fabric)
    assert len({f.name for f in CAT}) == 100
    assert re.fullmatch(r"[0-9a-f]{12}", CAT.version)


def test_catalog_covers_every_family_several_times_except_rare_ones():
    counts = {}
    for f in CAT:
        counts[f.family] = counts.get(f.family, 0) + 1
    assert set(counts) == set(FAMILY_KEYS)
    # The families the issue names must each have several members (hard to tell apart).
    for fam in ("plain", "twill", "satin", "jersey", "rib", "corduroy", "velvet", "felt", "fleece", "leather",
                "terry", "mesh", "lace"):
        assert counts[fam] >= 3, fam
    materials = {f.material for f in CAT}
    for m in ("cotton", "linen", "ramie", "wool", "silk", "polyester", "nylon", "cowhide"):
        assert m in materials


def test_catalog_physical_ranges():
    for f in CAT:
        assert 0.4 <= f.friction <= 1.0
        assert 0.05 <= f.thickness_mm <= 6.0
        assert f.relief_mm <= f.thickness_mm
        assert 0.0 <= f.compressibility <= 0.9
        assert 0.01 <= f.surface_modulus_mpa <= 1000.0
        assert 0.02 < f.texture_mm <= 20.0


def test_unknown_id_message():
    with pytest.raises(GelsimError, match=r"^unknown fabric id 101; ids run 1-100$"):
        CAT[101]
    with pytest.raises(GelsimError, match="unknown fabric id 0"):
        CAT[0]


def test_load_catalog_is_cached_and_version_tracks_content(tmp_path):
    assert load_catalog() is load_catalog()
    d = tmp_path / "cat"
    shutil.copytree(CATALOG_DIR, d)
    a = load_catalog(d)
    assert a.version == CAT.version          # same content, same version
    f = d / "woven.toml"
    f.write_text(f.read_text().replace('name = "cotton poplin"', 'name = "cotton poplin B"'))
    b = load_catalog(d)
    assert b is not a and b.version != a.version and b[1].name == "cotton poplin B"


# ----------------------------------------------------------------------------- validation

ENTRY = """
[[fabric]]
id = {id}
name = "{name}"
family = "plain"
material = "cotton"
friction = 0.6
thickness_mm = 0.2
compressibility = 0.3
surface_modulus_mpa = 2.0
relief_mm = 0.04
warp_pitch_mm = 0.2
weft_pitch_mm = 0.2
warp_width_mm = 0.18
weft_width_mm = 0.18
crimp = 0.5
"""


def _write(tmp_path: Path, text: str, name: str = "cat.toml") -> Path:
    d = tmp_path / "cat"
    d.mkdir(exist_ok=True)
    (d / name).write_text(text)
    return d


def _good(n: int = 2) -> str:
    return "".join(ENTRY.format(id=i, name=f"fabric {i}") for i in range(1, n + 1))


def test_small_valid_catalog_loads(tmp_path):
    cat = parse_catalog(_write(tmp_path, _good(3)))
    assert isinstance(cat, Catalog) and len(cat) == 3 and cat[2].name == "fabric 2"


@pytest.mark.parametrize("mutate, pattern", [
    (lambda t: t.replace("crimp = 0.5", "crimp = 0.5\ncrimpp = 0.3", 1),
     r"cat\.toml: fabric #1 \(id 1\): unknown key 'crimpp'; known keys are"),
    (lambda t: t.replace("friction = 0.6\n", "", 1), r"fabric #1 \(id 1\)\.friction: missing; add it"),
    (lambda t: t.replace("friction = 0.6", "friction = 1.5", 1), r"fabric #1 \(id 1\)\.friction: 1\.5 is out of range"),
    (lambda t: t.replace("relief_mm = 0.04", "relief_mm = \"deep\"", 1), r"relief_mm: expected a number"),
    (lambda t: t.replace("relief_mm = 0.04", "relief_mm = nan", 1), r"relief_mm: nan is not a finite number"),
    (lambda t: t.replace('family = "plain"', 'family = "tartan"', 1), r"\.family: unknown family 'tartan'; use one of"),
    (lambda t: t.replace("crimp = 0.5\n", "", 1), r"\.crimp: missing; family 'plain' needs"),
    (lambda t: t.replace("crimp = 0.5", "crimp = 0.5\nfeature_mm = 0.3", 1),
     r"\.feature_mm: not used by family 'plain'; remove it"),
    (lambda t: t.replace("relief_mm = 0.04", "relief_mm = 0.5", 1), r"relief_mm: 0\.5 exceeds thickness_mm"),
    (lambda t: t.replace("id = 2", "id = 1", 1), r"fabric #2 \(id 1\): duplicate id 1 \(also cat\.toml: fabric #1"),
    (lambda t: t.replace("id = 2", "id = 3", 1), r"ids must run 1\.\.2 without gaps; id 2 is missing"),
    (lambda t: t.replace('name = "fabric 2"', 'name = "fabric 1"', 1), r"duplicate name 'fabric 1'"),
    (lambda t: t + "\n[[fabric]\n", r"cat\.toml: malformed TOML"),
    (lambda t: "version = 3\n" + t, r"unknown top-level key 'version'"),
])
def test_validation_errors_name_file_entry_and_fix(tmp_path, mutate, pattern):
    d = _write(tmp_path, mutate(_good(2)))
    with pytest.raises(GelsimError, match=pattern):
        parse_catalog(d)


def test_duplicate_id_across_files_names_both(tmp_path):
    d = _write(tmp_path, _good(2), "a.toml")
    (d / "b.toml").write_text(ENTRY.format(id=2, name="other"))
    with pytest.raises(GelsimError, match=r"b\.toml: fabric #1 \(id 2\): duplicate id 2 \(also a\.toml: fabric #2"):
        parse_catalog(d)


def test_missing_or_empty_catalog(tmp_path):
    with pytest.raises(GelsimError, match="not found"):
        parse_catalog(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(GelsimError, match="no .toml files"):
        parse_catalog(tmp_path / "empty")


def test_bad_satin_step_rejected(tmp_path):
    t = _good(1).replace('family = "plain"', 'family = "satin"').replace("crimp = 0.5", "crimp = 0.5\n"
                                                                         "satin_harness = 6\nsatin_step = 3")
    with pytest.raises(GelsimError, match="satin_step: 3 does not make a satin"):
        parse_catalog(_write(tmp_path, t))


# ----------------------------------------------------------------------------- noise

def test_hash_is_deterministic_and_spread():
    ix = np.arange(-500, 500)
    a = hash_u32(ix[None, :], ix[:, None], 7)
    assert np.array_equal(a, hash_u32(ix[None, :], ix[:, None], 7))
    assert not np.array_equal(a, hash_u32(ix[None, :], ix[:, None], 8))
    assert not np.array_equal(a, a.T)                     # (x, y) and (y, x) differ
    bits = ((a[..., None] >> np.arange(32, dtype=np.uint32)) & 1).mean(axis=(0, 1))
    assert np.all(np.abs(bits - 0.5) < 0.01)              # every bit is a fair coin


def test_value_noise_range_and_smoothness():
    u = np.arange(400) * 0.01
    n = value_noise(u, u, 0.5, 0.5, 3)
    assert n.dtype == np.float32 and n.shape == (400, 400)
    assert n.min() >= -1 and n.max() <= 1 and n.std() > 0.1
    # smooth: neighbouring pixels (1/50 of a cell apart) differ by a small fraction of the range
    assert np.abs(np.diff(n, axis=1)).max() < 0.1


# ----------------------------------------------------------------------------- heightfields

@pytest.mark.parametrize("family", sorted(FAMILY_KEYS))
def test_heightfield_shape_range_and_relief(family):
    f = ONE_PER_FAMILY[family]
    mpp = 0.02
    scale = max(f.warp_pitch_mm or 0.0, f.feature_mm or 0.0, f.motif_mm or 0.0)
    n = max(96, int(round(3 * scale / mpp)))
    h = heightfield(f, x0_mm=-1.0, y0_mm=2.0, width_px=n, height_px=n // 2 + 1, mm_per_px=mpp, seed=1)
    assert h.dtype == np.float32 and h.shape == (n // 2 + 1, n)
    assert np.isfinite(h).all()
    assert h.min() >= 0.0
    assert h.max() <= f.relief_mm * 1.0001
    assert h.max() >= 0.5 * f.relief_mm                  # the peak is about the relief
    assert h.std() > 0.03 * f.relief_mm                  # there is texture


@pytest.mark.parametrize("family", sorted(FAMILY_KEYS))
def test_heightfield_is_deterministic(family):
    f = ONE_PER_FAMILY[family]
    kw = dict(x0_mm=0.3, y0_mm=-0.7, width_px=64, height_px=48, mm_per_px=0.03, rotation_deg=17.0)
    a = heightfield(f, seed=5, **kw)
    assert np.array_equal(a, heightfield(f, seed=5, **kw))
    if family in RANDOM_FAMILIES:
        b = heightfield(f, seed=6, **kw)
        assert np.abs(a - b).mean() > 0.02 * f.relief_mm


@pytest.mark.parametrize("family", sorted(FAMILY_KEYS))
@pytest.mark.parametrize("rotation", [0.0, 33.0])
def test_adjacent_regions_join_seamlessly(family, rotation):
    f = ONE_PER_FAMILY[family]
    mpp, x0, y0 = 0.02, -0.4, 0.3
    kw = dict(mm_per_px=mpp, seed=3, rotation_deg=rotation)
    big = heightfield(f, x0_mm=x0, y0_mm=y0, width_px=80, height_px=60, **kw)
    left = heightfield(f, x0_mm=x0, y0_mm=y0, width_px=40, height_px=60, **kw)
    right = heightfield(f, x0_mm=x0 + 40 * mpp, y0_mm=y0, width_px=40, height_px=60, **kw)
    bottom = heightfield(f, x0_mm=x0, y0_mm=y0 + 30 * mpp, width_px=80, height_px=30, **kw)
    if rotation == 0.0:   # axis-aligned: bit-identical
        assert np.array_equal(big[:, :40], left)
        assert np.array_equal(big[:, 40:], right)
        assert np.array_equal(big[30:], bottom)
    else:                 # resampled: equal to float32 rounding of the sampling coordinates
        tol = 1e-5 * f.relief_mm
        np.testing.assert_allclose(big[:, :40], left, rtol=0, atol=tol)
        np.testing.assert_allclose(big[:, 40:], right, rtol=0, atol=tol)
        np.testing.assert_allclose(big[30:], bottom, rtol=0, atol=tol)


def _period_px(profile: np.ndarray, lo: float, hi: float) -> float:
    """Period (px) of the strongest spectral peak with period in [lo, hi] px, refined by a parabola."""
    p = profile - profile.mean()
    spec = np.abs(np.fft.rfft(p * np.hanning(len(p)))) ** 2
    k = np.arange(len(spec))
    with np.errstate(divide="ignore"):
        period = len(p) / k
    ok = (period >= lo) & (period <= hi)
    i = int(k[ok][np.argmax(spec[ok])])
    a, b, c = np.log(spec[i - 1:i + 2])
    di = 0.5 * (a - c) / (a - 2 * b + c)
    return len(p) / (i + di)


@pytest.mark.parametrize("fid", [f.id for f in CAT if f.family == "plain"][:8])
def test_plain_weave_pitch_matches_catalog(fid):
    f = CAT[fid]
    mpp = 0.01
    n = 2048
    h = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=n, height_px=256, mm_per_px=mpp, seed=0)
    warp_px = f.warp_pitch_mm / mpp
    # Averaged over rows, the surface is the sequence of warp yarn profiles: period = warp pitch.
    got = _period_px(h.mean(axis=0), 0.6 * warp_px, 1.6 * warp_px)
    assert abs(got - warp_px) < 1.0, (got, warp_px)
    v = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=256, height_px=n, mm_per_px=mpp, seed=0)
    weft_px = f.weft_pitch_mm / mpp
    got = _period_px(v.mean(axis=1), 0.6 * weft_px, 1.6 * weft_px)
    assert abs(got - weft_px) < 1.0, (got, weft_px)


def test_rotation_turns_the_pattern():
    f = next(f for f in CAT if f.family == "corduroy")   # ridges run along v
    kw = dict(x0_mm=0.0, y0_mm=0.0, width_px=300, height_px=300, mm_per_px=0.02, seed=0)
    h0 = heightfield(f, **kw)
    h90 = heightfield(f, rotation_deg=90.0, **kw)
    # Unrotated, height varies across columns (u) and little along a column; rotated 90, the reverse.
    assert h0.mean(axis=0).std() > 4 * h0.mean(axis=1).std()
    assert h90.mean(axis=1).std() > 4 * h90.mean(axis=0).std()


def test_rotation_90_matches_coordinate_convention():
    f = next(f for f in CAT if f.family == "twill")
    mpp, n = 0.02, 64
    h90 = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=n, height_px=n, mm_per_px=mpp, seed=0, rotation_deg=90.0)
    # (u, v) = (x cos t + y sin t, -x sin t + y cos t) = (y, -x) at t = 90: row i of the rotated patch is
    # column u = i*mpp of the fabric, and its column j is v = -j*mpp.
    ref = heightfield(f, x0_mm=0.0, y0_mm=-(n - 1) * mpp, width_px=n, height_px=n, mm_per_px=mpp, seed=0)
    expect = ref[::-1, :].T       # expect[i, j] = ref at u = i*mpp, v = -j*mpp
    np.testing.assert_allclose(h90, expect, rtol=0, atol=1e-4 * f.relief_mm)


@pytest.mark.parametrize("kw, msg", [
    (dict(width_px=0, height_px=10, mm_per_px=0.01), "out of range"),
    (dict(width_px=10, height_px=10, mm_per_px=0.0), "must be a positive number"),
    (dict(width_px=10, height_px=10, mm_per_px=-1.0), "must be a positive number"),
    (dict(width_px=10.5, height_px=10, mm_per_px=0.01), "must be integers"),
])
def test_heightfield_bad_input(kw, msg):
    with pytest.raises(GelsimError, match=msg):
        heightfield(CAT[1], x0_mm=0.0, y0_mm=0.0, **kw)


# ----------------------------------------------------------------------------- distinctness

def _spectral_descriptor(f: Fabric, seed: int) -> np.ndarray:
    """Log power spectrum (Welch, 2x2 windows of 256 px at 0.03 mm/px = 7.7 mm, Hann), 8x8-bin averaged.

    It keeps what a tactile sensor sees of a texture (scales, orientations, amplitude) and averages out
    the phase, i.e. the particular random draw."""
    n, q, b = 256, 2, 8
    h = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=n * q, height_px=n * q, mm_per_px=0.03, seed=seed)
    win = np.outer(np.hanning(n), np.hanning(n)).astype(np.float32)
    acc = np.zeros((n, n))
    for a in range(q):
        for c in range(q):
            t = h[a * n:(a + 1) * n, c * n:(c + 1) * n]
            acc += np.abs(np.fft.fft2((t - t.mean()) * win)) ** 2
    acc = np.fft.fftshift(acc).reshape(n // b, b, n // b, b).mean(axis=(1, 3))
    return np.log10(acc + 1e-14).ravel()


def test_all_fabrics_pairwise_distinct():
    """Every pair of fabrics differs more than either fabric differs from itself under a new seed.

    Threshold: for fabrics i, j the RMS distance between their descriptors (decades of spectral
    power) must exceed max(d_i, d_j), where d_i is the distance between fabric i's descriptors for
    seeds 0 and 1, so two fabrics are never closer than two samples of the same fabric."""
    d0 = np.array([_spectral_descriptor(f, 0) for f in CAT])
    d1 = np.array([_spectral_descriptor(f, 1) for f in CAT])
    intra = np.sqrt(((d0 - d1) ** 2).mean(axis=1))
    inter = np.sqrt(((d0[:, None] - d0[None]) ** 2).mean(axis=2))
    np.fill_diagonal(inter, np.inf)
    ratio = inter / np.maximum(np.maximum(intra[:, None], intra[None, :]), 1e-9)
    i, j = np.unravel_index(np.argmin(ratio), ratio.shape)
    assert ratio[i, j] > 1.0, (CAT[i + 1].name, CAT[j + 1].name, inter[i, j], intra[i], intra[j])
    # and the seed-to-seed distance is not zero for the random families (the test could fail)
    assert all(intra[f.id - 1] > 0 for f in CAT if f.family in RANDOM_FAMILIES)


def test_coarse_resolution_is_antialiased_and_still_seamless():
    f = CAT.by_name("silk habotai")                # 0.10 x 0.11 mm pitch, no fuzz
    mpp = 0.2                                      # the physics' resolution: two yarns per pixel
    kw = dict(mm_per_px=mpp, seed=2, rotation_deg=25.0)
    h = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=60, height_px=40, **kw)
    naive = heightfield(f, x0_mm=0.0, y0_mm=0.0, width_px=60, height_px=40, _antialias=False, **kw)
    # Point sampling aliases the weave into a false pattern with the full yarn relief; averaging over
    # the pixel leaves little of a structure two yarns per pixel fine.
    assert h.std() < 0.3 * naive.std()
    assert abs(float(h.mean()) - float(naive.mean())) < 0.2 * f.relief_mm
    right = heightfield(f, x0_mm=30 * mpp, y0_mm=0.0, width_px=30, height_px=40, **kw)
    np.testing.assert_allclose(h[:, 30:], right, rtol=0, atol=1e-5 * f.relief_mm)


def test_fitted_label_shrinks_to_its_width():
    from gelsim.fabrics.preview import put_fitted_label

    def ink_columns(width_px):
        img = np.full((24, 300, 3), 255, np.uint8)
        put_fitted_label(img, "47 wool jersey, a long name", (0, 18), width_px, 0.38)
        return np.flatnonzero((img < 128).any(axis=(0, 2)))

    free, tight = ink_columns(300), ink_columns(90)
    assert tight.size and tight.max() <= 90 < free.max()
