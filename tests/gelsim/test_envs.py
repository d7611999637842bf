"""gelsim.envs.GraspEnv: Gymnasium's checker, and a scripted grasp that lifts (#14).

Gymnasium is an optional extra (`make gym`); without it these tests skip."""
from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from gelsim.envs import GraspEnv  # noqa: E402
from gelsim.errors import GelsimError  # noqa: E402


def test_env_passes_gymnasiums_checker():
    env = GraspEnv(resolution=(32, 24), max_steps=5)
    check_env(env, skip_render_check=True)


def test_scripted_grasp_lifts_and_feels_the_object():
    env = GraspEnv(resolution=(32, 24), object="box_edge", max_steps=60)
    obs, info = env.reset(seed=1)
    assert info["object"] == "box_edge" and obs["tactile_left"].shape == (24, 32, 3)
    assert obs["state"][1] == 0.0 and obs["state"][2] == 0.0       # nothing touches yet
    untouched = obs["tactile_left"].copy()
    for _ in range(15):                                              # down to the grasp height
        obs, *_ = env.step(np.array([-1.0, -1.0], np.float32))
    for _ in range(12):                                              # close
        obs, *_ = env.step(np.array([0.0, 1.0], np.float32))
    assert obs["state"][1] > 1.0 and obs["state"][2] > 1.0          # both pads pressed
    assert np.abs(obs["tactile_left"].astype(int) - untouched).max() > 20
    done = False
    for _ in range(30):                                              # lift
        obs, reward, done, truncated, _ = env.step(np.array([1.0, 1.0], np.float32))
        if done:
            break
    assert done and reward >= 0.03


def test_unknown_object_is_an_error():
    with pytest.raises(GelsimError, match="unknown object 'mug'"):
        GraspEnv(object="mug")
