"""The statistics stam reports, one implementation each: Wilson intervals of a rate, bootstrap
intervals over test sequences (cell accuracies, paired differences, ratios), and how many test
sequences a comparison needs.

The evaluation reuses the same test sequences for every model, n, setting and seed. A statistic is
therefore a mean over the N test sequences of a per-sequence quantity (a sequence's correctness
averaged over the seeds, or the difference of two such), and its interval comes from resampling
the sequences, the same resamples for every statistic, so that differences stay paired. Seeds
also shift a cell's accuracy as a whole, which resampling the sequences cannot see: that shift's
variance is measured across the seeds (:func:`seed_variance_ratio`) and added to each interval
(:func:`widen`). Fractions in, fractions out (0-1); callers convert to percent.
"""
from __future__ import annotations

import math

import numpy as np

from .errors import StamError

CI_LEVEL = 0.95
Z95 = 1.959963984540054  # two-sided 95% quantile of the standard normal
# 10,000 resamples: the Monte Carlo error of a 2.5% or 97.5% quantile is then under 1% of the
# interval's width (sqrt(0.025 * 0.975 / B) / phi(1.96) = 0.027 sigma, against a width of 3.9 sigma).
BOOTSTRAP_RESAMPLES = 10_000
# Fixed, so that the intervals are deterministic and every statistic of a run sees the same resamples.
BOOTSTRAP_SEED = 20200
_CHUNK = 1000  # resamples drawn at a time: a (chunk, N) count matrix, 9 MB at N = 1,100

# For planning a test split before any run: the variance over sequences of the per-sequence
# difference in correctness between two models. 0.25 is two single-seed models whose correctness
# differs on a quarter of the sequences (the difference is then -1, 0 or +1); averaging over seeds
# lowers it, two independent models at 50% accuracy have 0.5, and it cannot exceed 1. The
# experiment reports the half-width it measured.
PLANNING_DIFFERENCE_VARIANCE = 0.25
# Below this many test sequences the experiment warns: a paired difference's 95% half-width is then
# 4.4 points or more at the planning variance, as large as the paper's attention gains (1-5 points).
MIN_TEST_SEQUENCES = 500


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float] | None:
    """Wilson score interval of a proportion k/n (z = 1.96: 95%); None for n = 0. Unlike the
    normal approximation it stays inside [0, 1] when k is 0 or n."""
    if n <= 0:
        return None
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def bootstrap_means(columns: np.ndarray, *, resamples: int = BOOTSTRAP_RESAMPLES,
                    seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """Means of each column over ``resamples`` bootstrap resamples of the rows (drawn with
    replacement, as many as there are rows).

    ``columns``: ``float (N,)`` or ``(N, K)``, one row per test sequence. Every column sees the same
    resampled rows, so the replicates of two columns are paired. Returns ``float (resamples,)`` or
    ``(resamples, K)``; deterministic for a given ``seed``.

    The rows are resampled as one pool, not within fabrics. Resampling within fabrics would match a
    split with a fixed number of sequences per fabric, but it scales the variance inside each fabric
    by (n - 1) / n for n sequences per fabric (too narrow by 1/11 at 11, zero width at one per
    fabric); the plain bootstrap errs on the wide side instead, by the spread between fabrics.
    """
    values = np.asarray(columns, float)
    flat = values.ndim == 1
    values = values[:, None] if flat else values
    n = values.shape[0]
    if n == 0:
        raise StamError("bootstrap of zero rows; give at least one test sequence")
    rng = np.random.default_rng(seed)
    out = []
    for start in range(0, resamples, _CHUNK):
        b = min(_CHUNK, resamples - start)
        rows = rng.integers(0, n, (b, n))
        # How often each row is drawn in each resample: one bincount over (resample, row) pairs.
        counts = np.bincount((rows + n * np.arange(b)[:, None]).ravel(), minlength=b * n).reshape(b, n)
        out.append(counts @ values / n)
    reps = np.concatenate(out)
    return reps[:, 0] if flat else reps


def percentile_interval(replicates: np.ndarray, level: float = CI_LEVEL) -> tuple[float, float]:
    """The central ``level`` interval of bootstrap replicates (percentile method)."""
    lo, hi = np.quantile(np.asarray(replicates, float), [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def bootstrap_intervals(columns: np.ndarray, *, level: float = CI_LEVEL,
                        resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """Mean and bootstrap interval of each column of ``float (N, K)``: ``float (K, 3)`` rows of
    (mean, low, high). A column of per-sequence differences gives a paired difference's interval."""
    values = np.asarray(columns, float)
    reps = bootstrap_means(values, resamples=resamples, seed=seed)
    return np.array([(values[:, k].mean(), *percentile_interval(reps[:, k], level)) for k in range(values.shape[1])])


def bootstrap_ci(values: np.ndarray, **kw) -> tuple[float, float, float]:
    """(mean, low, high) of one per-sequence quantity ``float (N,)``; keywords as
    :func:`bootstrap_intervals`."""
    mean, lo, hi = bootstrap_intervals(np.asarray(values, float)[:, None], **kw)[0]
    return float(mean), float(lo), float(hi)


def ratio_ci(numerator: np.ndarray, denominator: np.ndarray, *,
             level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
             seed: int = BOOTSTRAP_SEED) -> tuple[float, float, float] | None:
    """(ratio, low, high) of mean(numerator) / mean(denominator), both ``float (N,)`` over the same
    sequences, resampled together; None when the denominator's mean is 0."""
    both = np.stack([np.asarray(numerator, float), np.asarray(denominator, float)], axis=1)
    if both[:, 1].mean() == 0:
        return None
    reps = bootstrap_means(both, resamples=resamples, seed=seed)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = reps[:, 0] / reps[:, 1]
    return (float(both[:, 0].mean() / both[:, 1].mean()), *percentile_interval(ratios, level))


def paired_halfwidth(n: int, variance: float = PLANNING_DIFFERENCE_VARIANCE, z: float = Z95) -> float:
    """Half-width (fraction) of the normal-approximation interval of a mean over ``n`` sequences of a
    per-sequence quantity with this variance: z sqrt(variance / n). With ``variance = p (1 - p)`` it
    is the interval of one accuracy p."""
    return z * math.sqrt(variance / n)


def required_test_size(difference: float, variance: float = PLANNING_DIFFERENCE_VARIANCE, z: float = Z95) -> int:
    """Test sequences needed for a paired difference of ``difference`` (fraction, e.g. 0.03 for 3
    points) to equal its interval's half-width: ceil((z / difference)^2 variance)."""
    return math.ceil((z / difference) ** 2 * variance)


def seed_variance_ratio(correct_by_cell: list[np.ndarray]) -> dict:
    """Whether seeds shift accuracy beyond what per-sequence flips explain.

    ``correct_by_cell``: per cell, ``0/1 (S, N)`` correctness of S seeds on N sequences. If the
    seeds' training noise flips sequences independently, the variance over seeds of a cell's
    accuracy is the mean over sequences of each sequence's variance over seeds, divided by N.
    Returns the observed and that expected variance, summed over cells with S >= 2, and their
    ratio: near 1, the bootstrap over sequences (of correctness averaged over seeds) covers the
    seed-to-seed variation; well above 1, seeds shift all sequences together, which that bootstrap
    cannot see. None when no cell has two seeds or no sequence ever flips.

    ``shift_variance``: that shared shift's variance per cell (fraction^2), pooled over the cells,
    (observed - expected) / cells, and 0 when negative. In the model ``correct[s, i] = a_i + b_s +
    e_si`` the observed term estimates ``var(b) + var(e) / N`` and the expected one
    ``(var(b) + var(e)) / N``, so their difference is ``var(b) (1 - 1/N)``: what :func:`widen` adds
    (divided by S) to an interval from the bootstrap over sequences.
    """
    observed = expected = 0.0
    cells = 0
    for c in correct_by_cell:
        c = np.asarray(c, float)
        if c.ndim != 2 or c.shape[0] < 2:
            continue
        observed += float(c.mean(1).var(ddof=1))
        expected += float(c.var(0, ddof=1).mean() / c.shape[1])
        cells += 1
    return {"cells": cells, "observed_variance": observed, "expected_variance": expected,
            "ratio": observed / expected if cells and expected > 0 else None,
            "shift_variance": max(0.0, (observed - expected) / cells) if cells else 0.0}


def widen(mean: float, low: float, high: float, variance: float, z: float = Z95) -> tuple[float, float]:
    """An interval ``(low, high)`` around ``mean`` with an independent error of this ``variance`` added:
    each side's distance from the mean grows in quadrature by ``z sqrt(variance)``. The seeds' shared
    shift (:func:`seed_variance_ratio`) is added to the bootstrap's intervals this way."""
    extra = z * z * max(0.0, variance)
    return (mean - math.sqrt((mean - low) ** 2 + extra), mean + math.sqrt((high - mean) ** 2 + extra))
