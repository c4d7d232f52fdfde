"""scripts/check_reports.py: a committed experiment report that no longer regenerates from its runs is named."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def test_check_reports_finds_a_committed_report_that_does_not_regenerate(tmp_path):
    # a project whose results/ holds one `bati experiment` report (ood-tasks, no cell finished: seconds) and one of
    # `bati report`; the first regenerates until its table is edited by hand
    from bati.cli import main

    project = tmp_path / "project"
    out = project / "results" / "quick" / "experiments"
    assert main(["experiment", "ood-tasks", "--report-only", "--out-dir", str(out),
                 "--data-root", str(tmp_path / "data")]) == 0
    report = out / "ood-tasks" / "report.md"
    (project / "results" / "other").mkdir()
    (project / "results" / "other" / "report.md").write_text("# Report\n")
    check = [sys.executable, str(SCRIPTS / "check_reports.py"), "--root", str(project)]
    done = subprocess.run(check, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "same     results/quick/experiments/ood-tasks/report.md" in done.stdout
    assert "skipped  results/other/report.md" in done.stdout  # names no command
    report.write_text(report.read_text().replace("cells finished: 0 of", "cells finished: 1 of"))
    done = subprocess.run(check + [str(report)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1 and "differs  results/quick/experiments/ood-tasks/report.md" in done.stdout
    assert "-- cells finished: 1 of" in done.stdout and "+- cells finished: 0 of" in done.stdout
    assert "cells finished: 1 of" in report.read_text()  # the committed report untouched: the rerun ran in a copy
    (report.parent / "FROZEN").write_text("runs of a family version since replaced\n")
    done = subprocess.run(check + [str(report)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "frozen   results/quick/experiments/ood-tasks/report.md" in done.stdout
    assert "runs of a family version since replaced" in done.stdout


def test_a_rerun_setting_joins_the_committed_commands_settings():
    sys.path.insert(0, str(SCRIPTS))
    try:
        from check_reports import with_settings, without
    finally:
        sys.path.remove(str(SCRIPTS))
    args = ["experiment", "main", "--settings", "steps=12000", "--seeds", "1", "--out-dir", "out"]
    assert with_settings(args, ["--settings", "csro.club_negatives=any-task"]) == [
        "experiment", "main", "--settings", "steps=12000", "csro.club_negatives=any-task", "--seeds", "1", "--out-dir",
        "out"]
    assert with_settings(["experiment", "kuhn"], ["--settings", "a=1"]) == ["experiment", "kuhn", "--settings", "a=1"]
    assert without(without(args, "--seeds"), "--out-dir") == ["experiment", "main", "--settings", "steps=12000"]
