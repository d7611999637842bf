"""Fixtures of the bench's tests: a tiny bench and its result (run once per session)."""
import pytest

from gelsim import bench
from gelsim.bench import BenchConfig


@pytest.fixture(scope="session")
def tiny():
    """A tiny bench: no pyrender (the reference is "balanced"), two scenes, 5 frames at 96x72; the coarse
    knit (0.8-1.1 mm loops, 4-6 px per period at 96x72) so that its texture is in the metric's band."""
    return BenchConfig(resolution=(96, 72), frames=5, precontact=1, fabrics=(57,), actions=("press",),
                       levels=("fast", "balanced"), reference="balanced", shortcut_level="")


@pytest.fixture(scope="session")
def tiny_result(tiny):
    return bench.run_bench(tiny)
