"""gelsim.bench.levels and .shortcuts: the level table and the shortcut study."""
from __future__ import annotations

import pytest

from gelsim import bench
from gelsim.bench import BenchConfig

KEYS = {"name", "ms_per_frame", "cpu_ms_per_frame", "stages_ms", "image_l1", "psnr", "ssim", "marker_err_mm",
        "marker_err_contact_mm", "force_err_n", "contact_area_err", "kept_relief", "kept_relief_min",
        "kept_relief_max", "image_texture", "image_texture_min", "image_texture_max", "texture_err",
        "image_texture_err", "image_texture_fast", "image_texture_fast_err", "per_scene", "cached_scenes"}


def test_run_bench_levels(tiny_result):
    levels = {lv["name"]: lv for lv in tiny_result["levels"]}
    assert list(levels) == ["fast", "balanced"]
    for lv in levels.values():
        assert KEYS <= set(lv)
        assert set(lv["stages_ms"]) == set(bench.TIMED_STAGES)
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
