"""scripts/cpu_main_queue.sh, the cpu-scale queue: its order, STOP_AT and the resumption of a cut job, with a stub
`python` that records the commands instead of training (bash only, seconds)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bati.experiments.pipeline import plan_experiment
from bati.experiments.specs import get_spec

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "cpu_main_queue.sh"
STUB = """#!/bin/sh
case "$1 $2" in "-m bati.cli")
  echo "$*" >> "$QUEUE_CALLS"; args="$*"; data=${args#*--family }
  case "$3 $4 $NO_DATA" in
    "data collect 1") echo "$data" >> "$QUEUE_CALLS.data";;
    "data info 1") grep -qxF -- "$data" "$QUEUE_CALLS.data" 2> /dev/null || exit 1;;
  esac
  exit 0;;
esac
exec "$REAL_PYTHON" "$@"
"""
"""A `python` that records the queue's `bati` commands (and succeeds; with NO_DATA=1, `bati data info` fails
for data not collected yet: a fresh machine) and runs its other Python (its questions about
the plans and the families) with the real interpreter."""

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
    Path(f"{calls}.data").unlink(missing_ok=True)
    full_env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "QUEUE_CALLS": str(calls),
                "REAL_PYTHON": sys.executable, "SEEDS": "0", **env}
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


FAMILIES = ("AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam")


def test_order_claims_first(tmp_path):
    jobs, _ = run_queue(tmp_path)
    assert jobs[:7] == [("main", "AntDir", "csro", "0"), ("main", "AntDir", "er-trl", "0"),
                        ("noise", "AntDir", "bati", "0"), ("noise", "AntDir", "focal", "0"),
                        ("main", "AntDir", "oracle", "0"), ("main", "AntDir", "bati+bati-r+bati-auto", "0"),
                        ("main", "AntDir", "focal", "0")]
    # phase 1's first pass (the Oracle, BATI, FOCAL) on the first three families, then the claim pairs of the
    # context-length and ood-tasks ablations (C5, C6), then the first pass on the last two families, before the rest
    first_pass = [(f, m) for _, f, m, _ in jobs[4:13]]
    assert first_pass == [(f, m) for f in ("AntDir", "HalfCheetahVel", "HalfCheetahDir")
                          for m in ("oracle", "bati+bati-r+bati-auto", "focal")]
    assert jobs[13:17] == [("context-length", "HalfCheetahDir", "bati+bati-r", "0"),
                           ("context-length", "HalfCheetahDir", "focal", "0"),
                           ("ood-tasks", "AntDir", "bati+bati-r", "0"), ("ood-tasks", "AntDir", "focal", "0")]
    # (the first pass then visits every family again: finished cells are skipped in seconds, skipped ones run)
    assert [(f, m) for _, f, m, _ in jobs[17:32]] == [(f, m) for f in FAMILIES
                                                       for m in ("oracle", "bati+bati-r+bati-auto", "focal")]
    # then phase 1b, Recon first (claim C3); ER-TRL's noise cells (beyond the paper) after the noise ablation's others
    assert jobs[32] == ("main", "AntDir", "recon", "0")
    assert [m for _, f, m, _ in jobs[32:37]] == ["recon", "unicorn", "csro", "bati-r+bati-auto", "no-context"]
    noise = [m for e, _, m, _ in jobs if e == "noise"]
    assert noise == ["bati", "focal", "bati-r", "csro", "unicorn", "recon", "er-trl"]
    ablations = [(e, m) for e, _, m, _ in jobs if e in ("context-length", "ood-tasks")]
    assert ablations[4:] == [(e, m) for e in ("context-length", "ood-tasks") for m in ("csro", "unicorn", "recon",
                                                                                       "bati-r")]
    families = list(dict.fromkeys(family for experiment, family, _, _ in jobs if experiment == "main"))
    assert families == list(FAMILIES)
    assert ("main", "WalkerParam", "dpt", "0") == jobs[-1]  # phase 2 last
    # BATI's job on a family evaluates BATI-R and BATI-auto as its test-time rules (one training): one command


def test_stop_at_skips_what_would_not_finish(tmp_path):
    # 70 minutes left: CSRO and ER-TRL (100 min) do not fit, nor a noise seed of BATI (two cells, 2 x 65) or FOCAL
    # (2 x 45); the Oracle (35) does.
    jobs, out = run_queue(tmp_path, STOP_AT=str(int(time.time()) + 70 * 60))
    assert jobs[0] == ("main", "AntDir", "oracle", "0")
    assert "skipped: csro (100 min)" in out and "skipped: focal (90 min)" in out
    past, out = run_queue(tmp_path, STOP_AT=str(int(time.time()) - 1))
    assert past == [] and "skipped: oracle" in out
    # on free cores (PACE=50: half the estimates) CSRO's seed (50 min) fits in the same 70 minutes
    jobs, out = run_queue(tmp_path, STOP_AT=str(int(time.time()) + 70 * 60), PACE="50")
    assert jobs[0] == ("main", "AntDir", "csro", "0") and "skipped: er-trl (50 min)" not in out


def planned_run(tmp_path: Path, experiment: str, family: str, method: str, **where) -> Path:
    """The run directory the queue's experiment plans for (family, method, seed 0) and the config values `where`."""
    plan = plan_experiment(get_spec(experiment), "cpu", tmp_path / "out" / "experiments", seeds=(0,),
                           data_root=tmp_path / "data")
    return next(c.config.out_dir for c in plan.cells if (c.config.family, c.config.method) == (family, method)
                and all(getattr(c.config, k) == v for k, v in where.items()))


@pytest.mark.parametrize("experiment, family, method, where", [
    ("noise", "AntDir", "csro", {"noise": 0.5}),  # a noise ablation's cell
    ("main", "HalfCheetahDir", "focal", {}),  # the main table's, at HalfCheetahDir's eps 0.8 (was taken for noise)
    ("context-length", "HalfCheetahDir", "bati", {}),  # eps 0.9
    ("ood-tasks", "AntDir", "focal", {}),  # eps 1 like main's, another setting
])
def test_a_cut_job_resumes_first_in_its_own_experiment(tmp_path, experiment, family, method, where):
    run = planned_run(tmp_path, experiment, family, method, **where)
    run.mkdir(parents=True)
    (run / "checkpoint.msgpack").write_bytes(b"")
    jobs, _ = run_queue(tmp_path)
    assert jobs[0] == (experiment, family, method, "0")
    (run / "eval.json").write_text("{}")  # finished: nothing to resume
    jobs, _ = run_queue(tmp_path)
    assert jobs[0] == ("main", "AntDir", "csro", "0")


def test_phase_0_resumes_the_cut_seed_only(tmp_path):
    # ood-tasks' BATI seed 1 was cut: phase 0 resumes seed 1 alone; seeds 0 and 2 come in the ablations' pass,
    # with BATI-R as its rule (phase 0 once trained them all there, BATI alone)
    run = planned_run(tmp_path, "ood-tasks", "AntDir", "bati")
    cut = run.parent / "bati-seed1"
    cut.mkdir(parents=True)
    (cut / "checkpoint.msgpack").write_bytes(b"")
    jobs, _ = run_queue(tmp_path, SEEDS="0 1 2")
    assert jobs[0] == ("ood-tasks", "AntDir", "bati", "1") and jobs[1] == ("main", "AntDir", "csro", "0")
    assert ("ood-tasks", "AntDir", "bati+bati-r", "0") in jobs and ("ood-tasks", "AntDir", "bati+bati-r", "2") in jobs


def test_a_cut_run_resumes_first_and_alone_its_rules_coming_from_its_own_evaluations(tmp_path):
    # WalkerParam's BATI seed 1 was cut with BATI-R and BATI-auto as its test-time rules (in its eval.jsonl): its job
    # is BATI's, first; the sweep resumes the run with the rules it began with (sweep.Sweep.arguments)
    run = planned_run(tmp_path, "main", "WalkerParam", "bati")
    cut = run.parent / "bati-seed1"
    cut.mkdir(parents=True)
    (cut / "checkpoint.msgpack").write_bytes(b"")
    (cut / "eval.jsonl").write_text('{"step": 10000, "rules": {"bati-r": {}, "bati-auto": {}}}\n')
    jobs, _ = run_queue(tmp_path, SEEDS="0 1 2")
    assert jobs[0] == ("main", "WalkerParam", "bati", "1")


def test_wait_pid_of_a_finished_process_does_not_wait(tmp_path):
    done = subprocess.Popen(["true"])
    done.wait()
    start = time.monotonic()
    jobs, _ = run_queue(tmp_path, WAIT_PID=str(done.pid))
    assert jobs and time.monotonic() - start < 20


def test_test_time_rules_come_only_with_a_run_to_do(tmp_path):
    # HalfCheetahVel's BATI seed 0 is finished: its job is BATI alone, finished, so none; BATI-R and BATI-auto beside
    # a finished BATI would train on their own, which their own later phase does (BATI-R hosting BATI-auto)
    done = planned_run(tmp_path, "main", "HalfCheetahVel", "bati")
    done.mkdir(parents=True)
    other = planned_run(tmp_path, "ood-tasks", "AntDir", "bati")  # another experiment's BATI, same family and seed:
    other.mkdir(parents=True)  # AntDir's main BATI is still to do, with the others as its rules
    (other / "eval.json").write_text("{}")
    (done / "eval.json").write_text("{}")
    jobs, _ = run_queue(tmp_path)
    first_pass = [(f, m) for e, f, m, _ in jobs if e == "main" and m.startswith("bati")][:2]
    assert first_pass == [("AntDir", "bati+bati-r+bati-auto"), ("HalfCheetahDir", "bati+bati-r+bati-auto")]
    hcv = [m for e, f, m, _ in jobs if e == "main" and f == "HalfCheetahVel" and m.startswith("bati")]
    assert hcv == ["bati-r+bati-auto", "bati-auto"]  # phase 1b, then phase 2's (skipped by the sweep once done)


def test_an_ablation_whose_bati_run_finished_alone_trains_bati_r_in_its_second_pass(tmp_path):
    # ood-tasks' BATI seed 0 finished without BATI-R as its rule (a resumed cut job): no `bati bati-r` job (BATI-R
    # would train on its own before FOCAL's claim cells); BATI-R comes in the ablations' second pass
    run = planned_run(tmp_path, "ood-tasks", "AntDir", "bati")
    run.mkdir(parents=True)
    (run / "eval.json").write_text("{}")
    jobs, _ = run_queue(tmp_path)
    ood = [m for e, _, m, _ in jobs if e == "ood-tasks"]
    assert ood == ["focal", "csro", "unicorn", "recon", "bati-r"]
    assert [m for e, _, m, _ in jobs if e == "context-length"][:2] == ["bati+bati-r", "focal"]  # untouched


def test_a_job_finished_at_the_start_is_skipped_without_starting_bati(tmp_path):
    for method in ("csro", "er-trl"):  # AntDir's first two jobs, finished
        run = planned_run(tmp_path, "main", "AntDir", method)
        run.mkdir(parents=True)
        (run / "eval.json").write_text("{}")
    jobs, _ = run_queue(tmp_path)
    assert jobs[0] == ("noise", "AntDir", "bati", "0")
    calls = (tmp_path / "calls.log").read_text()
    assert "main --scale cpu --families AntDir --methods csro " not in calls
    assert "main --scale cpu --families AntDir --methods er-trl " not in calls  # nor in phase 2


def test_data_is_collected_only_for_jobs_to_run(tmp_path):
    # a fresh machine (no data): AntDir's main data is not collected for its finished CSRO and ER-TRL jobs; the first
    # collections are the noise ablation's, just before its first job
    for method in ("csro", "er-trl"):
        run = planned_run(tmp_path, "main", "AntDir", method)
        run.mkdir(parents=True)
        (run / "eval.json").write_text("{}")
    run_queue(tmp_path, NO_DATA="1")
    calls = [line for line in (tmp_path / "calls.log").read_text().splitlines()
             if " data collect " in line or " experiment " in line and "--report-only" not in line]
    assert "--family AntDir --noise 0" in calls[0] and "--family AntDir --noise 0.5" in calls[1]
    assert " experiment noise " in calls[2] and "--methods bati " in calls[2]
    collections = [line.split("--family ")[1] for line in calls if " data collect " in line]
    assert len(collections) == len(set(collections))  # each once (later jobs find it)
    assert set(collections) == {"AntDir --noise 0", "AntDir --noise 0.5", "AntDir", *FAMILIES[1:]}
