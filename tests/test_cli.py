"""The `bati envs` command: listing, one demo episode, and one-line errors on bad input."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bati.cli import main
from bati.envs import FAMILY_NAMES


def run(capsys, *args: str):
    code = main(["envs", *args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(out: str, err: str, *needles: str) -> None:
    assert "Traceback" not in out + err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("error:")
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert "error" not in out


def test_envs_lists_all_families(capsys):
    code, out, err = run(capsys)
    assert code == 0
    for name in FAMILY_NAMES:
        assert name in out and f"bati/{name}-v0" in out
    assert err == ""


def test_envs_one_family(capsys):
    code, out, _ = run(capsys, "--family", "HopperParam")
    assert code == 0
    assert "HopperParam" in out and "dynamics" in out
    assert not any(name in out for name in FAMILY_NAMES if name != "HopperParam")


def test_envs_runs_one_episode(capsys):
    code, out, _ = run(capsys, "--family", "PointGoal", "--task", "0.6", "0.8", "--noise", "0")
    assert code == 0
    assert "over 200 steps" in out and "eps=0" in out


BAD_INPUT = [
    (["--family", "NoSuchFamily"], ["'NoSuchFamily'", "HalfCheetahVel"]),
    (["--family", "HalfCheetahVel", "--task", "5"], ["task 5.0", "[0, 2]"]),
    (["--family", "AntDir", "--task", "7"], ["task 7.0", "[0, 2*pi)"]),
    (["--family", "HalfCheetahDir", "--task", "0.5"], ["task 0.5", "{-1.0 (left), +1.0 (right)}"]),
    (["--family", "WalkerParam", "--task", "-4"], ["task -4.0", "[-3, 3]"]),
    (["--family", "PointGoal", "--task", "0", "-1"], ["[0.0, -1.0]", "angle in [0, pi]"]),
    (["--family", "HalfCheetahVel", "--task", "1", "--noise", "-1"], ["eps=-1", "[0, inf]"]),
    (["--family", "HalfCheetahDir", "--task", "1", "--noise", "1.5"], ["eps=1.5", "[0, 1]"]),
    (["--noise", "-2"], ["eps=-2", "[0, inf]"]),
]


@pytest.mark.parametrize("args,needles", BAD_INPUT, ids=[" ".join(a) for a, _ in BAD_INPUT])
def test_bad_input_is_a_one_line_error(capsys, args, needles):
    code, out, err = run(capsys, *args)
    assert code != 0
    assert_one_line_error(out, err, *needles)


def _subprocess(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "60"}  # narrow: the error must still be one line
    return subprocess.run(
        [sys.executable, "-m", "bati.cli", "envs", *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_subprocess_lists_families():
    result = _subprocess()
    assert result.returncode == 0, result.stderr
    for name in FAMILY_NAMES:
        assert name in result.stdout


def test_subprocess_bad_family_is_a_one_line_error():
    result = _subprocess("--family", "NoSuchFamily")
    assert result.returncode != 0
    # MuJoCo may print deprecation warnings to stderr; judge the lines of our error only
    stderr = "\n".join(line for line in result.stderr.splitlines() if not line.startswith("WARNING"))
    assert_one_line_error(result.stdout, stderr, "'NoSuchFamily'", "PointGoal")


def test_run_with_an_unknown_method_fails_before_any_work(capsys, tmp_path):
    code = main(["run", "--methods", "bati", "nope", "--data-root", str(tmp_path / "data")])
    out, err = capsys.readouterr()
    assert code == 2
    assert_one_line_error(out, err, "'nope'", "focal", "all")
    assert not (tmp_path / "data").exists()  # no data collected


def test_run_takes_steps_and_zoo_from_their_own_options_not_settings(capsys, tmp_path):
    code = main(["run", "--settings", "steps=5", "--data-root", str(tmp_path / "data"), "--out-dir", str(tmp_path / "r")])
    out, err = capsys.readouterr()
    assert code == 2
    assert_one_line_error(out, err, "--steps and --zoo-dir")
    assert not (tmp_path / "r").exists() and not (tmp_path / "data").exists()


def test_run_methods_all_means_every_method():
    from bati.methods import METHODS, method_names

    assert method_names(("all",)) == list(METHODS)
    assert method_names(("recon", "bati", "recon")) == ["recon", "bati"]


def test_run_reading_line_names_who_holds_and_who_falls():
    from bati.experiments.main_job import reading

    rows = [{"method": "bati", "p_train_normalised_mean": 0.5, "p_test_normalised_mean": 0.55, "p_test_mean": -245.0},
            {"method": "recon", "p_train_normalised_mean": 0.6, "p_test_normalised_mean": 0.1, "p_test_mean": -290.0}]
    line = reading(rows, 12_000, 1)
    assert "bati holds (0.50 -> 0.55)" in line and "recon falls (0.60 -> 0.10)" in line
    assert "best on p_test: bati." in line and "does not show" not in line and "1 seed(s) decide no ranking" in line
    rows[1].update(p_test_normalised_mean=0.9, p_test_mean=-210.0)  # Recon best on p_test: the effect does not show
    line = reading(rows, 3_000, 3)
    assert "best on p_test: recon. The paper's effect (BATI best under p_test contexts) does not show at 3,000 " \
           "steps and 3 seed(s)" in line and "decide no ranking" not in line


def test_sigterm_is_a_one_line_error_with_exit_code_143(capsys, monkeypatch):
    import signal
    import time

    from bati.cli_commands import Envs

    def terminated(self):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(10)  # the handler interrupts this

    monkeypatch.setattr(Envs, "run", terminated)
    before = signal.getsignal(signal.SIGTERM)
    code, out, err = run(capsys)
    assert code == 143
    assert_one_line_error(out, err, "terminated", "run the same command again to resume")
    assert signal.getsignal(signal.SIGTERM) is before
