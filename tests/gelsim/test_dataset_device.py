"""``gelsim generate --backend torch --stages all``: the whole frame on the torch engine (sequences in step), through
the CLI.

A tiny dataset (CPU torch) that ``gelsim verify`` accepts, whose labels are the numpy path's within the device
path's stated tolerances, whose manifest says the backend, stages and device, and whose bytes are the same for any
``--batch`` and ``--workers`` and after an interrupted run is resumed."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gelsim import dataset  # noqa: E402
from gelsim.cli import main  # noqa: E402
from gelsim.dataset import load_manifest  # noqa: E402
from gelsim.gel.twoscale_torch import TOLERANCE  # noqa: E402
from gelsim.markers_torch import TOL_PX  # noqa: E402
from gelsim.schema import record_path  # noqa: E402

# 2 fabrics x 2 sequences: two groups in step, so that two workers share them out
TINY = ["--fabrics", "2", "--sequences-per-fabric", "2", "--resolution", "160x120", "--fidelity", "fast",
        "--frames", "8-10", "--precontact", "1-2", "--format", "png", "--no-previews", "--json"]
DEVICE = ["--backend", "torch", "--stages", "all", "--device", "cpu"]
# the pose and forces: the physics, on the CPU in both paths
PHYSICS_KEYS = ("time_s", "normal_force_n", "in_contact", "shear_mm", "twist_deg")


def _gen(out, *extra, workers=1):
    return main(["generate", "--out", str(out), "--workers", str(workers), *TINY, *extra])


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("devgen")
    assert _gen(root / "numpy") == 0
    assert _gen(root / "b1", *DEVICE, "--batch", "1") == 0
    assert _gen(root / "b8", *DEVICE, "--batch", "8", workers=2) == 0
    return root


def _labels(root: Path, seq: dict) -> dict:
    with np.load(root / seq["labels"]) as z:
        return {k: z[k] for k in z}


def test_verify_accepts_it_and_the_manifest_says_backend_stages_device(made, capsys):
    capsys.readouterr()
    assert main(["verify", str(made / "b1")]) == 0
    assert "OK" in capsys.readouterr().out
    m = load_manifest(made / "b1")
    assert m["options"]["backend"] == "torch" and m["options"]["stages"] == "all"
    assert m["render"]["backend"] == "torch" and m["render"]["stages"] == "all"
    assert m["render"]["devices"] == ["cpu"] and m["render"]["labels"].startswith("device")
    assert m["render"]["torch"] == torch.__version__
    assert all(json.loads((made / "b1" / record_path(s["id"])).read_text())["device"] == "cpu"
               for s in m["sequences"])
    ref = load_manifest(made / "numpy")["render"]
    assert ref == {"backend": "fast", "stages": "none", "devices": ["cpu"], "labels": "numpy: the bit-exact reference"}


def test_same_bytes_for_any_batch_and_workers(made):
    b1, b8 = load_manifest(made / "b1"), load_manifest(made / "b8")
    assert b1["sequences"] == b8["sequences"]          # every checksum


def test_labels_agree_with_the_numpy_path_within_the_stated_tolerance(made):
    _assert_labels_agree(made / "numpy", made / "b1")


def _assert_labels_agree(numpy_root: Path, device_root: Path) -> None:
    """Every sequence's labels: the schema's keys, dtypes and shapes; the physics' byte for byte; the imprint's
    within :data:`TOLERANCE`, the markers' within :data:`TOL_PX`."""
    ref, dev = load_manifest(numpy_root), load_manifest(device_root)
    touched_frames = 0
    for r, d in zip(ref["sequences"], dev["sequences"]):
        a, b = _labels(numpy_root, r), _labels(device_root, d)
        assert list(a) == list(b)                                   # the schema's keys, in its order
        assert all(a[k].dtype == b[k].dtype and a[k].shape == b[k].shape for k in a)
        for k in PHYSICS_KEYS:
            assert np.array_equal(a[k], b[k]), k
        assert np.abs(a["indentation_mm"] - b["indentation_mm"]).max() <= TOLERANCE["indentation_mm"]
        area = a["contact_area_mm2"]
        assert np.all(np.abs(b["contact_area_mm2"] - area) <= TOLERANCE["area_rel"] * area + 1e-9)
        touched = np.isfinite(a["contact_centroid_px"][:, 0])
        assert np.array_equal(np.isfinite(b["contact_centroid_px"][:, 0]), touched)
        if touched.any():
            assert np.abs(a["contact_centroid_px"][touched] - b["contact_centroid_px"][touched]).max() \
                <= TOLERANCE["centroid_px"]
            # the box's edges are pixel edges: the same, or one mask pixel apart where the masks differ
            assert np.abs(a["contact_bbox_px"][touched] - b["contact_bbox_px"][touched]).max() <= 1.0
        touched_frames += int(touched.sum())
        assert np.array_equal(a["markers_rest_px"], b["markers_rest_px"])
        assert np.abs(a["markers_xy_px"] - b["markers_xy_px"]).max() <= TOL_PX
    assert touched_frames >= 10                                      # the comparison saw contacts


def test_the_nuisance_runs_on_the_device_and_leaves_the_labels_alone(made, capsys):
    """``--stages all --nuisance handheld``: the fibres' dents and the camera's gains on the torch engine, made on
    the host per sequence (the same draws as the numpy path's); the dataset verifies, its labels are the same bytes
    as without the nuisance, its frames are not, and any --batch gives the same bytes."""
    hand = made / "hand"
    assert _gen(hand, *DEVICE, "--nuisance", "handheld", "--batch", "3") == 0
    capsys.readouterr()
    assert main(["verify", str(hand)]) == 0 and "OK" in capsys.readouterr().out
    a, b = load_manifest(made / "b1"), load_manifest(hand)
    assert b["options"]["nuisance"] == "handheld" and b["render"]["stages"] == "all"
    assert [s["sha256"]["labels"] for s in a["sequences"]] == [s["sha256"]["labels"] for s in b["sequences"]]
    assert all(x["sha256"]["video"] != y["sha256"]["video"] for x, y in zip(a["sequences"], b["sequences"]))
    assert _gen(made / "hand8", *DEVICE, "--nuisance", "handheld", "--batch", "8") == 0
    assert load_manifest(made / "hand8")["sequences"] == b["sequences"]


def test_an_interrupted_run_resumes_to_the_same_bytes(made, tmp_path):
    """A group whose other member is written already is made again whole, so the missing one is the bytes an
    uninterrupted run writes; the written one is not rewritten."""
    import shutil

    out = tmp_path / "resumed"
    shutil.copytree(made / "b1", out)
    m = load_manifest(out)
    gone, kept = m["sequences"][0], m["sequences"][1]
    assert gone["fabric_id"] == kept["fabric_id"]                  # one group
    for rel in (record_path(gone["id"]), gone["labels"]):
        (out / rel).unlink()
    shutil.rmtree(out / gone["video"])
    kept_record = (out / record_path(kept["id"])).read_text()
    assert _gen(out, *DEVICE) == 0
    assert load_manifest(out)["sequences"] == m["sequences"]
    assert (out / record_path(kept["id"])).read_text() == kept_record


def test_groups_are_the_plans_alone():
    cfg = dataset.GenerateConfig(fabrics=3, sequences_per_fabric=40, units=2)
    specs = dataset.plan(cfg, 100)
    groups = dataset.device_groups(specs)
    assert sorted(s.id for g in groups for s in g) == sorted(s.id for s in specs)
    for g in groups:
        assert len({(s.fabric_id, s.unit) for s in g}) == 1 and len(g) <= dataset.MAX_LANES
    sizes = [len(g) for g in groups]
    assert sizes == [10] * 12                     # 20 per fabric and unit: two groups of 10 each
    assert dataset.device_groups(specs[:5]) == [specs[0:5:2], specs[1:5:2]]


@pytest.mark.parametrize("extra, words", [
    (["--stages", "all"], "for --backend torch"),
    (["--backend", "torch", "--stages", "all", "--fidelity", "reference"], "fidelity fast or balanced"),
    (["--backend", "torch", "--stages", "all", "--batch", "0"], "--batch"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, extra, words):
    assert main(["generate", "--out", str(tmp_path / "x"), "--fabrics", "1", "--sequences-per-fabric", "1",
                 *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_a_device_dataset_is_not_resumed_by_the_optics_stages(made, capsys):
    capsys.readouterr()
    assert _gen(made / "b1", "--backend", "torch") == 2
    assert "(stages)" in capsys.readouterr().err


def test_cuda_dataset_same_bytes_for_any_batch_and_labels_within_tolerance(made, tmp_path):  # pragma: no cover
    """On a GPU: the dataset made on CUDA is the same bytes for any --batch and --workers, its labels within the
    stated tolerance of the numpy path's, and its manifest names the GPU."""
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device here (CI has none)")
    cuda = ["--backend", "torch", "--stages", "all", "--device", "cuda"]
    assert _gen(tmp_path / "g1", *cuda, "--batch", "1") == 0
    assert _gen(tmp_path / "g8", *cuda, "--batch", "8", workers=2) == 0
    g1, g8 = load_manifest(tmp_path / "g1"), load_manifest(tmp_path / "g8")
    assert g1["sequences"] == g8["sequences"]
    assert [d.split(" ")[0] for d in g1["render"]["devices"]] == ["cuda:0"]
    _assert_labels_agree(made / "numpy", tmp_path / "g1")
