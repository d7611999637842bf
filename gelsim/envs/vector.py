"""GraspVectorEnv: ``num_envs`` grasp scenes (:class:`gelsim.envs.GraspEnv`'s) stepped together, their 2 N GelSight
pads rendered in one call on a torch device (:class:`gelsim.mujoco.batch.BatchGelSightSensor`).

A Gymnasium vector environment (``gymnasium.vector.VectorEnv``, next-step autoreset): the physics of each scene
runs on the CPU as GraspEnv's does (:func:`gelsim.envs.grasp.advance`), the tactile images of all pads at once on
the device. Observations, actions, rewards and episode ends are GraspEnv's, batched: ``tactile_left`` and
``tactile_right`` uint8 (N, H, W, 3), ``state`` float32 (N, 4); actions float32 (N, 2).

The scenes of one object share one compiled model (each environment its own ``MjData``), so an environment's reset
is a fresh state, not a rebuild. Every pad is one sensor unit (the batch's ``seed``: background, marker print,
noise stream); the object is drawn per episode from each environment's own seed stream unless ``object`` is given.
``profile`` defaults to ``vitac``: the torch optics render tiled shading tables (gelsight-mini's is per-pixel).
"""
from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from ..errors import GelsimError
from ..mujoco.batch import BatchGelSightSensor
from ..mujoco.grasp import OBJECTS, build_grasp_scene
from .grasp import STATE_HIGH, FPS, LIFT_GOAL_M, advance, state_vector


class GraspVectorEnv(gym.vector.VectorEnv):
    """See the module docstring. ``num_envs``; ``resolution`` (width, height) px of the tactile images;
    ``profile``; ``object`` (one of OBJECTS, or None: drawn per episode); ``max_steps``; ``device`` (torch device of
    the sensors); ``fidelity`` (fast or balanced); ``seed`` (the sensor unit's)."""
    metadata = {"render_modes": [], "render_fps": FPS, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 4, *, resolution: tuple[int, int] = (64, 48), profile: str = "vitac",
                 object: str | None = None, max_steps: int = 90, device: str | None = None, fidelity: str = "fast",
                 seed: int = 0):
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise GelsimError(f"num_envs {num_envs!r} is invalid; give a whole number of environments >= 1")
        if object is not None and object not in OBJECTS:
            raise GelsimError(f"unknown object {object!r}; choose one of {', '.join(OBJECTS)} or None")
        self.num_envs = num_envs
        self.resolution, self.profile, self.object, self.max_steps = tuple(resolution), profile, object, int(max_steps)
        self._device, self._fidelity, self._seed = device, fidelity, int(seed)
        w, h = self.resolution
        img = spaces.Box(0, 255, (h, w, 3), np.uint8)
        self.single_observation_space = spaces.Dict({"tactile_left": img, "tactile_right": img,
                                                     "state": spaces.Box(-STATE_HIGH, STATE_HIGH, dtype=np.float32)})
        self.single_action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._templates: dict = {}
        self._envs: list[dict] = []
        self._rngs = [np.random.default_rng(i) for i in range(num_envs)]
        self._sensor: BatchGelSightSensor | None = None
        self._autoreset = np.zeros(num_envs, bool)

    def _template(self, kind: str):
        if kind not in self._templates:
            self._templates[kind] = build_grasp_scene(kind, profile=self.profile)
        return self._templates[kind]

    def _new_episode(self, i: int) -> dict:
        kind = self.object or OBJECTS[int(self._rngs[i].integers(len(OBJECTS)))]
        sc = self._template(kind)
        d = mujoco.MjData(sc.model)
        mujoco.mj_copyData(d, sc.model, sc.data)          # the scene's initial state (the template is never stepped)
        m = sc.model
        env = {"kind": kind, "scene": sc, "data": d, "hand_q": m.joint("hand_z").qposadr[0],
               "obj": m.body(sc.object_body).id, "target": float(d.ctrl[sc.act_hand]), "steps": 0}
        env["z0"] = float(d.xpos[env["obj"]][2])
        return env

    def _pads(self, env) -> list:
        sc = env["scene"]
        return [(sc.model, env["data"], p) for p in sc.pads]

    def _observe(self, rewards_for: np.ndarray):
        frames = self._sensor.render()
        self.last_frames = frames
        n = self.num_envs
        rgb = frames.rgb.cpu().numpy()
        states = np.zeros((n, 4), np.float32)
        rises = np.zeros(n)
        for i, env in enumerate(self._envs):
            states[i], rises[i] = state_vector(env["data"], env["hand_q"], env["obj"], env["z0"],
                                               frames.normal_force_n[2 * i], frames.normal_force_n[2 * i + 1])
        obs = {"tactile_left": rgb[0::2], "tactile_right": rgb[1::2], "state": states}
        return obs, np.where(rewards_for, rises, 0.0)

    def reset(self, *, seed=None, options=None):
        """Every environment's new episode: ``seed`` an int (environment i draws from seed + i) or one per
        environment; None keeps each one's stream going."""
        super().reset(seed=seed)
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if np.isscalar(seed) else list(seed)
            if len(seeds) != self.num_envs:
                raise GelsimError(f"reset: {len(seeds)} seeds for {self.num_envs} environments")
            self._rngs = [np.random.default_rng(s) for s in seeds]
        self._envs = [self._new_episode(i) for i in range(self.num_envs)]
        pads = [p for env in self._envs for p in self._pads(env)]
        if self._sensor is None:
            self._sensor = BatchGelSightSensor(pads, profile=self.profile, fidelity=self._fidelity,
                                               resolution=self.resolution, seed=self._seed, device=self._device)
        else:
            for k, (m, d, p) in enumerate(pads):
                self._sensor.set_pad(k, m, d, p)
        self._autoreset[:] = False
        obs, _ = self._observe(np.zeros(self.num_envs, bool))
        return obs, {"object": np.array([e["kind"] for e in self._envs]), "_object": np.ones(self.num_envs, bool)}

    def step(self, actions):
        if self._sensor is None:
            raise GelsimError("step() before reset(); call reset() first")
        actions = np.asarray(actions, dtype=np.float64).reshape(self.num_envs, 2)
        stepped = ~self._autoreset
        for i in range(self.num_envs):
            if self._autoreset[i]:          # the episode ended at the last step: this step starts the next
                self._envs[i] = self._new_episode(i)
                for k, (m, d, p) in enumerate(self._pads(self._envs[i])):
                    self._sensor.set_pad(2 * i + k, m, d, p)
                continue
            env = self._envs[i]
            sc = env["scene"]
            env["target"] = advance(sc.model, env["data"], sc, env["target"], actions[i])
            env["steps"] += 1
        obs, rewards = self._observe(stepped)
        terminated = stepped & (obs["state"][:, 3] >= LIFT_GOAL_M)
        truncated = stepped & np.array([e["steps"] >= self.max_steps for e in self._envs])
        self._autoreset = terminated | truncated
        return obs, rewards.astype(np.float64), terminated, truncated, {}

    def close_extras(self, **kwargs) -> None:
        if self._sensor is not None:
            self._sensor.close()
