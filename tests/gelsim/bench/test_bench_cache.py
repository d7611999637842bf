"""gelsim.bench.cache: the yardstick runs kept on disk."""
from __future__ import annotations

import dataclasses

import numpy as np

from gelsim import bench
from gelsim.fidelity import get_fidelity
from gelsim.sensor import load_profile


def test_cache_returns_the_same_run_and_keys_on_what_matters(tmp_path, tiny):
    cfg = dataclasses.replace(tiny, sphere=False, cache_dir=str(tmp_path / "c"))
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
