"""Fixtures shared by the gelsim tests: the ViTac sensor profile at its own and at a small resolution
(frozen dataclasses, so one instance serves every test)."""
import pytest

from gelsim.sensor import load_profile


@pytest.fixture(scope="session")
def vitac():
    """The ViTac profile as shipped, 960 x 720 px."""
    return load_profile("vitac")


@pytest.fixture(scope="session")
def vitac320(vitac):
    """The ViTac sensor at 320 x 240 px (same field of view)."""
    return vitac.with_resolution(320)


@pytest.fixture(scope="module")
def torch_one_thread():
    """torch on one CPU thread for a module (the device tests' small tensors on a shared 2-core machine: more
    threads spin against each other, 10x slower under load)."""
    torch = pytest.importorskip("torch")
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
