"""Aggregate statistics through rliable (Agarwal et al. 2021, "Deep RL at the edge of the statistical
precipice"): IQM, stratified bootstrap CIs, probability of improvement, performance profiles.

Score matrices are (runs, tasks) arrays, rliable's layout; one number per run is a (runs, 1) matrix.
Here a "task" is whatever a report stratifies by: one family's table has one, the claims page's
cross-family numbers have one column per family. Every interval is a 95% percentile interval of
`BOOTSTRAP_REPS` stratified-bootstrap replicates (runs resampled within each column), drawn with
`seed`: the same scores and seed give the same numbers. The replicates are rliable's own draws, their
statistics computed for all replicates at once rather than in rliable's Python loop (the same intervals to 1e-12:
tests/test_report.py checks them against rliable.library.get_interval_estimates).

rliable is the `stats` extra (pinned with arch 7.2 and pandas < 3: arch 8 rejects rliable's
`random_state=None`, pandas 3 breaks arch 7); `require_rliable()` says so in one line before any work.
"""

from __future__ import annotations

import functools

import numpy as np

from bati.errors import BatiError

BOOTSTRAP_REPS = 2_000
CONFIDENCE = 0.95


def require_rliable() -> None:
    """BatiError (one line) unless rliable imports: reports need it."""
    try:
        import rliable.library  # noqa: F401
        import rliable.metrics  # noqa: F401
    except ImportError as err:
        raise BatiError(f"reports need rliable ({err}): pip install 'bati[stats]'") from err


def _matrix(scores) -> np.ndarray:
    scores = np.asarray(scores, dtype=float)
    return scores[:, None] if scores.ndim == 1 else scores


def iqm(scores) -> float:
    """Interquartile mean of all entries of a (runs, tasks) score matrix (rliable's aggregate_iqm)."""
    from rliable import metrics

    return float(metrics.aggregate_iqm(_matrix(scores)))


def probability_of_improvement(x, y) -> float:
    """P(X > Y): per task the fraction of run pairs with x > y (ties count 1/2), averaged over tasks."""
    from rliable import metrics

    x, y = _matrix(x), _matrix(y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"score matrices cover different numbers of tasks: {x.shape[1]} and {y.shape[1]}")
    return float(metrics.probability_of_improvement(x, y))


@functools.lru_cache(maxsize=64)
def _resamples(shapes: tuple[tuple[int, ...], ...], reps: int, seed: int) -> tuple[np.ndarray, ...]:
    """The run indices of `reps` stratified-bootstrap replicates of score matrices of these shapes: rliable 1.2's
    draws (per replicate, one `np.random.choice(runs, shape)` per matrix in order, from numpy's legacy
    generator seeded with `seed`; rliable's StratifiedBootstrap / StratifiedIndependentBootstrap), drawn once
    for every interval of the same shapes. Each array is (reps, runs, tasks), read-only."""
    rng = np.random.RandomState(seed)
    draws = tuple(np.empty((reps, *shape), dtype=np.int64) for shape in shapes)
    for r in range(reps):
        for draw, shape in zip(draws, shapes):
            draw[r] = rng.choice(shape[0], shape, replace=True)
    for draw in draws:
        draw.setflags(write=False)
    return draws


def _interval(replicates: np.ndarray) -> tuple[float, float]:
    """The 95% percentile interval of bootstrap replicates, as arch computes it for rliable."""
    alpha = (1.0 - CONFIDENCE) / 2
    low, high = np.percentile(replicates, [100 * alpha, 100 * (1.0 - alpha)])
    return float(low), float(high)


def _replicates(scores: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(reps, runs, tasks): each replicate's scores, runs resampled within each task (column)."""
    return scores[indices, np.arange(scores.shape[1])]


def iqm_interval(scores, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """IQM and its 95% stratified-bootstrap interval: (iqm, low, high); rliable's numbers, its replicates
    computed at once (rliable's own loop takes ~0.1 s an interval)."""
    from scipy.stats import trim_mean

    scores = _matrix(scores)
    (indices,) = _resamples((scores.shape,), reps, seed)
    replicates = trim_mean(_replicates(scores, indices).reshape(reps, -1), proportiontocut=0.25, axis=1)
    return (iqm(scores), *_interval(replicates))


def mean_interval(scores, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """The mean of all entries and its 95% stratified-bootstrap interval: (mean, low, high)."""
    from rliable import metrics

    scores = _matrix(scores)
    (indices,) = _resamples((scores.shape,), reps, seed)
    replicates = _replicates(scores, indices).mean(axis=1).mean(axis=1)  # over runs, then tasks: rliable's order
    return (float(metrics.aggregate_mean(scores)), *_interval(replicates))


def improvement_interval(x, y, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """P(X > Y) and its 95% interval (X's and Y's runs resampled independently within each task)."""
    point = probability_of_improvement(x, y)  # checks the shapes
    x, y = _matrix(x), _matrix(y)
    x_indices, y_indices = _resamples((x.shape, y.shape), reps, seed)
    xs = _replicates(x, x_indices)[:, :, None, :]  # (reps, runs x, 1, tasks)
    ys = _replicates(y, y_indices)[:, None, :, :]  # (reps, 1, runs y, tasks)
    # per task the Mann-Whitney U over all run pairs (ties one half) / pairs, then the mean over tasks
    per_task = (xs > ys).mean(axis=(1, 2)) + 0.5 * (xs == ys).mean(axis=(1, 2))
    return (point, *_interval(per_task.mean(axis=1)))


def performance_profile(scores, taus) -> np.ndarray:
    """The fraction of all (run, task) scores above each tau (rliable's run-score distribution)."""
    from rliable import library

    scores = _matrix(scores)
    return np.array([library.run_score_deviation(scores, tau) for tau in np.asarray(taus, dtype=float)])
