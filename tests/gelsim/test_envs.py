"""gelsim.envs.GraspEnv: Gymnasium's checker, and a scripted grasp that lifts (#14).

Gymnasium is an optional extra (`make gym`); without it these tests skip."""
from __future__ import annotations

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from gelsim.envs import GraspEnv  # noqa: E402
from gelsim.errors import GelsimError  # noqa: E402


def test_registered_env_passes_gymnasiums_checker_without_a_warning():
    """`gym.make("gelsim/Grasp-v0")` after `import gelsim.envs`; check_env with its render check (#42)."""
    import warnings

    env = gym.make("gelsim/Grasp-v0", resolution=(32, 24), max_steps=5)
    assert env.spec.id == "gelsim/Grasp-v0" and env.metadata["render_modes"] == ["rgb_array"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    assert [str(w.message) for w in caught] == []


def test_rgb_array_renders_both_fingers_side_by_side():
    env = gym.make("gelsim/Grasp-v0", resolution=(32, 24), max_steps=5, render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    img = env.render()
    assert img.shape == (24, 64, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[:, :32], obs["tactile_left"])
    np.testing.assert_array_equal(img[:, 32:], obs["tactile_right"])
    plain = gym.make("gelsim/Grasp-v0", resolution=(32, 24))
    plain.reset(seed=0)
    assert plain.render() is None                                                # no render_mode: nothing
    with pytest.raises(GelsimError, match="render_mode 'human' is not supported"):
        GraspEnv(render_mode="human")


def test_make_vec_steps_a_batch():
    envs = gym.make_vec("gelsim/Grasp-v0", num_envs=2, resolution=(32, 24), max_steps=3)
    obs, _ = envs.reset(seed=0)
    assert obs["tactile_left"].shape == (2, 24, 32, 3) and obs["state"].shape == (2, 4)
    obs, reward, terminated, truncated, _ = envs.step(np.zeros((2, 2), np.float32))
    assert reward.shape == (2,) and terminated.shape == (2,)
    envs.close()


def test_the_registry_table_registers_every_id_once():
    import gelsim.envs as envs

    assert "gelsim/Grasp-v0" in envs.ENVS and envs.register_envs() == list(envs.ENVS)   # a second call: no error
    for env_id in envs.ENVS:
        assert gym.spec(env_id).entry_point == envs.ENVS[env_id]["entry_point"]


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


def test_the_readme_loop_runs_in_a_fresh_interpreter():
    """`gym.make("gelsim/Grasp-v0")` in a fresh interpreter failed with NamespaceNotFound (#50). Gymnasium
    1.x reads no entry-point plugins, so the README's example names the module in the id, which Gymnasium
    imports on the way: run as written, in a new process that never imports gelsim itself."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    (code,) = [b for b in re.findall(r"```python\n(.*?)```", readme, flags=re.S) if "gymnasium" in b]
    assert not re.search(r"^\s*(import|from) gelsim", code, flags=re.M) and "env.close()" in code
    probe = code + "\nimport sys\nprint(both_fingers.shape, 'gelsim.envs' in sys.modules)\n"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[-2] == "(48, 128, 3) True"
