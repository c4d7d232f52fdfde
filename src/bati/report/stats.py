"""rliable-style aggregate statistics in numpy: IQM, stratified bootstrap CIs, probability of improvement.

Why not the `rliable` package: rliable 1.2.0 installs but fails to import with this environment's
pandas 3 (its dependency `arch` 7.2 calls pandas' `deprecate_kwarg` with an older signature). The
three estimators we need are a few lines each; they follow rliable's definitions (Agarwal et al.
2021, "Deep RL at the edge of the statistical precipice"):

- IQM: the 25% trimmed mean of all scores of a method (runs x tasks flattened), as
  `scipy.stats.trim_mean(scores, 0.25, axis=None)`: with n scores, int(0.25 n) are cut at each end.
- Stratified bootstrap: each replicate resamples the runs with replacement independently within
  every task (stratum), recomputes the statistic; the 95% interval is the 2.5 / 97.5 percentiles of
  the replicates (rliable's default "percentile" method).
- Probability of improvement P(X > Y): per task, the Mann-Whitney U statistic normalised to [0, 1]
  (pairs of runs with X > Y count 1, ties 1/2), averaged over tasks; its interval resamples X's and
  Y's runs independently within every task.

Everything is deterministic: the bootstrap uses `np.random.default_rng(seed)` (seed 0 by default).
Score matrices are (runs, tasks) arrays; a single number per run is a (runs, 1) matrix.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import trim_mean

BOOTSTRAP_REPS = 2_000
CONFIDENCE = 0.95


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of all entries of a (runs, tasks) score matrix."""
    return float(trim_mean(np.asarray(scores, dtype=float), proportiontocut=0.25, axis=None))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y): per task the fraction of run pairs with x > y (ties count 1/2), averaged over tasks."""
    x, y = _matrix(x), _matrix(y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"score matrices cover different numbers of tasks: {x.shape[1]} and {y.shape[1]}")
    per_task = [((xt[:, None] > yt[None, :]) + 0.5 * (xt[:, None] == yt[None, :])).mean()
                for xt, yt in zip(x.T, y.T)]
    return float(np.mean(per_task))


def _matrix(scores) -> np.ndarray:
    scores = np.asarray(scores, dtype=float)
    return scores[:, None] if scores.ndim == 1 else scores


def _resample(scores: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One stratified bootstrap replicate: runs resampled with replacement within each task (column)."""
    runs, tasks = scores.shape
    rows = rng.integers(0, runs, size=(runs, tasks))
    return scores[rows, np.arange(tasks)[None, :]]


def _interval(replicates: list[float]) -> tuple[float, float]:
    tail = 100 * (1 - CONFIDENCE) / 2
    low, high = np.percentile(replicates, [tail, 100 - tail])
    return float(low), float(high)


def iqm_interval(scores, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """IQM and its 95% stratified-bootstrap percentile interval: (iqm, low, high)."""
    scores = _matrix(scores)
    rng = np.random.default_rng(seed)
    return (iqm(scores), *_interval([iqm(_resample(scores, rng)) for _ in range(reps)]))


def improvement_interval(x, y, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """P(X > Y) and its 95% stratified-bootstrap interval (X's and Y's runs resampled independently)."""
    x, y = _matrix(x), _matrix(y)
    rng = np.random.default_rng(seed)
    reps_ = [probability_of_improvement(_resample(x, rng), _resample(y, rng)) for _ in range(reps)]
    return (probability_of_improvement(x, y), *_interval(reps_))
