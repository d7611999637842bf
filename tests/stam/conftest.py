import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def _one_thread():
    # Tiny tensors on a shared 2-core machine: one thread avoids spin contention.
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


TINY_PRESET = """
[pretrain]
width = 0.25
image_size = 96
epochs = 2
batch_size = 32
lr = 0.002
[train]
image_size = 96
width = 0.25
freeze_backbone = true
epochs = 3
batch_size = 16
optimizer = "adam"
lr = 0.002
progress = false
[sweep]
frames = [2, 3]
settings = ["clean", "noisy"]
seeds = 1
"""


@pytest.fixture(scope="session")
def tiny_preset(tmp_path_factory):
    """TINY_PRESET as a preset file."""
    preset = tmp_path_factory.mktemp("preset") / "tiny.toml"
    preset.write_text(TINY_PRESET)
    return preset


@pytest.fixture(scope="session")
def tiny_experiment(synth, tiny_preset, tmp_path_factory):
    from stam.experiment import run_experiment

    d = tmp_path_factory.mktemp("exp")
    preset = tiny_preset
    out = d / "out"
    res = run_experiment(str(synth), out, str(preset), log=None)
    return {"out": out, "preset": preset, "result": res, "data": synth}
