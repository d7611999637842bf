"""gelsim.bench.scenes: the bench's scenes and the validation of its settings."""
from __future__ import annotations

import pytest

from gelsim import bench
from gelsim.bench import BenchConfig
from gelsim.errors import GelsimError
from gelsim.sensor import load_profile


def test_scenes_and_sphere_heights(tiny):
    names = [s.name for s in bench.scenes_for(BenchConfig())]
    assert names[0] == "sphere-press" and len(names) == 1 + len(bench.DEFAULT_FABRICS) * 3
    assert len(set(names)) == len(names)
    profile = load_profile("vitac").with_resolution(96, 72)
    m = bench.scene_motion(bench.Scene("s", "sphere", "press", 3), tiny)
    assert m.start_xy_mm == (0.0, 0.0) and m.peak_force_n == bench.SPHERE_FORCE_N
    obj, surf = bench.prepare_scene(bench.Scene("s", "sphere", "press", 3), m, profile, catalog=None)
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
