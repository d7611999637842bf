"""A tiny dataset end to end, through the CLI as a user runs it."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gelsim.cli import main
from gelsim.dataset import load_manifest, verify
from gelsim.errors import GelsimError
from gelsim.sensor import SENSORS_DIR
from gelsim.video import count_frames

TINY = ["--fabrics", "3", "--sequences-per-fabric", "2", "--resolution", "96x72", "--fidelity", "fast",
        "--frames", "8-10", "--precontact", "2-3", "--no-previews", "--json"]


def _gen(out, *extra, workers=1):
    return main(["generate", "--out", str(out), "--workers", str(workers), *TINY, *extra])


def _contents(root: Path) -> dict:
    m = load_manifest(root)
    return {"sequences": m["sequences"], "options": m["options"], "complete": m["complete"]}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "one"
    assert _gen(out) == 0
    return out


def test_manifest_validates(tiny):
    m = load_manifest(tiny)
    assert m["complete"] is True
    assert len(m["sequences"]) == 6
    keys = {"id", "fabric_id", "action", "num_frames", "contact_onset", "split", "video", "labels"}
    for s in m["sequences"]:
        assert keys <= set(s)
        assert s["action"] in ("press", "slip", "twist")
        assert s["split"] in ("train", "val", "test")
        assert 8 <= s["num_frames"] <= 10
        assert 2 <= s["contact_onset"] <= 3
    assert m["profile"]["width_px"] == 96 and m["profile"]["height_px"] == 72


def test_videos_decode_and_precontact_has_zero_force(tiny):
    m = load_manifest(tiny)
    for s in m["sequences"]:
        assert count_frames(tiny / s["video"]) == s["num_frames"]
        with np.load(tiny / s["labels"]) as z:
            force = z["normal_force_n"]
            in_contact = z["in_contact"]
            assert len(force) == s["num_frames"]
            k = s["contact_onset"]
            assert np.all(force[:k] == 0) and not in_contact[:k].any()
            assert in_contact[k] and force[k] > 0
    assert verify(tiny) == []


def test_two_workers_give_identical_dataset(tiny, tmp_path):
    out = tmp_path / "two"
    assert _gen(out, workers=2) == 0
    assert _contents(out) == _contents(tiny)


def test_a_parent_with_cuda_spawns_its_workers_same_dataset(tiny, tmp_path, monkeypatch):
    """A process that has initialised CUDA cannot fork workers that use it (their initializer fails and
    the pool replaces them forever: a hang, seen on a GPU machine): such a parent spawns its workers,
    which write the same dataset."""
    from gelsim import dataset

    torch = pytest.importorskip("torch")
    assert dataset._pool_start_method() == "fork"
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    assert dataset._pool_start_method() == "spawn"
    out = tmp_path / "spawned"
    assert _gen(out, workers=2) == 0
    assert _contents(out) == _contents(tiny)


def test_sensor_units_are_drawn_recorded_and_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert _gen(a, "--units", "2") == 0
    assert _gen(b, "--units", "2", workers=2) == 0
    assert _contents(a) == _contents(b)          # same units and frames for any number of workers
    m = load_manifest(a)
    assert m["options"]["units"] == 2 and len(m["units"]) == 2 and m["unit_variation"]
    assert [s["unit"] for s in m["sequences"]] == [k % 2 for k in range(len(m["sequences"]))]
    u0, u1 = m["units"]
    assert u0["seed"] != u1["seed"] and u0["lights"] != u1["lights"]   # two different units
    # a unit's frames differ from the plain profile's
    plain = tmp_path / "plain"
    assert _gen(plain) == 0
    shas = {s["id"]: s["sha256"]["video"] for s in load_manifest(plain)["sequences"]}
    assert any(s["sha256"]["video"] != shas[s["id"]] for s in m["sequences"])


def test_rerun_is_a_no_op(tiny):
    before = {p: p.stat().st_mtime_ns for p in tiny.rglob("*.mp4")}
    assert _gen(tiny) == 0
    assert {p: p.stat().st_mtime_ns for p in tiny.rglob("*.mp4")} == before


def test_killed_run_resumes_to_the_same_dataset(tiny, tmp_path):
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "gelsim", "generate", "--out", str(out), "--workers", "1", *TINY]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if len(list((out / "records").glob("*.json"))) >= 2 if (out / "records").exists() else False:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed; the test needs a bigger dataset"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    m = load_manifest(out)
    assert m["complete"] is False
    assert verify(out, decode=False)  # an interrupted dataset is reported as faulty
    assert _gen(out) == 0
    assert _contents(out) == _contents(tiny)
    assert not list(out.rglob(".*partial*"))


def test_verify_catches_truncated_and_missing(tiny, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(tiny, bad)
    m = load_manifest(bad)
    v0 = bad / m["sequences"][0]["video"]
    v0.write_bytes(v0.read_bytes()[: v0.stat().st_size // 2])
    (bad / m["sequences"][1]["labels"]).unlink()
    faults = verify(bad)
    assert any(m["sequences"][0]["id"] in f and "checksum" in f for f in faults)
    assert any(m["sequences"][1]["id"] in f and "missing" in f for f in faults)
    assert main(["verify", str(bad)]) == 1
    assert main(["verify", str(tiny)]) == 0


def test_verify_stats_reports_and_writes_figures(tiny, tmp_path, capsys):
    out = tmp_path / "stats"
    assert main(["verify", str(tiny), "--no-decode", "--stats", "--stats-out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] and doc["faults"] == []
    st = doc["stats"]
    assert sum(a["sequences"] for a in st["actions"].values()) == 6
    assert {str(out / n) for n in ("dataset_stats.json", "dataset_stats.md", "dataset_stats.png",
                                   "dataset_actions.png")} == set(doc["stats_files"])
    assert json.loads((out / "dataset_stats.json").read_text()) == st
    # the contact area at peak force, recomputed here from the labels
    m = load_manifest(tiny)
    areas = []
    for s in m["sequences"]:
        if s["action"] == "press":
            with np.load(tiny / s["labels"]) as z:
                areas.append(float(z["contact_area_mm2"][np.argmax(z["normal_force_n"])]))
    q = st["actions"]["press"]["quantities"]["contact_area_mm2"]
    assert q["n"] == len(areas) and q["median"] == pytest.approx(np.median(areas), rel=1e-6)
    assert q["p5"] <= q["median"] <= q["p95"]
    # the text form prints the table
    assert main(["verify", str(tiny), "--no-decode", "--stats", "--stats-out", str(out), "--no-sheet"]) == 0
    text = capsys.readouterr().out
    assert "| contact area | mm^2 | peak force |" in text and "sequences checked: OK" in text


@pytest.mark.parametrize("args,msg", [(["--crop", "0.5"], "add --stats"), (["--stats", "--crop", "1.5"], "crop")])
def test_verify_stats_bad_options_one_line_exit_2(tiny, capsys, args, msg):
    assert main(["verify", str(tiny), "--no-decode", *args]) == 2
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1


@pytest.mark.parametrize("args,msg", [
    (["--fabrics", "101"], "fabrics"),
    (["--fabrics", "0"], "fabrics"),
    (["--profile", "nosuch"], "unknown sensor profile"),
    (["--actions", "7:1"], "--actions"),
    (["--frames", "36-25"], "inverted"),
    (["--precontact", "30-40"], "precontact"),
    (["--units", "-1"], "--units"),
    (["--device", "cpu"], "--backend torch"),
    (["--backend", "torch", "--batch", "0"], "--batch"),
    (["--backend", "torch", "--device", "tpu"], "--device"),
])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, args, msg):
    out = tmp_path / "never"
    code = main(["generate", "--out", str(out), *args])
    err = capsys.readouterr().err
    assert code == 2
    assert msg in err and err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_units_need_a_profile_with_unit_ranges(tmp_path, capsys):
    """--units on a profile without [unit_variation]: one line, exit 2, nothing written."""
    text = (SENSORS_DIR / "vitac.toml").read_text()
    plain = tmp_path / "plain.toml"
    plain.write_text(text.split("[unit_variation]")[0])
    out = tmp_path / "never"
    assert main(["generate", "--out", str(out), "--units", "2", "--profile", str(plain)]) == 2
    err = capsys.readouterr().err
    assert "unit_variation" in err and err.count("\n") == 1 and not out.exists()


def test_foreign_directory_is_refused_and_untouched(tmp_path, capsys):
    d = tmp_path / "mine"
    d.mkdir()
    (d / "thesis.tex").write_text("precious")
    assert main(["generate", "--out", str(d), *TINY]) == 2
    assert "not a gelsim dataset" in capsys.readouterr().err
    assert [p.name for p in d.iterdir()] == ["thesis.tex"]


def test_other_options_refused_on_existing_dataset(tiny, capsys):
    before = (tiny / "manifest.json").read_bytes()
    assert main(["generate", "--out", str(tiny), *TINY, "--seed", "5"]) == 2
    assert "other options" in capsys.readouterr().err
    assert (tiny / "manifest.json").read_bytes() == before


def test_dry_run_writes_nothing(tmp_path, capsys):
    out = tmp_path / "dry"
    assert main(["generate", "--out", str(out), "--dry-run", "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["sequences"] == 5000 and plan["estimated_bytes"] > 0 and plan["estimated_seconds"] > 0
    assert plan["actions"] == {"press": 3500, "slip": 500, "twist": 1000}
    assert not out.exists()
    # the estimate is the default level's, at the profile's 960x720, on the workers asked for
    from gelsim.fidelity import get_fidelity

    assert main(["generate", "--out", str(out), "--dry-run", "--json", "--workers", "2"]) == 0
    two = json.loads(capsys.readouterr().out)
    assert two["workers"] == 2 and two["resolution"] == [960, 720]
    assert two["estimated_seconds"] == round(get_fidelity().estimate_seconds(two["frames"], 960, 720, 2), 1)
    assert not out.exists()


def test_a_dataset_made_before_an_option_existed_resumes(tiny, tmp_path, capsys):
    """A manifest without the newer `split` option reads as the default split: rerunning the same
    command resumes instead of refusing the directory; another split is refused, one line, exit 2."""
    import shutil

    out = tmp_path / "old"
    shutil.copytree(tiny, out)
    m = json.loads((out / "manifest.json").read_text())
    del m["options"]["split"]
    (out / "manifest.json").write_text(json.dumps(m))
    capsys.readouterr()
    assert _gen(out) == 0
    assert _gen(out, "--split", "1:1:1") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("gelsim: error: --out") and "(split)" in err[-1]


def _check_resume_refused(tiny, tmp_path, capsys, field, value, says):
    """A copy of ``tiny`` whose manifest's ``field`` is ``value`` (made elsewhere) is refused on resume: one
    line holding each of ``says``, exit 2, the manifest untouched; a Ray node refuses its task the same way,
    before writing anything. Without the field (a manifest from before it) the resume goes ahead."""
    import shutil

    from gelsim import dataset

    m = load_manifest(tiny)
    out = tmp_path / "other"
    shutil.copytree(tiny, out)
    m[field] = value
    (out / "manifest.json").write_text(json.dumps(m))
    before = (out / "manifest.json").read_bytes()
    capsys.readouterr()
    assert _gen(out) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(x in err[0] for x in says), err
    assert (out / "manifest.json").read_bytes() == before
    with pytest.raises(GelsimError, match=says[-1]):
        dataset.ray_sequences(dataset.GenerateConfig(), str(out), [])
    del m[field]
    (out / "manifest.json").write_text(json.dumps(m))
    assert _gen(out) == 0
    return load_manifest(out)


def test_the_manifest_records_the_libraries_and_resume_refuses_others(tiny, tmp_path, capsys):
    """Another OpenCV (4.14 against 5.0) gives other heightfields, contacts, labels and frames from the
    same seed, so the manifest records the numeric libraries' versions and a resume under others is
    refused (one line naming them, exit 2, nothing touched); a manifest from before the field resumes."""
    from gelsim import dataset, schema

    m = load_manifest(tiny)
    assert m["libraries"] == dataset.library_versions() and list(m["libraries"]) == list(schema.LIBRARIES)
    _check_resume_refused(tiny, tmp_path, capsys, "libraries", {**m["libraries"], "opencv": "4.14.0"},
                          ("opencv 4.14.0 (here ", "other library versions"))


def test_resume_refuses_a_dataset_begun_by_other_code(tiny, tmp_path, capsys):
    """Other gelsim code (a changed imprint, say) gives other sequences from the same seed: the manifest
    records the code's digest, and a resume under other code is refused (one line, exit 2, nothing
    touched), on the driver and on a Ray node; a manifest from before the field resumes."""
    from gelsim.provenance import source_digest

    assert load_manifest(tiny)["source"] == source_digest() and len(source_digest()) == 64
    resumed = _check_resume_refused(tiny, tmp_path, capsys, "source", "0" * 64,
                                    ("--replace-stale", "other gelsim code"))
    assert resumed["source"] == source_digest()
    # a run interrupted under other code is to be finished by that code
    m = {**resumed, "source": "0" * 64, "complete": False}
    (tmp_path / "other" / "manifest.json").write_text(json.dumps(m))
    capsys.readouterr()
    assert _gen(tmp_path / "other") == 2
    assert "finish it with the code that began it" in capsys.readouterr().err


def dataset_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def test_dry_run_says_what_happens_to_out(tiny, tmp_path, capsys):
    """The dry run reads --out as the run would: new, complete, resumed (with the time for the frames to
    go), or refused with the run's own line (exit 2); with --replace-stale it names where the stale
    dataset would go. Nothing is written or moved."""
    import shutil

    def dry(out, *extra):
        capsys.readouterr()
        rc = _gen(out, "--dry-run", "--json", *extra)
        cap = capsys.readouterr()
        return rc, (json.loads(cap.out) if rc == 0 else cap.err)

    rc, plan = dry(tmp_path / "new")
    assert rc == 0 and plan["out_state"] == {"state": "new", "done": 0, "total": 6, "frames_to_go": plan["frames"]}
    rc, plan = dry(tiny)
    assert rc == 0 and plan["out_state"]["state"] == "complete" and plan["out_state"]["frames_to_go"] == 0
    assert plan["estimated_seconds"] == 0 and plan["estimated_bytes"] == 0
    out = tmp_path / "half"
    shutil.copytree(tiny, out)
    m = load_manifest(out)
    gone = m["sequences"][0]
    (out / gone["video"]).unlink()                                  # one sequence to redo
    rc, plan = dry(out)
    st = plan["out_state"]
    assert rc == 0 and st["state"] == "resume" and (st["done"], st["total"]) == (5, 6)
    assert st["frames_to_go"] == gone["num_frames"]
    from gelsim.fidelity import get_fidelity

    w, h = plan["resolution"]
    assert plan["estimated_seconds"] == round(get_fidelity("fast").estimate_seconds(st["frames_to_go"], w, h, 1), 1)
    assert 0 < plan["estimated_bytes"] < dataset_bytes(tiny)
    m["source"] = "0" * 64
    (out / "manifest.json").write_text(json.dumps(m))
    before = sorted(p.name for p in out.iterdir())
    rc, err = dry(out)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "other gelsim code" in err
    rc, plan = dry(out, "--replace-stale")
    assert rc == 0 and plan["out_state"]["state"] == "replace"
    assert plan["out_state"]["moved_to"] == str(out.with_name("half.stale-1"))
    assert sorted(p.name for p in out.iterdir()) == before and not out.with_name("half.stale-1").exists()


def test_replace_stale_sets_a_stale_dataset_aside_and_nothing_else(tiny, tmp_path, capsys):
    """--replace-stale renames a dataset made by other code (or options) to DIR.stale-N, the first free
    N, keeping every file, and makes the dataset anew; a resumable dataset is resumed in place, and a
    directory that is not a gelsim dataset is refused and left alone (exit 2)."""
    import shutil

    from gelsim import dataset

    out = tmp_path / "ds"
    shutil.copytree(tiny, out)
    m = load_manifest(out)
    # resumable: nothing moves
    assert _gen(out, "--replace-stale") == 0 and not out.with_name("ds.stale-1").exists()
    # made by other code: renamed whole, twice to two places
    for n in (1, 2):
        m["source"] = "0" * 64
        (out / "manifest.json").write_text(json.dumps(m))
        files = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
        capsys.readouterr()
        assert _gen(out, "--replace-stale") == 0
        assert f"moved to {out.with_name(f'ds.stale-{n}')}" in capsys.readouterr().err
        old = out.with_name(f"ds.stale-{n}")
        assert sorted(str(p.relative_to(old)) for p in old.rglob("*")) == files
        assert json.loads((old / "manifest.json").read_text())["source"] == "0" * 64
        assert _contents(out) == _contents(tiny)                    # made anew: the same dataset
    # made with other options: also stale
    assert dataset.set_aside_stale(out, dataset.GenerateConfig(fabrics=1)) == out.with_name("ds.stale-3")
    assert not out.exists()
    assert _gen(out) == 0
    # bad input alongside: refused before anything is moved
    m = load_manifest(out)
    m["source"] = "0" * 64
    (out / "manifest.json").write_text(json.dumps(m))
    capsys.readouterr()
    assert _gen(out, "--replace-stale", "--backend", "torch", "--device", "tpu") == 2
    with pytest.raises(GelsimError, match="--format"):
        dataset.generate(dataset.GenerateConfig(format="gif"), out, replace_stale=True)
    assert out.exists() and not out.with_name("ds.stale-4").exists()
    # not a dataset: never moved
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert _gen(junk, "--replace-stale") == 2
    assert "not a gelsim dataset" in capsys.readouterr().err and (junk / "notes.txt").read_text() == "mine"
    assert not junk.with_name("junk.stale-1").exists()


def _frames(root: Path, seq: dict) -> np.ndarray:
    from gelsim.video import read_video

    return np.asarray(read_video(root / seq["video"]), np.int16)


def test_torch_backend_same_labels_frames_within_tolerance_same_bytes_for_any_batch(tmp_path, capsys):
    """--backend torch writes the fast backend's dataset: the labels byte for byte, the frames within the
    backend's stated tolerance (PNG frames, so that the codec does not blur the comparison), and the same
    bytes for any --batch; the manifest records the backend, not the device or the batch."""
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, TOL_MEAN_DN

    pytest.importorskip("torch")
    args = ["--fabrics", "2", "--sequences-per-fabric", "2", "--format", "png"]
    assert _gen(tmp_path / "fast", *args) == 0
    assert _gen(tmp_path / "b1", *args, "--backend", "torch", "--device", "cpu", "--batch", "1") == 0
    assert _gen(tmp_path / "b4", *args, "--backend", "torch", "--batch", "4", workers=2) == 0
    fast, b1, b4 = (load_manifest(tmp_path / n) for n in ("fast", "b1", "b4"))
    assert b1["sequences"] == b4["sequences"]                      # every checksum: the same bytes
    assert b1["options"] == {**fast["options"], "backend": "torch"} and "device" not in b1["options"]
    changed = 0
    for f, t in zip(fast["sequences"], b1["sequences"]):
        assert f["sha256"]["labels"] == t["sha256"]["labels"]
        a, b = _frames(tmp_path / "fast", f), _frames(tmp_path / "b1", t)
        err = np.abs(a - b)
        assert err.max() <= TOL_MAX_UINT8_DN and err.mean() < TOL_MEAN_DN, (f["id"], err.max(), err.mean())
        changed += int(np.abs(a - a[:1]).max() > 10)                 # the sequence shows a press
    assert changed >= 3
    # a torch dataset is not resumed by the fast backend, and says why
    capsys.readouterr()
    assert _gen(tmp_path / "b1", *args) == 2
    assert "(backend)" in capsys.readouterr().err


def test_device_cuda_writes_the_fast_dataset(tmp_path):  # pragma: no cover - runs only on a GPU machine
    """--device cuda writes the fast backend's labels byte for byte and its frames within the torch
    backend's tolerance, and the same bytes for any --batch (and --workers): issue #16 on a GPU."""
    torch = pytest.importorskip("torch")
    from gelsim.optics.torch_backend import TOL_MAX_UINT8_DN, TOL_MEAN_DN

    if not torch.cuda.is_available():
        pytest.skip("no CUDA device here (CI has none)")
    args = ["--fabrics", "2", "--sequences-per-fabric", "2", "--format", "png"]
    assert _gen(tmp_path / "fast", *args) == 0
    assert _gen(tmp_path / "g1", *args, "--backend", "torch", "--device", "cuda", "--batch", "1") == 0
    assert _gen(tmp_path / "g16", *args, "--backend", "torch", "--device", "cuda", "--batch", "16", workers=2) == 0
    fast, g1, g16 = (load_manifest(tmp_path / n) for n in ("fast", "g1", "g16"))
    assert g1["sequences"] == g16["sequences"]
    for f, t in zip(fast["sequences"], g1["sequences"]):
        assert f["sha256"]["labels"] == t["sha256"]["labels"]
        err = np.abs(_frames(tmp_path / "fast", f) - _frames(tmp_path / "g1", t))
        assert err.max() <= TOL_MAX_UINT8_DN and err.mean() < TOL_MEAN_DN, (f["id"], err.max(), err.mean())


def test_device_cuda_without_cuda_is_one_line_exit_2(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    out = tmp_path / "never"
    assert main(["generate", "--out", str(out), *TINY, "--backend", "torch", "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no CUDA device on this machine" in err and "--device cpu" in err
    assert not out.exists()
