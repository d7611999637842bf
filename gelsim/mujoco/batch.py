"""Many GelSight sensors in one call: :class:`BatchGelSightSensor` renders N pads (of N environments, or several
pads of one scene) at once on any torch device.

Per call, for every pad, the host does what :class:`gelsim.mujoco.GelSightSensor` does with MuJoCo (its contact
forces, the ray casts of what lies in front of the pad, the protrusion map, the stick/slip state), then the frame
pipeline (:func:`gelsim.stream.make_frames` on the torch engine, :class:`gelsim.engines.TorchEngine`) does the rest
for all pads together: the imprint (each pad warm-started from its own previous frame), the markers and the camera
image. A pad without a contact force gets the flat gel (with noise, when on), as the single sensor does.

The pads of one batch are one sensor unit: one profile, resolution, fidelity and ``seed`` (the background's
illumination, the markers' print and the noise stream's seed, as :class:`GelSightSensor`'s ``seed``). Its frames
equal N single sensors' (``GelSightSensor(..., seed=seed)``, one per pad, rendered in the same order) within the
device path's tolerances: the imprint's (:data:`gelsim.gel.twoscale_torch.TOLERANCE`), the markers'
(:data:`gelsim.markers_torch.TOL_PX`) and the torch optics' (``TOL_MAX_UINT8_DN`` per pixel), tested in
``tests/gelsim/test_device_sensor.py``.

Pads that share a model (N copies of one scene, each with its own ``MjData``) share one single sensor's host
machinery (its private ray scene is compiled once); each pad keeps its own contact history.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from ..engines import TorchEngine
from ..errors import GelsimError
from ..fidelity import Fidelity, get_fidelity
from ..stream import FrameRequest, FrameSetup, Touch, make_frames
from .sensor import GelSightSensor
from .stickslip import StickSlip


@dataclass
class _PadState:
    """One pad's contact history (GelSightSensor's, kept apart so that pads can share a sensor's machinery)."""
    stick_slip: StickSlip = field(default_factory=StickSlip)
    frame: int = 0
    warm: object = None                  # the previous frame's imprint (the torch engine's), or None


@dataclass
class BatchFrames:
    """N tactile frames (as :class:`gelsim.mujoco.TactileFrame`, batched): ``rgb`` uint8 ``(N, H, W, 3)``,
    ``depth_mm`` float32 ``(N, H, W)``, ``contact_mask`` bool ``(N, H, W)``, ``markers_xy_px`` float32 ``(N, M, 2)``
    (tensors on the device); ``markers_rest_px`` float32 ``(M, 2)``; per pad (numpy ``(N,)`` or ``(N, 2)``)
    ``normal_force_n``, ``tangential_force_n``, ``shear_mm``, ``twist_deg``, ``in_contact``, ``slipping``,
    ``time_s``."""
    rgb: object
    depth_mm: object
    contact_mask: object
    markers_xy_px: object
    markers_rest_px: np.ndarray
    normal_force_n: np.ndarray
    tangential_force_n: np.ndarray
    shear_mm: np.ndarray
    twist_deg: np.ndarray
    in_contact: np.ndarray
    slipping: np.ndarray
    time_s: np.ndarray

    def __len__(self) -> int:
        return int(self.normal_force_n.shape[0])

    def frame(self, i: int):
        """Pad ``i``'s frame as a :class:`gelsim.mujoco.TactileFrame` (numpy, on the host)."""
        from .sensor import TactileFrame

        return TactileFrame(self.rgb[i].cpu().numpy(), self.markers_xy_px[i].cpu().numpy(), self.markers_rest_px.copy(),
                            float(self.normal_force_n[i]), self.tangential_force_n[i].copy(),
                            self.contact_mask[i].cpu().numpy(), self.depth_mm[i].cpu().numpy(), self.shear_mm[i].copy(),
                            float(self.twist_deg[i]), bool(self.in_contact[i]), bool(self.slipping[i]),
                            float(self.time_s[i]))


class BatchGelSightSensor:
    """N GelSight sensors rendered together (see the module docstring).

    ``pads``: a list of ``(model, data, pad_geom_name)``; ``profile`` (default ``vitac``: the torch optics render
    tiled shading tables, which gelsight-mini's spatially exact one is not), ``fidelity`` (``fast`` or ``balanced``: the
    device imprint's two-scale levels), ``resolution``, ``seed`` and ``noise`` as :class:`GelSightSensor`'s, for
    every pad; ``device``: the torch device (``cpu``, ``cuda``, ``cuda:N``).
    """

    def __init__(self, pads, *, profile="vitac", fidelity: str | Fidelity = "fast",
                 resolution: tuple[int, int] | None = None, seed: int = 0, noise: bool = True, device=None):
        from ..optics import Renderer
        from ..optics.torch_backend import BatchRenderer, resolve_device

        pads = list(pads)
        if not pads:
            raise GelsimError("BatchGelSightSensor needs at least one (model, data, pad) triple")
        fid = get_fidelity(fidelity)
        if fid.imprint_model != "twoscale":
            raise GelsimError(f"the batched sensor runs the two-scale imprint on the device; give fidelity fast or "
                              f"balanced, not {fid.name}")
        self.device = resolve_device(device) if not hasattr(device, "type") else device
        self.fidelity = fid
        self.seed, self.noise = int(seed), bool(noise)
        self._hosts: dict = {}
        self._make = dict(profile=profile, fidelity=fid, resolution=resolution, seed=seed, noise=noise)
        self._pads = []
        for k, entry in enumerate(pads):
            try:
                model, data, pad = entry
            except (TypeError, ValueError):
                raise GelsimError(f"pad {k}: give (model, data, pad geom name), got {entry!r}") from None
            self._pads.append((self._host(model, data, pad, k), data, _PadState()))
        first = self._pads[0][0]
        self.profile = first.profile
        if any(h.profile != self.profile for h, _, _ in self._pads):
            raise GelsimError("the pads of one batch share one profile and resolution; make one batch per sensor kind")
        _check_torch_optics(self.profile)
        self.renderer = BatchRenderer(Renderer(self.profile, "torch", supersample=fid.supersample, seed=self.seed,
                                               device=self.device))
        self.setup = FrameSetup.make(self.profile, fid, sensor_seed=self.seed, renderer=self.renderer)
        self.engine = TorchEngine(self.device, sync=True)
        self._rest = first.rest_px
        self.timings_ms: dict[str, float] = {}

    def _host(self, model, data, pad, k):
        """The single sensor whose machinery pads of ``model``'s geom ``pad`` share (made on first use)."""
        if not isinstance(data, mujoco.MjData):
            raise GelsimError(f"pad {k}: data is not a mujoco.MjData")
        key = (id(model), pad)
        host = self._hosts.get(key)
        if host is None or host.model is not model:
            host = GelSightSensor(model, data, pad, **self._make)
            self._hosts[key] = host
        if hasattr(self, "profile") and host.profile != self.profile:
            raise GelsimError("the pads of one batch share one profile and resolution; make one batch per sensor kind")
        return host

    def set_pad(self, i: int, model, data, pad: str) -> None:
        """Pad ``i`` is now the geom ``pad`` of (``model``, ``data``) (an environment reset to a new scene): its
        contact history and noise stream restart. Machinery no pad uses any more is let go."""
        host = self._host(model, data, pad, i)
        self._pads[i] = (host, data, _PadState())
        used = {id(h) for h, _, _ in self._pads}
        self._hosts = {k: h for k, h in self._hosts.items() if id(h) in used}

    def __len__(self) -> int:
        return len(self._pads)

    @property
    def shape(self) -> tuple[int, int]:
        return self.profile.shape

    def reset(self, which=None) -> None:
        """Forget the contact history (and restart the noise stream) of every pad, or of the pads ``which``."""
        idx = range(len(self._pads)) if which is None else which
        for i in idx:
            host, data, _ = self._pads[i]
            self._pads[i] = (host, data, _PadState())

    def _host_step(self, host: GelSightSensor, data, st: _PadState):
        """One pad's MuJoCo side: (normal N, tangential (2,), protrusion or None, shear (2,), twist, slipping)."""
        host.data = data
        try:
            found = host.contact_forces()
            gaps = None
            if found is not None:
                gaps = host.rays.gaps_mm(data)
                if not np.isfinite(gaps).any():
                    found = None
            if found is None:
                st.stick_slip.release()
                st.warm = None
                return 0.0, np.zeros(2), None, np.zeros(2), 0.0, False
            normal, tang, torque, mu, body = found
            prot = host.protrusion_mm(gaps)
            shear, twist, slipping = host.shear_twist(st.stick_slip, body, normal, tang, torque, mu)
            return float(normal), np.asarray(tang, float), prot, np.asarray(shear, float), float(twist), bool(slipping)
        finally:
            host.data = None

    def render(self) -> BatchFrames:
        """Every pad's tactile frame of its scene's current state."""
        import torch

        clock = self.engine.clock
        t0 = clock()
        n = len(self._pads)
        normal = np.zeros(n)
        tang = np.zeros((n, 2))
        shear = np.zeros((n, 2))
        twist = np.zeros(n)
        slipping = np.zeros(n, bool)
        requests = []
        for i, (host, data, st) in enumerate(self._pads):
            rng = np.random.default_rng([self.seed, st.frame])
            st.frame += 1
            f, tg, prot, sh, tw, sl = self._host_step(host, data, st)
            normal[i], tang[i], shear[i], twist[i], slipping[i] = f, tg, sh, tw, sl
            touch = None if prot is None else Touch(prot, force_n=f, shear_mm=tuple(sh), twist_deg=tw, warm=st.warm)
            requests.append(FrameRequest(touch, rng, self.noise))
        host_ms = (clock() - t0) * 1e3
        made = make_frames(requests, self.setup, self.engine)
        live = made.imprints.pressed
        for i, (_, _, st) in enumerate(self._pads):
            st.warm = made.parts[i].imprint
        xy = made.markers.xy if made.markers is not None else torch.zeros((n, 0, 2), device=self.device)
        # (the optics stage has always been "render" here)
        self.timings_ms = {"host": host_ms, **{("render" if k == "optics" else k): v * 1e3
                                                for k, v in made.seconds.items()}, "total": (clock() - t0) * 1e3}
        in_contact = np.zeros(n, bool)
        in_contact[live] = True
        times_s = np.array([float(data.time) for _, data, _ in self._pads])
        return BatchFrames(made.frames, made.imprints.depth_mm, made.imprints.contact_mask, xy, self._rest.copy(),
                           normal, tang, shear, twist, in_contact, slipping, times_s)

    def close(self) -> None:
        """Free the single sensors' resources."""
        for host in self._hosts.values():
            host.close()


def _check_torch_optics(profile) -> None:
    """One line for a profile the torch optics cannot render (a shading table with the exact per-pixel lookup)."""
    if profile.shading.model != "lut":
        return
    from ..optics.lut import LutShader

    if LutShader(profile).exact:
        h, w = profile.shape
        raise GelsimError(f"profile {profile.name!r} at {w}x{h} px shades with the table's per-pixel lookup, which the "
                          "torch optics do not render; use vitac at 64x48 px or more for the batched sensor, or "
                          "GelSightSensor for this one")


# ---------------------------------------------------------------- a test and benchmark rig

@dataclass
class BallScene:
    """One environment of :func:`ball_scenes`: a ball on a slide pushed into a pad (``pad``) facing +z."""
    model: object
    data: object
    pad: str = "pad"
    force_n: float = 1.0

    def settle(self, steps: int = 50) -> None:
        for _ in range(steps):
            mujoco.mj_step(self.model, self.data)

    def step(self, steps: int = 5) -> None:
        """A few physics steps (the ball's push varies slowly with time, so frames differ)."""
        self.data.ctrl[0] = -self.force_n * (1.0 + 0.2 * np.sin(8.0 * self.data.time))
        for _ in range(steps):
            mujoco.mj_step(self.model, self.data)


def ball_scenes(n: int, *, profile: str = "vitac", diameter_mm: float = 8.0, force_n: float = 1.0,
                seed: int = 0) -> list[BallScene]:
    """``n`` copies of :func:`gelsim.mujoco.grasp.press_scene` (one compiled model, one ``MjData`` each), settled
    once and copied, each pushed with its own force (``force_n`` times 0.6-1.4, drawn from ``seed``) and a few
    steps on its own, so that the pads' imprints differ."""
    from .grasp import press_scene

    model, template = press_scene(force_n, diameter_mm, profile=profile, settle_steps=800)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        d = mujoco.MjData(model)
        mujoco.mj_copyData(d, model, template)
        f = force_n * float(rng.uniform(0.6, 1.4))
        d.ctrl[0] = -f
        sc = BallScene(model, d, "pad", f)
        sc.settle(20)
        out.append(sc)
    return out
