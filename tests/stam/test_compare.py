"""stam.compare on made-up sweeps written as `stam experiment` writes its cells: paired differences
between two runs, the change in attention's gain, and the refusals."""
import json

import numpy as np
import pytest

from stam import cli
from stam.compare import compare_runs, markdown
from stam.errors import StamError

IDS = [f"f{f:03d}-s{k:04d}" for f in range(20) for k in range(10)]  # 200 test sequences


def _write_run(root, correct, ids=IDS, seed=0):
    """A sweep directory whose cell (setting, n, model, seed) got ``correct[(setting, n, model)]`` (0/1 over
    ``ids``; one array for every seed, or a list with one per seed), each cell listing the sequences in its
    own order."""
    rng = np.random.default_rng(seed)
    for (setting, n, model), c in correct.items():
        per_seed = c if isinstance(c, list) else [c] * 3
        for s, cs in enumerate(per_seed):
            order = rng.permutation(len(ids))
            d = root / "cells" / setting / f"n{n}" / model / f"seed{s}"
            d.mkdir(parents=True)
            (d / "result.json").write_text(json.dumps({
                "setting": setting, "frames": n, "model": model, "seed": s, "test_acc": float(np.mean(cs)),
                "test_ids": [ids[i] for i in order], "test_correct": [int(cs[i]) for i in order]}))
    return root


def _base(p_cnn=0.3, seed=1):
    rng = np.random.default_rng(seed)
    u = rng.random(len(IDS))
    out = {}
    for setting in ("clean", "noisy"):
        for n in (2, 3):
            for m in ("cnn", "cnn_sa", "stam"):
                out[(setting, n, m)] = (u < p_cnn).astype(int)
    return out


def test_identical_runs_differ_by_nothing(tmp_path):
    a = _write_run(tmp_path / "a", _base())
    b = _write_run(tmp_path / "b", _base(), seed=5)  # the same results, listed in other orders
    res = compare_runs(a, b)
    assert res["test_sequences"] == len(IDS) and res["seeds"] == {"a": 3, "b": 3}
    assert len(res["cells"]) == 12 and res["all_cells"]["cells"] == 12
    for row in res["cells"] + res["means"] + res["gains"]:
        assert row["difference"]["mean"] == 0.0 and not row["difference"]["resolved"]
    assert res["all_cells"]["difference"]["ci95"] == [0.0, 0.0]  # no flips and no seed shift: nothing to widen


def test_a_change_in_one_model_is_measured_paired_and_moves_its_gain(tmp_path):
    base = _base()
    b_cells = {k: v.copy() for k, v in base.items()}
    wrong = np.flatnonzero(base[("clean", 2, "stam")] == 0)
    # B's STAM gets 30 more sequences right at clean n = 2 (15 points on 200), nothing else changes.
    b_cells[("clean", 2, "stam")][wrong[:30]] = 1
    res = compare_runs(_write_run(tmp_path / "a", base), _write_run(tmp_path / "b", b_cells))
    cell = {(c["setting"], c["frames"], c["model"]): c for c in res["cells"]}
    d = cell[("clean", 2, "stam")]
    assert d["b"] - d["a"] == pytest.approx(15.0)
    assert d["difference"]["mean"] == pytest.approx(15.0) and d["difference"]["resolved"]
    lo, hi = d["difference"]["ci95"]
    assert 8.0 < lo < 15.0 < hi < 22.0  # sqrt(p (1 - p) / N) with p = 0.15: a 5-point half-width
    assert cell[("clean", 3, "stam")]["difference"]["mean"] == 0.0
    gains = {(g["setting"], g["model"]): g for g in res["gains"]}
    assert gains[("clean", "stam")]["a"]["mean"] == 0.0
    assert gains[("clean", "stam")]["b"]["mean"] == pytest.approx(7.5)  # averaged over n = 2, 3
    assert gains[("clean", "stam")]["difference"]["mean"] == pytest.approx(7.5)
    assert gains[("noisy", "stam")]["difference"]["mean"] == 0.0
    assert res["all_cells"]["difference"]["mean"] == pytest.approx(15.0 / 12)
    text = markdown(res)
    assert "**+15.0 [" in text and "STAM − CNN, clean" in text and "All 12 shared cells" in text


def test_the_seeds_shared_shift_widens_the_intervals(tmp_path):
    rng = np.random.default_rng(3)
    u = rng.random(len(IDS))
    # Seeds that move a whole cell's threshold by several points: the shift no bootstrap over sequences sees.
    shifted = {k: [(u < 0.3 + d).astype(int) for d in (-0.06, 0.0, 0.06)] for k in _base()}
    steady = {k: [(u < 0.3).astype(int)] * 3 for k in _base()}
    b = {k: [(u < 0.35).astype(int)] * 3 for k in _base()}
    wide = compare_runs(_write_run(tmp_path / "a1", shifted), _write_run(tmp_path / "b1", b))
    narrow = compare_runs(_write_run(tmp_path / "a2", steady), _write_run(tmp_path / "b2", b))
    assert wide["shift_variance"]["a"] > 0 and narrow["shift_variance"]["a"] == 0
    w, n = (r["cells"][0]["difference"] for r in (wide, narrow))
    assert w["mean"] == pytest.approx(n["mean"], abs=1.0)  # (the shifted seeds average to about the same)
    assert w["ci95"][1] - w["ci95"][0] > 1.5 * (n["ci95"][1] - n["ci95"][0])


def test_runs_on_other_sequences_or_without_cells_are_refused(tmp_path):
    a = _write_run(tmp_path / "a", _base())
    other = _write_run(tmp_path / "b", _base(), ids=[i.replace("-s", "-t") for i in IDS])
    with pytest.raises(StamError, match="different sequences"):
        compare_runs(a, other)
    (tmp_path / "empty").mkdir()
    with pytest.raises(StamError, match="no finished cells"):
        compare_runs(a, tmp_path / "empty")
    disjoint = _write_run(tmp_path / "c", {("clean", 5, "cnn"): _base()[("clean", 2, "cnn")]})
    with pytest.raises(StamError, match="no cell"):
        compare_runs(a, disjoint)


def test_cli_writes_the_markdown_and_fails_in_one_line(tmp_path, capsys):
    a = _write_run(tmp_path / "a", _base())
    b = _write_run(tmp_path / "b", _base(p_cnn=0.4))
    out = tmp_path / "cmp" / "b-vs-a.md"
    assert cli.main(["compare", str(a), str(b), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["markdown"] == str(out) and out.read_text().startswith("Run B (b) against run A (a)")
    assert all(r["difference"]["resolved"] for r in doc["means"])  # 10 points on 200 sequences, every cell
    assert cli.main(["compare", str(a), str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no finished cells" in err[0]
