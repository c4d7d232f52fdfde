"""scripts/cpu_main_queue.sh, the cpu-scale queue: its order, STOP_AT and the resumption of a cut job, with a stub
`python` that records the commands instead of training (bash only, seconds)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "cpu_main_queue.sh"
STUB = """#!/bin/sh
echo "$*" >> "$QUEUE_CALLS"
"""

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def run_queue(tmp_path: Path, **env: str) -> tuple[list[tuple[str, str, str, str]], str]:
    """The (experiment, family, method, seed) of each training command the queue issued (several methods of one
    command joined by +), and its output."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    stub = bin_dir / "python"
    stub.write_text(STUB)
    stub.chmod(0o755)
    calls = tmp_path / "calls.log"
    calls.unlink(missing_ok=True)
    full_env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "QUEUE_CALLS": str(calls),
                "SEEDS": "0", **env}
    out = subprocess.run(["bash", str(SCRIPT), str(tmp_path / "data"), str(tmp_path / "out" / "experiments")],
                         env=full_env, capture_output=True, text=True, timeout=120, check=True)
    jobs = []
    for line in calls.read_text().splitlines() if calls.exists() else []:
        match = re.match(r"-m bati\.cli experiment (\S+) --scale cpu --families (\S+) --methods (.+?) --seeds (\d+)",
                         line)
        if match:
            experiment, family, methods, seed = match.groups()
            jobs.append((experiment, family, methods.replace(" ", "+"), seed))
    return jobs, out.stdout


def test_order_claims_first(tmp_path):
    jobs, _ = run_queue(tmp_path)
    assert jobs[:7] == [("main", "AntDir", "csro", "0"), ("main", "AntDir", "er-trl", "0"),
                        ("noise", "AntDir", "bati", "0"), ("noise", "AntDir", "focal", "0"),
                        ("main", "AntDir", "oracle", "0"), ("main", "AntDir", "bati+bati-r+bati-auto", "0"),
                        ("main", "AntDir", "focal", "0")]
    # phase 1's first pass (the Oracle, BATI, FOCAL) on every family before ER-TRL's noise cells and the rest
    first_pass = [(f, m) for _, f, m, _ in jobs[4:19]]
    assert first_pass == [(f, m) for f in ("AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam")
                          for m in ("oracle", "bati+bati-r+bati-auto", "focal")]
    assert jobs[19] == ("noise", "AntDir", "er-trl", "0") and jobs[20] == ("main", "AntDir", "bati-r", "0")
    families = list(dict.fromkeys(family for experiment, family, _, _ in jobs if experiment == "main"))
    assert families == ["AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam"]
    assert ("main", "WalkerParam", "dpt", "0") == jobs[-1]  # phase 2 last
    # BATI's job on a family evaluates BATI-R and BATI-auto alongside (one training): the three in one command


def test_stop_at_skips_what_would_not_finish(tmp_path):
    # 70 minutes left: CSRO and ER-TRL (100 min) do not fit, nor a noise seed of BATI (two cells, 2 x 65) or FOCAL
    # (2 x 45); the Oracle (35) does.
    jobs, out = run_queue(tmp_path, STOP_AT=str(int(time.time()) + 70 * 60))
    assert jobs[0] == ("main", "AntDir", "oracle", "0")
    assert "skipped: csro (100 min)" in out and "skipped: focal (90 min)" in out
    past, out = run_queue(tmp_path, STOP_AT=str(int(time.time()) - 1))
    assert past == [] and "skipped: oracle" in out


def test_a_cut_job_resumes_first(tmp_path):
    run = tmp_path / "out" / "experiments" / "HopperParam" / "cpu-eps0.5-abcdef12" / "bati-r-seed0"
    run.mkdir(parents=True)
    (run / "checkpoint.msgpack").write_bytes(b"")
    jobs, _ = run_queue(tmp_path)
    assert jobs[0] == ("noise", "HopperParam", "bati-r", "0")  # not eps 1: a noise ablation's cell
    (run / "eval.json").write_text("{}")  # finished: nothing to resume
    jobs, _ = run_queue(tmp_path)
    assert jobs[0] == ("main", "AntDir", "csro", "0")


def test_wait_pid_of_a_finished_process_does_not_wait(tmp_path):
    done = subprocess.Popen(["true"])
    done.wait()
    start = time.monotonic()
    jobs, _ = run_queue(tmp_path, WAIT_PID=str(done.pid))
    assert jobs and time.monotonic() - start < 20


def test_methods_evaluated_alongside_come_only_with_a_run_to_do(tmp_path):
    # HalfCheetahVel's BATI seed 0 is finished: its job is BATI alone (skipped in seconds); BATI-R and BATI-auto
    # beside a finished BATI would train on their own, which their own later phases do
    done = tmp_path / "out" / "experiments" / "HalfCheetahVel" / "cpu-eps1-abcdef12" / "bati-seed0"
    done.mkdir(parents=True)
    (done / "eval.json").write_text("{}")
    jobs, _ = run_queue(tmp_path)
    first_pass = [(f, m) for e, f, m, _ in jobs if e == "main" and m.startswith("bati")][:3]
    assert first_pass == [("AntDir", "bati+bati-r+bati-auto"), ("HalfCheetahVel", "bati"),
                          ("HalfCheetahDir", "bati+bati-r+bati-auto")]
