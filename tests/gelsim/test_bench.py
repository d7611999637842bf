"""gelsim.bench and `gelsim bench`: metrics, scenes, the level table and its reports."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from gelsim import bench
from gelsim.bench import BenchConfig, ErrorAcc, psnr_from_mse, ssim
from gelsim.cli import main
from gelsim.errors import GelsimError
from gelsim.fidelity import get_fidelity
from gelsim.motion import sample_motion
from gelsim.sensor import load_profile

# A tiny bench: no pyrender (the reference is "balanced"), two scenes, 5 frames at 96x72; the coarse
# knit (0.8-1.1 mm loops, 4-6 px per period at 96x72) so that its texture is in the metric's band.
TINY = BenchConfig(resolution=(96, 72), frames=5, precontact=1, fabrics=(57,), actions=("press",),
                   levels=("fast", "balanced"), reference="balanced", shortcut_level="")
KEYS = {"name", "ms_per_frame", "cpu_ms_per_frame", "stages_ms", "image_l1", "psnr", "ssim", "marker_err_mm",
        "marker_err_contact_mm", "force_err_n", "contact_area_err", "kept_relief", "kept_relief_min",
        "kept_relief_max", "image_texture", "image_texture_min", "image_texture_max", "texture_err",
        "image_texture_err", "image_texture_fast", "image_texture_fast_err", "per_scene", "cached_scenes"}


def test_ssim_identical_and_degraded():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    assert ssim(a, a) == pytest.approx(1.0)
    noisy = np.clip(a + rng.normal(0, 20, a.shape), 0, 255).astype(np.uint8)
    worse = np.clip(a + rng.normal(0, 60, a.shape), 0, 255).astype(np.uint8)
    assert 1.0 > ssim(a, noisy) > ssim(a, worse) > 0.0
    with pytest.raises(GelsimError):
        ssim(a, a[:-1])


def test_psnr_and_error_pooling():
    assert psnr_from_mse(0.0) is None
    assert psnr_from_mse(1.0) == pytest.approx(20 * math.log10(255))
    acc = ErrorAcc()
    ref = np.full((4, 4, 3), 100, np.uint8)
    acc.add_frame(ref + 2, ref)
    acc.add_frame(ref, ref)
    acc.add_markers(np.array([[[3.0, 4.0]]]), np.zeros((1, 1, 2)), 0.5)
    acc.add_forces(np.array([1.0, 2.0]), np.array([1.5, 2.0]))
    s = acc.summary()
    assert s["image_l1"] == pytest.approx(1.0)                       # half the pixels off by 2 DN
    assert s["psnr"] == pytest.approx(10 * math.log10(255 ** 2 / 2.0), abs=1e-3)
    assert s["marker_err_mm"] == pytest.approx(2.5)                  # 5 px at 0.5 mm/px
    assert s["force_err_n"] == pytest.approx(0.25)


def test_texture_pooling_per_scene_then_over_scenes():
    acc = ErrorAcc()
    # scene a: gel relief 0.5 of the reference's in both frames, image texture 2x; scene b: 0.8 / 1
    # (through the fast shader: 0.25 in scene a, not measured in b)
    for _ in range(2):
        acc.add_texture("a", 0.01, 0.02, 4.0, 2.0, 1.0, 4.0)
    acc.add_texture("b", 0.008, 0.01, 3.0, 3.0)
    acc.add_texture("b", float("nan"), 0.01, 3.0, 3.0)        # no region: left out
    ratios = acc.texture_ratios()
    assert ratios["a"] == pytest.approx((0.5, 2.0, 0.25)) and ratios["b"][:2] == pytest.approx((0.8, 1.0))
    assert ratios["b"][2] is None
    s = acc.summary()
    assert s["kept_relief"] == pytest.approx(math.sqrt(0.5 * 0.8), abs=1e-4)   # geometric mean
    assert (s["kept_relief_min"], s["kept_relief_max"]) == (0.5, 0.8)
    assert s["image_texture"] == pytest.approx(math.sqrt(2.0), abs=1e-4)
    assert s["texture_err"] == pytest.approx((0.5 + 0.2) / 2) and s["image_texture_err"] == pytest.approx(0.5)
    assert s["image_texture_fast"] == 0.25 and s["image_texture_fast_err"] == 0.75
    acc.add_area(12.0, 10.0)
    acc.add_area(8.0, 10.0)
    acc.add_area(5.0, 0.0)                                        # no reference contact: left out
    assert acc.summary()["contact_area_err"] == pytest.approx(0.2)
    empty = ErrorAcc().summary()
    assert empty["kept_relief"] is None and empty["texture_err"] is None and empty["contact_area_err"] is None


def test_scenes_and_sphere_heights():
    names = [s.name for s in bench.scenes_for(BenchConfig())]
    assert names[0] == "sphere-press" and len(names) == 1 + len(bench.DEFAULT_FABRICS) * 3
    assert len(set(names)) == len(names)
    profile = load_profile("vitac").with_resolution(96, 72)
    m = bench.scene_motion(bench.Scene("s", "sphere", "press", 3), TINY)
    assert m.start_xy_mm == (0.0, 0.0) and m.peak_force_n == bench.SPHERE_FORCE_N
    obj, surf = bench._prepare(bench.Scene("s", "sphere", "press", 3), m, profile, catalog=None)
    assert obj.diameter_mm == bench.SPHERE_DIAMETER_MM and surf.friction == bench.SPHERE_FRICTION
    assert surf.heights_mm.max() == pytest.approx(bench.SPHERE_DIAMETER_MM / 2, abs=0.05)


def test_config_validation():
    with pytest.raises(GelsimError, match="frames"):
        BenchConfig(frames=3, precontact=2).validate()
    with pytest.raises(GelsimError, match="unknown action"):
        BenchConfig(actions=("poke",)).validate()
    with pytest.raises(GelsimError, match="unknown fidelity"):
        BenchConfig(levels=("ultra",)).validate()
    with pytest.raises(GelsimError, match="no scenes"):
        BenchConfig(sphere=False, fabrics=()).validate()


@pytest.fixture(scope="module")
def tiny_result():
    return bench.run_bench(TINY)


def test_run_bench_levels(tiny_result):
    levels = {lv["name"]: lv for lv in tiny_result["levels"]}
    assert list(levels) == ["fast", "balanced"]
    for lv in levels.values():
        assert KEYS <= set(lv)
        assert set(lv["stages_ms"]) == set(bench.STAGES)
        assert lv["ms_per_frame"] == pytest.approx(sum(lv["stages_ms"].values()), abs=0.05)
        assert lv["stages_ms"]["encode"] > 0 and lv["stages_ms"]["physics"] > 0 and lv["stages_ms"]["optics"] > 0
    ref = levels["balanced"]
    assert ref["image_l1"] == 0 and ref["psnr"] is None and ref["ssim"] == 1 and ref["marker_err_mm"] == 0
    assert ref["force_err_n"] == 0 and ref["contact_area_err"] == 0 and ref["marker_err_contact_mm"] == 0
    assert ref["kept_relief"] == 1 and ref["image_texture"] == 1 and ref["texture_err"] == 0
    fast = levels["fast"]  # half-resolution imprint and twice the timestep: measurably different
    assert fast["image_l1"] > 0 and fast["psnr"] > 20 and 0.5 < fast["ssim"] < 1
    assert fast["marker_err_mm"] > 0 and fast["force_err_n"] > 0 and fast["marker_err_contact_mm"] > 0
    # a half-resolution imprint of a 4-6 px texture keeps some of it, not all and not none
    assert 0.2 < fast["kept_relief"] < 0.98 and 0.2 < fast["image_texture"] < 1.5
    assert fast["texture_err"] == pytest.approx(abs(1 - fast["kept_relief"]), abs=1e-3)   # one fabric scene
    assert 0 < fast["contact_area_err"] < 1
    assert fast["image_texture_fast"] == fast["image_texture"]   # both levels render with the fast shader
    assert tiny_result["settings"]["scenes"] == ["sphere-press", "fabric57-press"]
    sphere = next(p for p in fast["per_scene"] if p["scene"] == "sphere-press")
    assert sphere["kept_relief"] is None and sphere["contact_area_err"] > 0   # no texture on a ball


def test_measure_texture_is_linear_in_the_gel_relief():
    """A run whose gel relief is half the yardstick's keeps 0.5 of it, exactly; its image texture
    falls too (the shading is not linear in the slopes, so not exactly by half)."""
    from gelsim.fabrics import load_catalog

    profile = load_profile("vitac").with_resolution(160, 120)
    catalog = load_catalog()
    sc = bench.Scene("k", 57, "press", 0)
    cfg = dataclasses.replace(TINY, resolution=(160, 120))
    motion = bench.scene_motion(sc, cfg)
    fid = get_fidelity("balanced")
    renderer = bench._make_renderer(profile, fid, 0)
    run = bench.run_level(sc, motion, profile, fid, catalog=catalog, renderer=renderer, encode=None,
                          keep_imprints=True)
    assert sorted(run.imprints) == list(np.flatnonzero(run.contact.in_contact & (run.contact.normal_force_n > 0)))
    yard = bench.measure_texture(run, catalog[57], profile, renderer)
    assert yard.region.shape == (len(yard.frames), 120, 160) and yard.region.any()
    assert np.isfinite(yard.gel_rms).all() and (yard.gel_rms > 0).all() and (yard.img_rms > 0).all()
    half = dataclasses.replace(run, imprints={i: (0.5 * d, m) for i, (d, m) in run.imprints.items()})
    t = bench.measure_texture(half, catalog[57], profile, renderer, yardstick=yard)
    np.testing.assert_allclose(t.gel_rms, 0.5 * yard.gel_rms, rtol=1e-5)
    assert (t.img_rms < 0.8 * yard.img_rms).all() and (t.img_rms > 0.2 * yard.img_rms).all()
    renderer.close()


def test_cache_returns_the_same_run_and_keys_on_what_matters(tmp_path):
    cfg = dataclasses.replace(TINY, sphere=False, cache_dir=str(tmp_path / "c"))
    first = bench.run_bench(cfg)
    files = sorted((tmp_path / "c").glob("*.npz"))
    assert len(files) == 1                                   # one reference scene
    again = bench.run_bench(cfg)
    a, b = ({lv["name"]: lv for lv in r["levels"]} for r in (first, again))
    assert b["balanced"]["cached_scenes"] == 1 and a["balanced"]["cached_scenes"] == 0
    for k in ("image_l1", "kept_relief", "image_texture", "contact_area_err", "marker_err_contact_mm"):
        assert b["fast"][k] == a["fast"][k], k
    cache = bench.RunCache(tmp_path / "c")
    profile = load_profile("vitac").with_resolution(96, 72)
    sc = bench.scenes_for(cfg)[0]
    bal = get_fidelity("balanced")
    k0 = cache.run_key(sc, cfg, profile, bal, None)
    assert k0 == files[0].stem
    assert cache.run_key(sc, cfg, profile, dataclasses.replace(bal, macro_cells=32), None) != k0
    assert cache.run_key(dataclasses.replace(sc, seed=9), cfg, profile, bal, None) != k0
    assert cache.run_key(sc, dataclasses.replace(cfg, frames=6), profile, bal, None) != k0
    assert bench.RunCache("").get_run(k0) is None
    # a cached run whose texture lacks a measure is measured again from its stored imprints
    with np.load(files[0]) as z:
        arrays = {k: z[k] for k in z.files if k != "tex_img_fast"}
    assert arrays["imp_depth"].shape[1:] == (72, 96)
    np.savez_compressed(files[0], **arrays)
    third = {lv["name"]: lv for lv in bench.run_bench(cfg)["levels"]}
    assert third["balanced"]["cached_scenes"] == 1 and third["fast"]["image_texture_fast"] == a["fast"]["image_texture_fast"]
    with np.load(files[0]) as z:
        assert "tex_img_fast" in z.files


def test_supersampling_changes_the_image_not_the_gel():
    """Through the fast shader at supersample 1 every supersampling value shows the same gel texture
    (ratio 1); through its own supersampled renderer the image's texture changes."""
    cfg = BenchConfig(resolution=(96, 72), frames=4, precontact=1, fabrics=(57,), actions=("press",), sphere=False)
    sw = bench.run_convergence(cfg, knobs=("supersample",))["sweeps"][0]
    pts = sw["points"]
    assert [p["value"] for p in pts] == [1, 2, 3, 4]
    assert all(p["image_texture_fast"] == 1 and p["kept_relief"] == 1 for p in pts)
    assert pts[0]["image_texture_err"] > 0 and pts[-1]["image_texture_err"] == 0


def test_reports(tiny_result, tmp_path):
    paths = bench.write_reports(tiny_result, tmp_path / "r")
    assert json.loads(paths["json"].read_text())["levels"][0]["name"] == "fast"
    md = paths["markdown"].read_text()
    assert "| fast |" in md and "| balanced |" in md and "96x72" in md
    fast = tiny_result["levels"][0]
    assert f"| fabric57-press | {fast['per_scene'][1]['kept_relief']:.2f} /" in md   # the per-scene texture table
    both = {"runs": [tiny_result, tiny_result]}
    paths = bench.write_reports(both, tmp_path / "two")
    assert paths["markdown"].read_text().count("### 96x72") == 2
    png = paths["plot"].read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    (tmp_path / "file").write_text("x")
    with pytest.raises(GelsimError, match="is a file"):
        bench.write_reports(tiny_result, tmp_path / "file")


def test_shortcut_study_rows():
    cfg = BenchConfig(resolution=(96, 72), frames=5, precontact=2, fabrics=(), sphere=True, levels=("balanced",),
                      reference="balanced", shortcut_level="balanced")
    res = bench.run_bench(cfg)
    rows = {r["variant"]: r for r in res["shortcuts"]}
    assert set(rows) == {"all shortcuts", "no shortcuts", "labels only"}
    # at this coarse grid the pyramid's touched window is up to 3% off the full frame's (gel.py; see
    # test_shortcuts.test_pyramid_touched_window_equals_full): a few DN on the sphere's rim
    assert rows["no shortcuts"]["max_abs_dn"] <= 4 and rows["no shortcuts"]["max_marker_px"] < 0.05
    assert rows["labels only"]["stages_ms"]["optics"] == 0 and rows["labels only"]["stages_ms"]["imprint"] == 0
    assert rows["all shortcuts"]["stages_ms"]["imprint"] > 0


def test_convergence_supersample_error_falls(tmp_path):
    cfg = BenchConfig(resolution=(96, 72), frames=5, precontact=1, fabrics=(), sphere=True)
    res = bench.run_convergence(cfg, knobs=("supersample", "physics_dt_s"))
    sweeps = {s["knob"]: s for s in res["sweeps"]}
    ss = [p["image_l1"] for p in sweeps["supersample"]["points"]]
    assert ss[-1] == 0 and ss[0] > ss[1] > ss[2] > 0
    dt = [p["force_err_n"] for p in sweeps["physics_dt_s"]["points"]]
    assert dt[-1] == 0 and dt[0] > dt[-2]
    paths = bench.write_convergence(res, tmp_path)
    assert paths["plot"].stat().st_size > 5000 and "supersample" in paths["markdown"].read_text()


def test_convergence_imprint_model_pyramid_loses_texture():
    """The imprint-model sweep on a plain weave resolved as a 0.2 mm weave is at 960x720 (cotton
    canvas, 0.5-0.55 mm pitch, 4-5 px per period at 160x120): the elastic reference is its own
    yardstick, the two-scale model keeps the weave's relief and the pyramid loses much of it (its
    contact stays at a quarter of a wave whatever the force); errors are reported per fabric scene."""
    cfg = BenchConfig(resolution=(160, 120), frames=4, precontact=1, fabrics=(5,), actions=("press",), sphere=False)
    sw = bench.run_convergence(cfg, knobs=("imprint_model",))["sweeps"][0]
    pts = {p["value"]: p for p in sw["points"]}
    assert list(pts) == ["pyramid", "twoscale", "elastic"] and sw["metric"] == "texture_err"
    assert pts["elastic"]["kept_relief"] == 1 and pts["elastic"]["texture_err"] == 0
    assert pts["pyramid"]["kept_relief"] < 0.8 and abs(pts["twoscale"]["kept_relief"] - 1) < 0.2
    assert pts["pyramid"]["texture_err"] > 2 * pts["twoscale"]["texture_err"] > 0
    assert set(pts["pyramid"]["per_scene"]) == {"fabric5-press"}
    # The reference solves every pixel: it stays several times the two-scale model's cost (about 9.5x here
    # since the layer's convolutions moved to OpenCV's DFT, which both models use; 3x leaves room for load).
    assert pts["elastic"]["stage_ms"] > 3 * pts["twoscale"]["stage_ms"]


def test_cli_json(tmp_path, capsys):
    rc = main(["bench", "--json", "--resolution", "64x48,80x60", "--frames", "4", "--precontact", "1", "--fabrics",
               "", "--levels", "fast", "--reference", "balanced", "--no-shortcut-study", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["settings"]["resolution"] for r in doc["runs"]] == [[64, 48], [80, 60]]
    for r in doc["runs"]:
        assert [lv["name"] for lv in r["levels"]] == ["fast", "balanced"]
        assert KEYS <= set(r["levels"][0])
        assert r["levels"][0]["kept_relief"] is None          # the sphere alone: no texture
    assert (tmp_path / "bench.md").exists() and (tmp_path / "bench_pareto.png").exists()
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2  # the reference's sphere, at each size


def test_cli_quick(tmp_path, capsys):
    rc = main(["bench", "--quick", "--json", "--levels", "fast", "--reference", "balanced", "--no-cache",
               "--out", str(tmp_path)])
    assert rc == 0
    (run,) = json.loads(capsys.readouterr().out)["runs"]
    assert run["settings"]["resolution"] == list(bench.QUICK["resolution"])
    assert run["settings"]["scenes"] == ["fabric50-press", "fabric50-slip"] and "shortcuts" not in run
    fast = run["levels"][0]
    assert 0 < fast["kept_relief"] < 1 and fast["contact_area_err"] > 0 and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("argv, msg", [
    (["--frames", "3", "--precontact", "2"], "frames"),
    (["--fabrics", "1,x"], "--fabrics"),
    (["--fabrics", "999"], "unknown fabric"),
    (["--resolution", "10x10"], "too small"),
    (["--convergence", "--knobs", "colour"], "--knobs"),
    (["--resolution", ","], "--resolution"),
    (["--quick", "--levels", "ultra"], "unknown fidelity"),
])
def test_cli_bad_input(argv, msg, capsys, tmp_path):
    assert main(["bench", "--out", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gelsim: error:") and msg in err and err.count("\n") == 1


@pytest.mark.gl
def test_reference_level_with_pyrender():
    from gelsim.optics import available_backends

    if "pyrender" not in available_backends():
        pytest.skip("no OpenGL context")
    cfg = BenchConfig(resolution=(64, 48), frames=4, precontact=1, fabrics=(), levels=("balanced",),
                      shortcut_level="")
    res = bench.run_bench(cfg)
    lv = {x["name"]: x for x in res["levels"]}
    assert lv["reference"]["image_l1"] == 0 and lv["balanced"]["image_l1"] > 0
    assert lv["reference"]["stages_ms"]["optics"] > lv["balanced"]["stages_ms"]["optics"]
