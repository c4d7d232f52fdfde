"""Is a run's number converged? Its drift over the scored window.

A run's number is the mean of its last evaluations (`evaluations_averaged`, 5 by default: at 100k steps with an
evaluation every 10k, steps 60k-100k). If the run had converged, more steps would change nothing, so the score
would not move inside that window either. The drift is the change across the window of the least-squares line
through those evaluations: slope x (last step - first step), in the units of the score (normalised where the run
records reference returns). Over a method's seeds, the mean drift with its 95% stratified-bootstrap interval
(rliable) says "still rising" or "still falling" when the interval excludes 0, "flat" when it holds 0 or, for
normalised scores, when the drift is negligible (under `NEGLIGIBLE`) (with fewer than `MIN_SEEDS` seeds: the
number only). Flat is not proof of convergence (a slow climb hides in noisy
evaluations: read the interval's width), but rising is proof that it is not.
"""

from __future__ import annotations

import math

import numpy as np

from bati.report.runs import RunResult
from bati.report.stats import BOOTSTRAP_REPS, mean_interval

MIN_SEEDS = 3
"""Seeds below which no interval (and no verdict) is given."""
MIN_POINTS = 3
"""Evaluations a window needs for a line through them to say anything."""
NEGLIGIBLE = 0.02
"""A normalised drift smaller than this (2% of the experts' margin over random, across the window) is flat
whatever its interval: tight intervals would otherwise call a converged run 'falling' by 0.01."""


def window_drift(steps, scores) -> float:
    """The change across the window of the least-squares line through (step, score); NaN under MIN_POINTS."""
    steps, scores = np.asarray(steps, dtype=float), np.asarray(scores, dtype=float)
    if len(steps) != len(scores):
        raise ValueError(f"{len(steps)} steps for {len(scores)} scores")
    keep = np.isfinite(scores)
    steps, scores = steps[keep], scores[keep]
    if len(steps) < MIN_POINTS or steps.max() == steps.min():
        return math.nan
    slope = np.polyfit(steps, scores, 1)[0]
    return float(slope * (steps.max() - steps.min()))


def run_drift(run: RunResult, source: str = "p_test", normalise: bool = True) -> float:
    """`run`'s drift of its `source` return (normalised when it records references and `normalise`) over the
    evaluations its number averages; NaN when its curve has too few."""
    n = run.evaluations_averaged or 0
    window = [point for point in run.curve if f"{source}_return" in point][-n:] if n else []
    value = (lambda v: run.normalised(v)) if normalise and run.reference_returns else (lambda v: v)  # noqa: E731
    return window_drift([p["step"] for p in window], [value(float(p[f"{source}_return"])) for p in window])


def drift_interval(drifts, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> tuple[float, float, float]:
    """The mean drift over seeds and its 95% interval; (mean, NaN, NaN) under MIN_SEEDS finite drifts."""
    drifts = np.asarray([d for d in drifts if math.isfinite(d)], dtype=float)
    if not len(drifts):
        return math.nan, math.nan, math.nan
    if len(drifts) < MIN_SEEDS:
        return float(drifts.mean()), math.nan, math.nan
    return mean_interval(drifts, reps, seed)


def drift_verdict(mean: float, low: float, high: float, negligible: float = 0.0) -> str:
    """'rising' / 'falling' when the interval excludes 0 and the mean is at least `negligible` (NEGLIGIBLE for
    normalised scores; raw returns have no common unit), 'flat' otherwise, '' without an interval."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return ""
    if abs(mean) < negligible:
        return "flat"
    return "rising" if low > 0 else "falling" if high < 0 else "flat"


def format_drift(mean: float, low: float, high: float, digits: int = 2, negligible: float = 0.0) -> str:
    """'+0.03 [-0.02, +0.08] flat', or '+0.03 (< 3 seeds)' without an interval, or '–' without a drift."""
    if not math.isfinite(mean):
        return "–"
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"{mean:+.{digits}f} (< {MIN_SEEDS} seeds)"
    return f"{mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}] {drift_verdict(mean, low, high, negligible)}"
