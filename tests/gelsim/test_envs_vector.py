"""gelsim.envs.vector.GraspVectorEnv: GraspEnv's scenes stepped together, their pads rendered in one batched call.

Gymnasium is an optional extra (`make gym`); without it these tests skip."""
from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")
pytest.importorskip("torch")

from gelsim.envs import GraspEnv  # noqa: E402
from gelsim.envs.vector import GraspVectorEnv  # noqa: E402
from gelsim.errors import GelsimError  # noqa: E402

pytestmark = pytest.mark.usefixtures("torch_one_thread")
DOWN, CLOSE, LIFT = np.array([-1.0, -1.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0])


def script(n_down=15, n_close=12, n_lift=30):
    return [DOWN] * n_down + [CLOSE] * n_close + [LIFT] * n_lift


def test_scripted_grasp_lifts_in_every_environment_and_autoresets():
    n = 3
    env = GraspVectorEnv(n, object="box_edge", max_steps=80)
    obs, info = env.reset(seed=1)
    assert env.observation_space.contains(obs) and list(info["object"]) == ["box_edge"] * n
    untouched = obs["tactile_left"].copy()
    ended = np.zeros(n, bool)
    for k, a in enumerate(script()):
        obs, reward, terminated, truncated, _ = env.step(np.tile(a, (n, 1)).astype(np.float32))
        if k == 26:                                              # closed on the object
            assert (obs["state"][:, 1] > 1.0).all() and (obs["state"][:, 2] > 1.0).all()
            assert (np.abs(obs["tactile_left"].astype(int) - untouched).max(axis=(1, 2, 3)) > 20).all()
        ended |= terminated
        if terminated.all():
            break
    assert ended.all() and (reward >= 0.03).all() and not truncated.any()
    obs, reward, terminated, truncated, _ = env.step(np.zeros((n, 2), np.float32))   # next-step autoreset
    assert (reward == 0).all() and not terminated.any() and np.allclose(obs["state"][:, 1:], 0.0)
    assert np.array_equal(obs["tactile_left"], untouched)                           # the flat gel again
    env.close()


def test_physics_and_forces_are_graspenvs():
    """The same actions give GraspEnv's state (hand height, both pads' forces, the object's rise) exactly: the
    physics is the same function, the forces are MuJoCo's."""
    single = GraspEnv(profile="vitac", object="sphere", max_steps=40)
    vec = GraspVectorEnv(2, object="sphere", max_steps=40)
    s_obs, _ = single.reset(seed=0)
    v_obs, _ = vec.reset(seed=0)
    np.testing.assert_array_equal(v_obs["state"][1], s_obs["state"])
    for a in script(12, 10, 5):
        s_obs, *_ = single.step(a.astype(np.float32))
        v_obs, *_ = vec.step(np.tile(a, (2, 1)).astype(np.float32))
        np.testing.assert_array_equal(v_obs["state"][0], s_obs["state"])
    assert s_obs["state"][1] > 1.0


def test_make_vec_through_a_vector_entry_point():
    env = gym.make_vec("gelsim/GraspBatched-v0", num_envs=2, vectorization_mode="vector_entry_point",
                       object="bolt", max_steps=5)
    obs, _ = env.reset(seed=3)
    assert obs["tactile_right"].shape == (2, 48, 64, 3)
    env.close()


def test_bad_input_is_one_line():
    with pytest.raises(GelsimError, match="num_envs"):
        GraspVectorEnv(0)
    with pytest.raises(GelsimError, match="unknown object"):
        GraspVectorEnv(2, object="cup")
    with pytest.raises(GelsimError, match="reset"):
        GraspVectorEnv(1).step(np.zeros((1, 2), np.float32))
