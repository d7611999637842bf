"""stam.experiment's analysis on made-up cells: accuracies, paired differences and ratios with
their intervals, and the markdown they are written as (the tiny end-to-end run is in test_cli)."""
import json

import numpy as np
import pytest

from stam.experiment import analyse, markdown_differences

FRAMES = [2, 3]
MODELS = ["cnn", "cnn_sa", "stam"]
SETTINGS = ["clean", "noisy"]


def _cells(seed=0, fabrics=20, per_fabric=10, seeds=3, shift=0.0):
    """CNN right on about 30% (clean) or 20% (noisy) of the sequences, each seed flipping some and,
    with ``shift``, moving its whole threshold by N(0, shift); CNN+SA exactly as CNN; STAM as CNN and
    also right on 60 sequences CNN gets wrong in every seed."""
    rng = np.random.default_rng(seed)
    ids = [f"f{f:03d}-s{k:04d}" for f in range(fabrics) for k in range(per_fabric)]
    n = len(ids)
    easy = rng.random(n)
    extra = rng.permutation(np.flatnonzero(easy >= 0.45))[:60]
    cells = []
    for setting, p in (("clean", 0.3), ("noisy", 0.2)):
        for frames in FRAMES:
            for s in range(seeds):
                cnn = (easy < p + (shift * rng.normal() if shift else 0.0) + 0.05 * (rng.random(n) - 0.5)).astype(int)
                stam = cnn.copy()
                stam[extra] = 1
                for model, correct in (("cnn", cnn), ("cnn_sa", cnn), ("stam", stam)):
                    order = rng.permutation(n)  # each cell lists the sequences in its own order
                    cells.append({"setting": setting, "frames": frames, "model": model, "seed": s,
                                  "test_ids": [ids[i] for i in order],
                                  "test_correct": [int(correct[i]) for i in order]})
    return cells, ids


def test_analyse_accuracies_differences_and_ratios():
    cells, ids = _cells()
    a = analyse(cells, MODELS, FRAMES, SETTINGS, ids)
    json.dumps(a)  # plain Python types all through
    assert a == analyse(cells, MODELS, FRAMES, SETTINGS, ids)  # deterministic

    row = a["tables"]["clean"]["cnn"][2]
    assert row["seeds"] == 3 and row["mean"] == pytest.approx(np.mean(row["values"]))
    assert row["ci95"][0] < row["mean"] < row["ci95"][1] and row["paper"] == 67.23
    # About the binomial width at 200 sequences (a little narrower: seeds averaged).
    assert 4 < row["ci95"][1] - row["ci95"][0] < 2 * 1.96 * 100 * np.sqrt(0.3 * 0.7 / 200) * 1.1

    by = {(d["difference"], d["frames"]): d for d in a["differences"]}
    same = by[("CNN+SA − CNN, clean", 2)]
    assert same["mean"] == 0 and same["ci95"] == [0, 0] and not same["resolved"]
    assert same["paper"] == pytest.approx(72.12 - 67.23)
    gain = by[("STAM − CNN, noisy", "mean")]
    assert gain["mean"] == pytest.approx(30.0) and gain["resolved"] and gain["ci95"][0] > 20
    assert gain["paper"] == pytest.approx(np.mean([72.00 - 53.20, 72.20 - 58.20]))
    drop = by[("noisy − clean, CNN", "mean")]
    assert drop["mean"] < 0 and drop["resolved"]
    # STAM gains the same 60 sequences in both settings: no robustness difference.
    assert by[("(STAM − CNN), noisy − clean", "mean")]["mean"] == pytest.approx(0, abs=1e-9)
    assert {d["kind"] for d in a["differences"]} == {"model", "setting", "robustness"}
    assert len(a["differences"]) == 9 * 3  # 9 rows x (n = 2, 3, mean)

    r = a["ratios"]["cnn"]
    clean = np.mean([a["tables"]["clean"]["cnn"][n]["mean"] for n in FRAMES])
    noisy = np.mean([a["tables"]["noisy"]["cnn"][n]["mean"] for n in FRAMES])
    assert r["ratio"] == pytest.approx(noisy / clean) and r["ci95"][1] < 1 and r["resolved"]
    assert r["paper"] == pytest.approx(np.mean([53.20, 58.20]) / np.mean([67.23, 72.04]))

    res = a["resolution"]
    assert res["test_sequences"] == 200 and res["seeds"] == 3
    assert res["paired_halfwidth_points"] > 0 and res["accuracy_halfwidth_points"] > 0
    # Seeds only flip sequences independently here.
    assert a["seed_check"]["cells"] == 12 and 0.5 < a["seed_check"]["ratio"] < 2


def test_markdown_differences():
    cells, ids = _cells()
    a = analyse(cells, MODELS, FRAMES, SETTINGS, ids)
    text = markdown_differences(a, FRAMES)
    lines = {l.split(" | ")[0]: l for l in text.splitlines() if l.startswith("| ")}
    assert lines["| Difference"] == "| Difference | n=2 | n=3 | mean over n |"
    assert lines["| CNN+SA − CNN, clean"].startswith("| CNN+SA − CNN, clean | +0.0 [+0.0, +0.0] (+4.89) |")
    assert "| **+30.0 [" in lines["| STAM − CNN, clean"]  # resolved: bold
    assert "Noisy/clean accuracy ratio" in text and "STAM **" in text
    assert a["resolution"]["statement"] in text and "Seed check:" in text
    assert "Resolved (CI excludes 0): 6 of 12 model − CNN, 9 of 9 noisy − clean, 0 of 6 (model − CNN) noisy − clean" in text


def test_analyse_without_a_baseline_or_both_settings():
    cells, ids = _cells(seeds=1)
    only = [c for c in cells if c["model"] == "stam" and c["setting"] == "clean"]
    a = analyse(only, ["stam"], FRAMES, ["clean"], ids)
    assert a["differences"] == [] and a["ratios"] == {} and a["seed_check"]["ratio"] is None
    assert "no two models were run" in a["resolution"]["statement"]
    assert set(a["tables"]["clean"]["stam"]) == set(FRAMES)


def test_intervals_include_the_seeds_shared_shift():
    from stam import stats

    cells, ids = _cells(shift=0.05)
    a = analyse(cells, MODELS, FRAMES, SETTINGS, ids)
    var = a["seed_check"]["shift_variance"]
    assert a["seed_check"]["ratio"] > 3 and 0.3 * 0.05 ** 2 < var < 3 * 0.05 ** 2
    # A cell: the bootstrap's interval over sequences, each side widened by the shift over 3 seeds.
    by_id = {}
    for c in cells:
        if (c["setting"], c["frames"], c["model"]) == ("clean", 2, "cnn"):
            by_id[c["seed"]] = dict(zip(c["test_ids"], c["test_correct"]))
    seed_avg = np.array([[by_id[s][i] for i in ids] for s in range(3)], float).mean(0)
    mean, lo, hi = stats.bootstrap_ci(seed_avg)
    row = a["tables"]["clean"]["cnn"][2]
    assert row["ci95"] == pytest.approx([100 * v for v in stats.widen(mean, lo, hi, var / 3)])
    assert row["ci95"][1] - row["ci95"][0] > 100 * (hi - lo) + 1
    # CNN+SA equals CNN seed for seed, but cells' seeds count as independent: an interval around 0
    # as wide as two cells' shifts, not resolved.
    same = {(d["difference"], d["frames"]): d for d in a["differences"]}[("CNN+SA − CNN, clean", 2)]
    half = 100 * 1.959963984540054 * np.sqrt(2 * var / 3)
    assert same["mean"] == 0 and same["ci95"] == pytest.approx([-half, half]) and not same["resolved"]


def test_precontact_cost_with_the_contact_frames_matched():
    # 200 sequences, n = 2..4. Onset 1 on the first 150 (noisy n holds clean k = n - 1 after one flat
    # frame), onset 3 on the next 30 (noisy n = 4 holds k = 1 contact frame: no such clean cell, so no
    # pair), no onset detected on the last 20. The CNN's noisy window is right exactly where its clean
    # window of k frames is (the flat frame costs nothing); STAM's noisy window is wrong on the first 30
    # sequences, whatever its clean window says. Both seeds agree (no seed shift).
    frames, n_seq = [2, 3, 4], 200
    ids = [f"f{i % 20:03d}-s{i:04d}" for i in range(n_seq)]
    onsets = {t: (1 if i < 150 else 3 if i < 180 else None) for i, t in enumerate(ids)}
    rng = np.random.default_rng(3)
    clean = {n: (rng.random(n_seq) < 0.2 + 0.1 * n).astype(int) for n in frames}
    cells = []
    for model in ("cnn", "stam"):
        for n in frames:
            noisy = rng.integers(0, 2, n_seq)                 # what sequences without a matched window get
            for i in range(150):
                noisy[i] = clean[n - 1][i] if n - 1 in clean else noisy[i]
            if model == "stam":
                noisy[:30] = 0
            for seed in range(2):
                for setting, correct in (("clean", clean[n]), ("noisy", noisy)):
                    cells.append({"setting": setting, "frames": n, "model": model, "seed": seed,
                                  "test_ids": ids, "test_correct": correct.tolist(),
                                  "test_predictions": [0] * n_seq, "test_acc": float(correct.mean())})
    a = analyse(cells, ["cnn", "stam"], frames, SETTINGS, ids, onsets)
    pc = a["precontact"]
    # pairs: onset 1 and n = 3, 4 (k = 2, 3) on 150 sequences; onset 3 leaves k = 1 (not run)
    assert pc["windows"] == 300 and pc["sequences"] == 150 and pc["onsets"] == [1]
    assert pc["models"]["cnn"]["mean"] == 0 and pc["models"]["cnn"]["ci95"] == [0, 0]
    clean_right = sum(clean[k][:30].sum() for k in (2, 3))
    assert pc["models"]["stam"]["mean"] == pytest.approx(-100 * clean_right / 300)
    assert pc["minus_cnn"]["stam"]["mean"] == pytest.approx(pc["models"]["stam"]["mean"])
    assert pc["minus_cnn"]["stam"]["resolved"] and not pc["models"]["cnn"]["resolved"]
    text = markdown_differences(a, frames)
    assert "Frames before contact, contact frames matched" in text and "over 300 windows of 150 sequences" in text
    # Without onsets (or without both settings) there is no such analysis.
    assert analyse(cells, ["cnn", "stam"], frames, SETTINGS, ids)["precontact"] is None


def test_precontact_against_extra_clean_cells():
    """With noisy n = 2, 4 and the clean setting also at n = 1, 3 (run for this), a window one frame before
    contact is costed against the clean window of n - 1 frames; Table I shows the extra n, the differences
    stay over the sweep's n."""
    n_seq, rng = 120, np.random.default_rng(5)
    ids = [f"f{i % 12:03d}-s{i:04d}" for i in range(n_seq)]
    clean = {k: (rng.random(n_seq) < 0.1 * k).astype(int) for k in (1, 2, 3, 4)}
    cells = []
    for k, c in clean.items():
        cells.append({"setting": "clean", "frames": k, "model": "cnn", "seed": 0, "test_ids": ids,
                      "test_correct": c.tolist()})
    for n in (2, 4):   # the frame before contact costs exactly the sequences 0..29 that the clean window gets right
        noisy = clean[n - 1].copy()
        noisy[:30] = 0
        cells.append({"setting": "noisy", "frames": n, "model": "cnn", "seed": 0, "test_ids": ids,
                      "test_correct": noisy.tolist()})
    a = analyse(cells, ["cnn"], [2, 4], SETTINGS, ids, {t: 1 for t in ids})
    pc = a["precontact"]
    assert pc["windows"] == 2 * n_seq and pc["onsets"] == [1]
    assert pc["models"]["cnn"]["mean"] == pytest.approx(-100 * (clean[1][:30].sum() + clean[3][:30].sum()) / 240)
    assert set(a["tables"]["clean"]["cnn"]) == {1, 2, 3, 4} and set(a["tables"]["noisy"]["cnn"]) == {2, 4}
    assert {d["frames"] for d in a["differences"]} == {2, 4, "mean"}
