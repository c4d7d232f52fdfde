"""The one process pool (bati.processes): spawned workers, stopped at once when the body fails."""

from __future__ import annotations

import os
import time

import pytest

from bati.processes import spawned_pool


def test_a_spawned_pool_runs_tasks_in_other_processes():
    with spawned_pool(2) as pool:
        pids = {pool.submit(os.getpid).result() for _ in range(4)}
    assert os.getpid() not in pids


def test_a_failing_body_stops_the_workers_at_once():
    start = time.perf_counter()
    with pytest.raises(RuntimeError, match="interrupted"):
        with spawned_pool(1) as pool:
            pool.submit(os.getpid).result()  # the worker is up
            pool.submit(time.sleep, 120)
            time.sleep(0.5)  # ... and sleeping
            raise RuntimeError("interrupted")
    assert time.perf_counter() - start < 60  # not after the 120 s task
