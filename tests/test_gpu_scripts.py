"""The GPU session's scripts without a GPU: gpu_paper_scale.sh's packing (results, and the checkpoint of each
unfinished run a file each) and gpu_local.py (away / back, unpack into the committed cells and .gpu/resume)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
SETTING = Path("AntDir") / "paper-eps1-abc"

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def write_run(tree: Path, name: str, *, finished: bool, checkpoint: bool, tag: str = "device") -> Path:
    run = tree / SETTING / name
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"method": name.split("-seed")[0]}))
    (run / "eval.jsonl").write_text(json.dumps({"step": 10, "tag": tag}) + "\n")
    (run / "metrics.jsonl").write_text(json.dumps({"step": 10}) + "\n")
    if finished:
        (run / "eval.json").write_text(json.dumps({"tag": tag}))
    if checkpoint:
        (run / "checkpoint.msgpack").write_bytes(b"weights of " + name.encode())
    (run / ".lock").write_text("{}")
    return run


def device_results(tmp_path: Path) -> Path:
    """A device's results: bati seed 0 finished (its checkpoint beside), seed 1 cut with a checkpoint, bati-r seed 1
    in a folder of its own (no checkpoint), focal seed 0 finished, a session log."""
    results = tmp_path / "device"
    write_run(results, "bati-seed0", finished=True, checkpoint=True)
    write_run(results, "bati-seed1", finished=False, checkpoint=True)
    write_run(results, "bati-r-seed1", finished=False, checkpoint=False)
    write_run(results, "focal-seed0", finished=True, checkpoint=False)
    (results / "session.log").write_text("AntDir main exit 0\n")
    (results / "context-length.sweep.json").write_text("{}")  # each experiment's status file
    return results


def pack(tmp_path: Path, results: Path) -> Path:
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    done = subprocess.run(["bash", str(SCRIPTS / "gpu_paper_scale.sh")], capture_output=True, text=True,
                          env={**os.environ, "MODE": "pack", "RESULTS": str(results), "OUT": str(out)})
    assert done.returncode == 0, done.stderr
    return out


def test_pack_returns_results_without_checkpoints_and_one_file_per_unfinished_checkpoint(tmp_path):
    results = device_results(tmp_path)
    out = pack(tmp_path, results)
    (out / "resume-1.tar").write_bytes(b"an earlier pack's")  # a stale one: removed by the next pack
    out = pack(tmp_path, results)
    with tarfile.open(out / "results.tar.gz") as tar:
        names = tar.getnames()
    assert not [n for n in names if n.endswith(("checkpoint.msgpack", ".lock"))]
    assert f"./{SETTING}/bati-seed1/metrics.jsonl" in names and "./session.log" in names
    assert sorted(p.name for p in out.iterdir()) == ["results.tar.gz", "resume-0.tar"]
    with tarfile.open(out / "resume-0.tar") as tar:
        assert tar.getnames() == [f"{SETTING}/bati-seed1/checkpoint.msgpack"]


def gpu_local(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPTS / "gpu_local.py"), "--root", str(root), *args],
                          capture_output=True, text=True)


def test_unpack_adds_new_cells_keeps_committed_ones_and_keeps_unfinished_runs_to_resume(tmp_path):
    out = pack(tmp_path, device_results(tmp_path))
    root = tmp_path / "checkout"
    committed = root / "results" / "paper" / "experiments"
    write_run(committed, "bati-seed0", finished=True, checkpoint=False, tag="committed")
    write_run(root / ".gpu" / "resume", "csro-seed2", finished=False, checkpoint=True)  # an earlier session's
    done = gpu_local(root, "unpack", str(out), "--logs", "results/paper/h200-x")
    assert done.returncode == 0, done.stderr
    assert "1 finished cell(s) new" in done.stdout and "1 already there" in done.stdout
    assert "then: bati experiment context-length --scale paper --report-only" in done.stdout
    assert json.loads((committed / SETTING / "bati-seed0" / "eval.json").read_text()) == {"tag": "committed"}
    focal = committed / SETTING / "focal-seed0"
    assert sorted(p.name for p in focal.iterdir()) == ["config.json", "eval.json", "eval.jsonl", "metrics.jsonl"]
    resume = root / ".gpu" / "resume" / SETTING
    assert sorted(p.name for p in resume.iterdir()) == ["bati-r-seed1", "bati-seed1"]  # the earlier set replaced
    assert (resume / "bati-seed1" / "checkpoint.msgpack").read_bytes() == b"weights of bati-seed1"
    assert (resume / "bati-r-seed1" / "eval.jsonl").exists()
    logs = root / "results" / "paper" / "h200-x"
    assert (logs / "session.log").read_text() == "AntDir main exit 0\n"
    partial = logs / "partial" / SETTING / "bati-seed1"
    assert sorted(p.name for p in partial.iterdir()) == ["config.json", "eval.jsonl", "metrics.jsonl"]


def test_unpack_refuses_a_folder_without_a_pack_in_one_line(tmp_path):
    (tmp_path / "results" / "paper" / "experiments").mkdir(parents=True)
    done = gpu_local(tmp_path, "unpack", str(tmp_path / "nothing"), "--logs", "logs")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().count("\n") == 0 and "results.tar.gz" in done.stderr


def test_unpack_never_overwrites_an_earlier_sessions_logs(tmp_path):
    out = pack(tmp_path, device_results(tmp_path))
    root = tmp_path / "checkout"
    committed = root / "results" / "paper" / "experiments"
    committed.mkdir(parents=True)
    logs = root / "results" / "paper" / "h200-x"
    logs.mkdir(parents=True)
    (logs / "session.log").write_text("an earlier session's\n")
    done = gpu_local(root, "unpack", str(out), "--logs", "results/paper/h200-x")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().count("\n") == 0 and "new --logs folder" in done.stderr
    assert (logs / "session.log").read_text() == "an earlier session's\n"
    assert list(committed.iterdir()) == [] and not (root / ".gpu" / "resume").exists()  # nothing done


def test_away_leaves_a_slim_copy_of_the_committed_cells_and_back_restores_results(tmp_path):
    root = tmp_path / "checkout"
    committed = root / "results" / "paper" / "experiments"
    write_run(committed, "bati-seed0", finished=True, checkpoint=False)
    write_run(committed, "bati-seed1", finished=False, checkpoint=False)
    (root / "results" / "cpu").mkdir()
    (root / "results" / "cpu" / "big.jsonl").write_text("x" * 1000)
    subprocess.run(["git", "init", "-q", str(root)], check=True)
    stash = tmp_path / "away"
    done = gpu_local(root, "away", "--stash", str(stash), "--no-pause")
    assert done.returncode == 0, done.stderr
    assert not (root / "results").exists() and (stash / "cpu" / "big.jsonl").exists()
    slim = root / ".gpu" / "committed" / SETTING
    assert [p.name for p in slim.iterdir()] == ["bati-seed0"]
    assert sorted(p.name for p in (slim / "bati-seed0").iterdir()) == ["config.json", "eval.json", "eval.jsonl"]
    again = gpu_local(root, "away", "--stash", str(stash), "--no-pause")
    assert again.returncode == 2 and "back" in again.stderr
    done = gpu_local(root, "back")
    assert done.returncode == 0, done.stderr
    assert (root / "results" / "cpu" / "big.jsonl").exists() and not stash.exists()
    assert not (root / ".gpu" / "committed").exists()  # it would hide cells committed later from the next calls
    assert gpu_local(root, "back").returncode == 2


def test_away_never_pauses_the_processes_that_called_it():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import gpu_local
    finally:
        sys.path.remove(str(SCRIPTS))
    assert {os.getpid(), os.getppid()} <= gpu_local.ancestors()
