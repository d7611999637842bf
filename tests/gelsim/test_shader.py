"""gelsim.optics.shader: the backends' contract, its load-time check and its default compositing."""
from __future__ import annotations

import numpy as np
import pytest

from gelsim.errors import GelsimError
from gelsim.optics import Renderer
from gelsim.optics import shader as sh
from gelsim.optics.ops.filters import gaussian_blur
from gelsim.sensor import load_profile


@pytest.fixture(scope="module")
def prof():
    return load_profile("digit").with_resolution(64)      # digit shades with Phong: the "fast" class


class Box(sh.Shader):
    """A shader whose change is a fixed +10 DN box (rows 4-9, columns 6-13) wherever the gel is pressed."""
    name = "box"

    def __init__(self, profile=None, maps=None):
        pass

    def delta(self, depth_mm, margin_px=0):
        if not np.any(depth_mm > 0):
            return None
        return (slice(4, 10), slice(6, 14)), np.full((6, 8, 3), 10.0, np.float32)


def test_every_registered_backend_satisfies_the_contract(prof):
    import importlib

    for key, (module, name) in sh.SHADER_CLASSES.items():
        cls = getattr(importlib.import_module(module), name)
        assert sh.check_shader(cls, key) is cls and cls.name
    assert sh.shader_class("fast", prof).name == "fast"
    assert sh.shader_class("fast", load_profile("vitac")).name == "lut"
    with pytest.raises(GelsimError, match="unknown render backend"):
        sh.shader_class("raytracer", prof)


def _one_line(exc) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("render backend 'x'")
    return msg


def test_check_names_what_breaks_the_contract():
    class NoDelta(sh.Shader):
        name = "nodelta"

    class OldDelta(Box):
        def delta(self, depth_mm):          # the margin the Renderer passes is missing
            return None

    class Nameless(Box):
        name = ""

    class NotAShader:
        def delta(self, depth_mm, margin_px=0):
            return None

    for cls, what in ((NotAShader, "derive it from Shader"), (NoDelta, "does not implement delta"),
                      (OldDelta, "OldDelta.delta(self, depth_mm)"), (Nameless, "has no name")):
        with pytest.raises(GelsimError) as e:
            sh.check_shader(cls, "x")
        assert what in _one_line(e)
    assert sh.check_shader(Box, "x") is Box


def test_renderer_refuses_a_broken_backend_when_loading_it(prof, monkeypatch):
    import types

    mod = types.ModuleType("fake_backend")

    class Broken(sh.Shader):
        name = "broken"

    mod.Broken = Broken
    monkeypatch.setitem(__import__("sys").modules, "fake_backend", mod)
    monkeypatch.setitem(sh.SHADER_CLASSES, "fast", ("fake_backend", "Broken"))
    with pytest.raises(GelsimError, match="render backend 'fast': Broken does not implement delta"):
        Renderer(prof, "fast")


def test_default_parts_and_compose():
    s = Box()
    flat = np.zeros((16, 20), np.float32)
    pressed = flat.copy()
    pressed[7, 9] = 0.1
    assert s.parts(flat, 0, 1.0) is None and s.delta(flat) is None
    (roi, change, blurred), = s.parts(pressed, 0, 1.0)
    assert roi == (slice(4, 10), slice(6, 14)) and not blurred and change.shape == (6, 8, 3)
    bg = np.full((16, 20, 3), 100.0, np.float32)
    frame = np.full_like(bg, -1.0)
    assert s.compose(frame, bg, flat, 0, 1.0, gaussian_blur) is False
    assert np.all(frame == -1.0)                      # untouched for a flat gel
    assert s.compose(frame, bg, pressed, 0, 1.0, gaussian_blur) is True
    want = bg.copy()
    want[roi] += gaussian_blur(np.full((6, 8, 3), 10.0, np.float32), 1.0)
    np.testing.assert_allclose(frame, want, atol=1e-5)
    # with finish: one call with the whole frame's rows, into a buffer of the shader's own if frame is None
    calls = []
    assert s.compose(None, bg, pressed, 0, 1.0, gaussian_blur, lambda rows, y0, y1: calls.append((rows.copy(), y0, y1)))
    assert len(calls) == 1 and calls[0][1:] == (0, 16)
    np.testing.assert_array_equal(calls[0][0], frame)
    assert s.close() is None


def test_renderer_draws_through_compose(prof, monkeypatch):
    """The Renderer's shading is exactly the backend's compose: swap in the box shader."""
    import gelsim.optics as optics

    monkeypatch.setattr(optics, "shader_class", lambda backend, profile: Box)
    r = Renderer(prof, "fast")
    depth = np.zeros(prof.shape, np.float32)
    depth[6, 8] = 0.2
    bg = r.background_float()
    got = r.render_float(depth) - bg
    # a constant box blurred with replicated borders stays constant, and nothing spreads out of it
    inside = np.zeros(prof.shape, bool)
    inside[4:10, 6:14] = True
    np.testing.assert_allclose(got[inside], 10.0, atol=1e-4)
    assert np.all(got[~inside] == 0)
    np.testing.assert_array_equal(r.render_float(None), bg)
    r.close()
