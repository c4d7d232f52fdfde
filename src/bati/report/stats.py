"""Aggregate statistics through rliable (Agarwal et al. 2021, "Deep RL at the edge of the statistical
precipice"): IQM, stratified bootstrap CIs, probability of improvement, performance profiles.

Score matrices are (runs, tasks) arrays, rliable's layout; one number per run is a (runs, 1) matrix.
Here a "task" is whatever a report stratifies by: one family's table has one, the claims page's
cross-family numbers have one column per family. Every interval is a 95% percentile interval of
`BOOTSTRAP_REPS` stratified-bootstrap replicates (runs resampled within each column), drawn with
`seed`: the same scores and seed give the same numbers.

rliable is the `stats` extra (pinned with arch 7.2 and pandas < 3: arch 8 rejects rliable's
`random_state=None`, pandas 3 breaks arch 7); `require_rliable()` says so in one line before any work.
"""

from __future__ import annotations

import warnings

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


def _estimate(scores, func, reps: int, seed: int) -> tuple[float, float, float]:
    """rliable's point estimate and interval. rliable 1.2's stratified bootstrap draws its indices from
    numpy's global generator (whatever random_state it is given), so that generator is seeded here and
    restored afterwards."""
    from rliable import library

    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():  # arch 7.2 deprecates the random_state that rliable passes
            warnings.simplefilter("ignore", FutureWarning)
            point, interval = library.get_interval_estimates(
                {"x": scores}, func, reps=reps, confidence_interval_size=CONFIDENCE,
                random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(saved)
    low, high = np.asarray(interval["x"]).reshape(2)
    return float(np.asarray(point["x"]).reshape(())), float(low), float(high)


def iqm_interval(scores, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """IQM and its 95% stratified-bootstrap interval: (iqm, low, high)."""
    from rliable import metrics

    return _estimate(_matrix(scores), lambda s: np.array([metrics.aggregate_iqm(s)]), reps, seed)


def mean_interval(scores, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """The mean of all entries and its 95% stratified-bootstrap interval: (mean, low, high)."""
    from rliable import metrics

    return _estimate(_matrix(scores), lambda s: np.array([metrics.aggregate_mean(s)]), reps, seed)


def improvement_interval(x, y, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """P(X > Y) and its 95% interval (X's and Y's runs resampled independently within each task)."""
    from rliable import metrics

    x, y = _matrix(x), _matrix(y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"score matrices cover different numbers of tasks: {x.shape[1]} and {y.shape[1]}")
    return _estimate([x, y], lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps, seed)


def performance_profile(scores, taus) -> np.ndarray:
    """The fraction of all (run, task) scores above each tau (rliable's run-score distribution)."""
    from rliable import library

    scores = _matrix(scores)
    return np.array([library.run_score_deviation(scores, tau) for tau in np.asarray(taus, dtype=float)])
