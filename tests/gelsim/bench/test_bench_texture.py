"""gelsim.bench.texture (and gelsim.bench.runs' imprint capture): the texture metric of a run."""
from __future__ import annotations

import dataclasses

import numpy as np

from gelsim import bench
from gelsim.fidelity import get_fidelity
from gelsim.sensor import load_profile


def test_measure_texture_is_linear_in_the_gel_relief(tiny):
    """A run whose gel relief is half the yardstick's keeps 0.5 of it, exactly; its image texture
    falls too (the shading is not linear in the slopes, so not exactly by half)."""
    from gelsim.fabrics import load_catalog

    profile = load_profile("vitac").with_resolution(160, 120)
    catalog = load_catalog()
    sc = bench.Scene("k", 57, "press", 0)
    cfg = dataclasses.replace(tiny, resolution=(160, 120))
    motion = bench.scene_motion(sc, cfg)
    fid = get_fidelity("balanced")
    renderer = bench.make_renderer(profile, fid, 0)
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
