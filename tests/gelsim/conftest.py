"""Fixtures shared by the gelsim tests: the ViTac sensor profile at its own and at a small resolution
(frozen dataclasses, so one instance serves every test), and two short sequences prepared for the torch tests."""
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


@pytest.fixture(scope="session")
def two_sequences():
    """Two short sequences prepared once (their contact simulations and patches: gelsim.sequence.SequenceRun, at
    160x120, balanced): a twist of a plain weave and a slip of a corduroy. ``(profile, fidelity, [(object,
    motion, seed), ...], [SequenceRun, ...])``; a test runs ``run.again()``, not the runs themselves."""
    from gelsim.fabrics import load_catalog
    from gelsim.fidelity import get_fidelity
    from gelsim.motion import sample_motion
    from gelsim.sequence import SequenceRun

    prof = load_profile("vitac").with_resolution(160, 120)
    fid = get_fidelity("balanced")
    cat = load_catalog()
    specs = [(cat[1], sample_motion("twist", 5, frames=(7, 7), precontact=(2, 2)), 5),
             (cat[64], sample_motion("slip", 6, frames=(8, 8), precontact=(1, 1)), 6)]
    return prof, fid, specs, [SequenceRun(o, m, prof, fid, seed=s) for o, m, s in specs]
