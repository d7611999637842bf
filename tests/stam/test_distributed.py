"""``torchrun --nproc-per-node 2 -m stam train``: DDP on gloo gives one process's metrics, resumes
exactly, and ranks started with other arguments stop with one line.

Tolerance: with dropout off, the two runs differ only in the order the gradients are summed, so
every logged loss agrees to 1e-4 and every accuracy exactly, and the final weights to 1e-4.
"""
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from stam.distributed import global_batches, share
from stam.train import make_loader

TORCHRUN = str(Path(sys.executable).with_name("torchrun"))
LOSS_TOL = 1e-4
WEIGHT_TOL = 1e-4


def test_ranks_share_the_batches_one_process_draws():
    class Items(torch.utils.data.Dataset):
        def __len__(self):
            return 37

        def __getitem__(self, i):
            return torch.zeros(1), i

    one = [y.tolist() for _, y in make_loader(Items(), 8, True, 3, 5, 0)]
    assert global_batches(37, 8, 3, 5) == one
    assert global_batches(37, 8, 3, 6) != one            # another epoch, another order
    for world in (2, 3, 8, 9):
        for batch in one:
            parts = [share(batch, r, world) for r in range(world)]
            counted = [p[:n] for p, n in parts]
            assert sum(counted, []) == batch             # every item once, in order
            sizes = [n for _, n in parts]
            assert max(sizes) - min(sizes) <= 1
            assert all(len(p) >= 1 for p, _ in parts)     # every rank takes part in every step


def _env(threads=1):
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    return env | {"OMP_NUM_THREADS": str(threads)}


@pytest.fixture
def preset(tiny_preset):
    return tiny_preset


def _train(synth, out, preset, *extra, procs=1):
    launcher = [TORCHRUN, "--standalone", "--nproc-per-node", str(procs)] if procs > 1 else [sys.executable]
    cmd = [*launcher, "-m", "stam", "train", "--data", str(synth), "--out", str(out), "--preset", str(preset),
           "--set", "threads=1", "--json", *extra]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout)   # one JSON document: rank 0's


def _log(out):
    with open(out / "log.csv") as f:
        return list(csv.DictReader(f))


def _assert_same_metrics(a, b):
    assert len(a) == len(b)
    for ra, rb in zip(a, b):
        for k in ("train_loss", "val_loss"):
            assert abs(float(ra[k]) - float(rb[k])) <= LOSS_TOL, (k, ra, rb)
        for k in ("epoch", "train_acc", "val_acc", "lr"):
            assert ra[k] == rb[k], (k, ra, rb)


def test_two_processes_give_the_metrics_of_one(synth, preset, tmp_path):
    one = _train(synth, tmp_path / "one", preset, "--set", "dropout=0")
    two = _train(synth, tmp_path / "two", preset, "--set", "dropout=0", procs=2)
    assert two["ranks"] == 2 and two["rank"] == 0 and "ranks" not in one
    _assert_same_metrics(_log(tmp_path / "one"), _log(tmp_path / "two"))
    assert two["best_val_acc"] == one["best_val_acc"] and two["best_epoch"] == one["best_epoch"]
    assert float(_log(tmp_path / "one")[-1]["train_acc"]) > 0.5   # it learned something (4 classes)
    wa = torch.load(tmp_path / "one" / "best.pt", weights_only=True)["model"]
    wb = torch.load(tmp_path / "two" / "best.pt", weights_only=True)["model"]
    assert wa.keys() == wb.keys()
    assert max(float((wa[k].float() - wb[k].float()).abs().max()) for k in wa) <= WEIGHT_TOL
    # Rank 0 pretrained once, the other rank reused its backbone (same file as one process's).
    assert (torch.load(tmp_path / "one" / "pretrain" / "backbone.pt", weights_only=True)["val_acc"]
            == torch.load(tmp_path / "two" / "pretrain" / "backbone.pt", weights_only=True)["val_acc"])


def test_two_process_resume_continues_exactly(synth, preset, tmp_path):
    # Dropout on: the resumed ranks must get back their own random states. A constant rate, so
    # that a run of 2 epochs continued to 3 is the run of 3 (a cosine's length changes the rates).
    constant = ("--set", "lr_schedule=constant")
    _train(synth, tmp_path / "full", preset, "--epochs", "3", *constant, procs=2)
    _train(synth, tmp_path / "cut", preset, "--epochs", "2", *constant, procs=2)
    _train(synth, tmp_path / "cut", preset, "--epochs", "3", "--resume", *constant, procs=2)
    full, resumed = _log(tmp_path / "full"), _log(tmp_path / "cut")
    assert [r["epoch"] for r in resumed] == ["1", "2", "3"]
    _assert_same_metrics(full, resumed)
    ck = torch.load(tmp_path / "cut" / "last.pt", weights_only=True)
    assert len(ck["rng_ranks"]) == 2 and not torch.equal(ck["rng_ranks"][0], ck["rng_ranks"][1])


def test_ranks_with_other_arguments_stop_with_one_line(synth, preset, tmp_path, free_port):
    """As torchrun starts them (RANK, WORLD_SIZE, MASTER_ADDR/PORT), but rank 1 with another seed:
    what two nodes started with different commands would do."""
    procs = []
    for rank, seed in ((0, "0"), (1, "1")):
        env = _env() | {"RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1",
                        "MASTER_PORT": str(free_port)}
        procs.append(subprocess.Popen([sys.executable, "-m", "stam", "train", "--data", str(synth), "--out",
                                       str(tmp_path / "run"), "--preset", str(preset), "--seed", seed, "--json"],
                                      env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    results = [p.communicate(timeout=300) + (p.returncode,) for p in procs]
    (out0, err0, rc0), (out1, err1, rc1) = results
    assert rc0 == 2 and rc1 == 2
    lines = err0.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stam: error: the torchrun ranks disagree"), err0
    assert "seed: 0 on rank 0, 1 on rank 1" in lines[0]
    assert err1.strip() == "" and out0 == "" and out1 == ""
    assert not (tmp_path / "run" / "pretrain").exists()    # nothing trained or written


def test_a_truncated_video_is_one_line_on_every_rank(synth, preset, tmp_path):
    """Rank 0 pretrains and meets the truncated video while rank 1 waits: rank 1 printed a 30-line gloo
    traceback (#42). Now each rank says one line, rank 1 with rank 0's reason (torchrun's agent keeps
    the job's store); torchrun's own summary of the failed job follows them."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(synth, data)
    manifest = json.loads((data / "manifest.json").read_text())
    video = data / next(s["video"] for s in manifest["sequences"] if s["split"] == "train")
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 3])
    cmd = [TORCHRUN, "--standalone", "--nproc-per-node", "2", "-m", "stam", "train", "--data", str(data),
           "--out", str(tmp_path / "run"), "--preset", str(preset), "--set", "threads=1"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    assert r.returncode != 0
    lines = r.stderr.splitlines()
    ours = [line for line in lines if line.startswith("stam: error:")]
    assert len(ours) == 2, r.stderr[-3000:]
    # read, a truncated video fails its checksum before it is decoded (#50)
    assert any(line.startswith(f"stam: error: video {video} does not match the manifest's checksum") for line in ours)
    assert any(line.startswith("stam: error: rank 1 of 2 stopped: rank 0 failed: ") and str(video) in line
               for line in ours), ours
    assert not [line for line in lines if line.startswith("[rank")], r.stderr[-3000:]   # no rank's traceback
