"""GraspEnv: pick an object up with a two-finger gripper that feels it through two GelSight pads.

Scene: :func:`gelsim.mujoco.grasp.build_grasp_scene` (one of its OBJECTS per episode, drawn from the
seed unless ``object`` is given). One step is one tactile camera frame (1/30 s of physics).

* action: float32 (2,) in [-1, 1]: the hand's vertical speed (times HAND_SPEED_M_S) and the grip
  (-1 open ... 1 closed with MAX_GRIP_N);
* observation: ``tactile_left``, ``tactile_right``: uint8 (H, W, 3) images; ``state``: float32 (4,)
  hand height above the grasp height (m), left and right normal force on the gel (N), object
  height above its start (m);
* reward: the object's rise since the start, m, per step; the episode ends (terminated) once it
  is LIFT_GOAL_M up, or after ``max_steps`` (truncated).
* ``render_mode="rgb_array"``: :meth:`GraspEnv.render` returns the two tactile images side by side,
  uint8 (H, 2 W, 3) RGB, left finger first (what the gripper feels; it needs no OpenGL). There is no
  ``"human"`` mode: gelsim opens no window; show the image with matplotlib, or write the frames to a video
  (:func:`gelsim.video.write_video`).

Registered with Gymnasium as ``gelsim/Grasp-v0`` (:mod:`gelsim.envs`).
"""
from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from ..errors import GelsimError
from ..mujoco import GelSightSensor
from ..mujoco.grasp import APPROACH_M, OBJECTS, build_grasp_scene

HAND_SPEED_M_S = 0.1
MAX_GRIP_N = 8.0
LIFT_GOAL_M = 0.03
FPS = 30.0
# Bounds of the state vector, for its Box: the hand travels within +-0.2 m, forces stay below 100 N.
STATE_HIGH = np.array([0.2, 100.0, 100.0, 0.2], np.float32)


class GraspEnv(gym.Env):
    """See the module docstring. ``resolution``: tactile image (width, height) px; ``profile``:
    sensor profile; ``object``: one of OBJECTS (None: drawn per episode); ``max_steps``;
    ``render_mode``: None or "rgb_array" (see the module docstring)."""
    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(self, *, resolution: tuple[int, int] = (64, 48), profile: str = "gelsight-mini",
                 object: str | None = None, max_steps: int = 90, render_mode: str | None = None):
        if object is not None and object not in OBJECTS:
            raise GelsimError(f"unknown object {object!r}; choose one of {', '.join(OBJECTS)} or None")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            # no "human": gelsim opens no window (it runs headless); a caller shows render()'s image itself
            raise GelsimError(f"render_mode {render_mode!r} is not supported (gelsim opens no window); give "
                              "'rgb_array' and show env.render()'s image (e.g. matplotlib's imshow), or None")
        self.render_mode = render_mode
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self.resolution, self.profile, self.object, self.max_steps = tuple(resolution), profile, object, int(max_steps)
        w, h = self.resolution
        img = spaces.Box(0, 255, (h, w, 3), np.uint8)
        self.observation_space = spaces.Dict({"tactile_left": img, "tactile_right": img,
                                              "state": spaces.Box(-STATE_HIGH, STATE_HIGH, dtype=np.float32)})
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._scene = None

    def _obs(self):
        tl, tr = (s.render() for s in self._sensors)
        self._last = (tl.rgb, tr.rgb)
        state, rise = state_vector(self._scene.data, self._hand_q, self._obj, self._obj_z0, tl.normal_force_n,
                                   tr.normal_force_n)
        return {"tactile_left": tl.rgb, "tactile_right": tr.rgb, "state": state}, rise

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        kind = self.object or OBJECTS[int(self.np_random.integers(len(OBJECTS)))]
        sc = build_grasp_scene(kind, profile=self.profile)
        self._scene = sc
        m = sc.model
        self._sensors = [GelSightSensor(m, sc.data, p, profile=self.profile, resolution=self.resolution,
                                        seed=int(self.np_random.integers(2**31)))
                         for p in sc.pads]
        self._hand_q = m.joint("hand_z").qposadr[0]
        self._obj = m.body(sc.object_body).id
        self._obj_z0 = float(sc.data.xpos[self._obj][2])
        self._target = APPROACH_M
        self._steps = 0
        obs, _ = self._obs()
        return obs, {"object": kind}

    def step(self, action):
        self._target = advance(self._scene.model, self._scene.data, self._scene, self._target, action)
        self._steps += 1
        obs, rise = self._obs()
        terminated = rise >= LIFT_GOAL_M
        truncated = self._steps >= self.max_steps
        return obs, rise, bool(terminated), bool(truncated), {}

    def render(self):
        """With ``render_mode="rgb_array"``: both tactile images of the last step side by side, uint8
        (H, 2 W, 3) RGB; None otherwise (Gymnasium's convention)."""
        if self.render_mode is None or self._last is None:
            return None
        return np.concatenate(self._last, axis=1)


def advance(model, data, scene, target: float, action) -> float:
    """One step's physics (1/FPS s of it) of a grasp scene (``scene``'s actuator ids; ``model``, ``data`` its
    model and this environment's state) under ``action`` (see the module docstring): returns the hand's new
    target height, m."""
    a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    n = int(round(1.0 / FPS / model.opt.timestep))
    target = float(np.clip(target + a[0] * HAND_SPEED_M_S / FPS, -0.01, 0.15))
    grip = -1.0 + (MAX_GRIP_N + 1.0) * (a[1] + 1.0) / 2.0
    data.ctrl[scene.act_hand] = target
    data.ctrl[scene.act_left] = data.ctrl[scene.act_right] = grip
    for _ in range(n):
        mujoco.mj_step(model, data)
    return target


def state_vector(data, hand_q: int, obj: int, obj_z0: float, left_n: float, right_n: float):
    """The observation's ``state`` (float32 (4,), clipped to its Box) and the object's rise (m) of a grasp scene."""
    rise = float(data.xpos[obj][2] - obj_z0)
    state = np.array([data.qpos[hand_q], left_n, right_n, rise], np.float32)
    return np.clip(state, -STATE_HIGH, STATE_HIGH), rise
