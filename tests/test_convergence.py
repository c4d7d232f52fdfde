"""The drift of a run's number over its scored window (bati.report.convergence): hand-computed lines."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bati.report.convergence import drift_interval, drift_verdict, format_drift, run_drift, window_drift
from bati.report.runs import RunResult


def test_the_drift_is_the_change_of_the_least_squares_line_across_the_window():
    steps = [60_000, 70_000, 80_000, 90_000, 100_000]
    assert window_drift(steps, [0.5, 0.6, 0.7, 0.8, 0.9]) == pytest.approx(0.4)  # slope 1e-5 x 40k steps
    assert window_drift(steps, [1.0, 0.0, 1.0, 0.0, 1.0]) == pytest.approx(0.0)  # noise around a flat line
    # least squares, not last minus first (0 here): sum (x - 2)(y - 1.2) = 1.0 over sum (x - 2)^2 = 10, a slope
    # of 0.1 per evaluation, 0.4 across the four intervals
    assert window_drift(steps, [0.0, 2.0, 1.0, 3.0, 0.0]) == pytest.approx(0.4)
    assert math.isnan(window_drift(steps[:2], [0.0, 1.0]))  # two points say nothing
    assert math.isnan(window_drift(steps, [0.1, math.nan, math.nan, math.nan, 0.2]))
    with pytest.raises(ValueError, match="5 steps for 4 scores"):
        window_drift(steps, [0.0] * 4)


def run(curve: list[float], averaged: int = 3, refs: dict | None = None) -> RunResult:
    points = [{"step": 10_000 * (i + 1), "p_test_return": v, "p_train_return": 0.0} for i, v in enumerate(curve)]
    return RunResult(path=Path("eval.json"), family="AntDir", method="bati", seed=0, p_test_return=curve[-1],
                     p_train_return=0.0, evaluations_averaged=averaged, curve=points, reference_returns=refs)


def test_a_runs_drift_covers_only_the_evaluations_its_number_averages_and_is_normalised():
    climbing_then_flat = [0.0, 50.0, 100.0, 100.0, 100.0, 100.0]
    assert run_drift(run(climbing_then_flat, averaged=4)) == pytest.approx(0.0)
    assert run_drift(run(climbing_then_flat, averaged=6)) > 0
    refs = {"random": -100.0, "expert": 100.0}  # normalised: (v + 100) / 200, a drift of 200 raw is 1.0
    assert run_drift(run([0.0, 100.0, 200.0], refs=refs)) == pytest.approx(1.0)
    assert run_drift(run([0.0, 100.0, 200.0], refs=refs), normalise=False) == pytest.approx(200.0)
    assert math.isnan(run_drift(run([0.0, 1.0, 2.0], averaged=2)))


def test_three_seeds_give_an_interval_and_a_verdict_fewer_give_the_number_only():
    mean, low, high = drift_interval([0.1, 0.2, 0.3], reps=200)
    assert mean == pytest.approx(0.2) and 0.1 <= low <= 0.2 <= high <= 0.3
    assert drift_verdict(mean, low, high) == "rising" and format_drift(mean, low, high).endswith("rising")
    assert drift_verdict(*drift_interval([-0.3, -0.2, -0.1], reps=200)) == "falling"
    assert drift_verdict(*drift_interval([-0.2, 0.1, 0.2], reps=200)) == "flat"
    mean, low, high = drift_interval([0.1, 0.3, math.nan])
    assert mean == pytest.approx(0.2) and math.isnan(low) and drift_verdict(mean, low, high) == ""
    assert format_drift(mean, low, high) == "+0.20 (< 3 seeds)" and format_drift(*drift_interval([])) == "–"


def test_a_negligible_normalised_drift_is_flat_even_with_a_tight_interval():
    mean, low, high = drift_interval([-0.011, -0.010, -0.009], reps=200)
    assert drift_verdict(mean, low, high) == "falling"  # raw returns: no common unit, no tolerance
    assert drift_verdict(mean, low, high, negligible=0.02) == "flat"
    assert format_drift(mean, low, high, negligible=0.02).endswith("flat")
    assert drift_verdict(*drift_interval([0.05, 0.06, 0.07], reps=200), negligible=0.02) == "rising"
