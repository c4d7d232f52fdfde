"""`bati report DIR`: tables, CSVs and curves from hand-made eval.json files with known numbers."""

from __future__ import annotations

import csv
import json
from pathlib import Path
import math

import numpy as np
import pytest

from bati.cli import main
from bati.report import ReportWarning, build_report, load_runs
from bati.report.build import CSV_COLUMNS, method_order
from bati.report.runs import jobs_wall_time
from bati.report.stats import improvement_interval, iqm, iqm_interval, probability_of_improvement

RANDOM, EXPERT = -500.0, -250.0
# PointGoal, eps 1 (new format): method -> per seed (p_train, p_test, inference error p_train, p_test).
POINTGOAL = {
    "bati": [(-280.0, -300.0, 0.2, 0.3), (-290.0, -310.0, 0.3, 0.4), (-300.0, -320.0, 0.4, 0.5)],
    "recon": [(-270.0, -400.0, 0.1, 1.2), (-280.0, -410.0, 0.2, 1.3), (-290.0, -420.0, 0.3, 1.4)],
    "no-context": [(-350.0, -350.0, None, None), (-360.0, -360.0, None, None), (-370.0, -370.0, None, None)],
}


def config(family, method, seed, noise=1.0, **extra):
    return {"family": family, "method": method, "seed": seed, "scale": "quick", "steps": 3000, "noise": noise,
            "context_length": 200, "eval_context_length": 200, "data_seed": 0, "task_batch": 16,
            "batch_size": 64, "out_dir": f"runs/{family}/{method}-seed{seed}", "data_root": "data",
            "iql": {"expectile": 0.7}, **extra}


def write_run(root, family, method, seed, p_train, p_test, err_train, err_test, *, new=True, noise=1.0,
              evaluations=5, steps=3000, subdir=""):
    run_dir = root / subdir / family / f"{method}-seed{seed}"
    run_dir.mkdir(parents=True)
    curve = [{"step": s, "p_test_return": p_test + (steps - s) / 100 * (-1) ** seed,
              "p_train_return": p_train + (steps - s) / 200} for s in range(300, steps + 1, 300)]
    summary = {"family": family, "method": method, "seed": seed, "scale": "quick", "steps": steps,
               "evaluations_averaged": evaluations, "p_test_return": p_test, "p_train_return": p_train,
               "p_test_inference_error": err_test, "p_train_inference_error": err_train,
               "p_test_task_returns": [p_test] * 3, "p_train_task_returns": [p_train] * 3, "curve": curve}
    if new:
        for point in curve:
            point["p_test_inference_error"], point["p_train_inference_error"] = err_test, err_train
        summary.update(config=config(family, method, seed, noise),
                       reference_returns={"random": RANDOM, "expert": EXPERT},
                       data={"n_episodes": 20, "n_context_episodes": 5, "transitions": 80000},
                       device="cpu", jax_version="0.10.2", commit="abc1234", wall_time_s=12.5)
    (run_dir / "eval.json").write_text(json.dumps(summary))
    return run_dir


@pytest.fixture
def results(tmp_path):
    """PointGoal (new format, eps 1 and eps 0.5) and HopperParam (old format: no config, no references)."""
    root = tmp_path / "runs"
    for method, seeds in POINTGOAL.items():
        for seed, values in enumerate(seeds):
            write_run(root, "PointGoal", method, seed, *values)
            write_run(root, "PointGoal", method, seed, values[0] - 5, values[1] - 5, *values[2:], noise=0.5,
                      subdir="eps0.5")
    for method, base in (("bati", 1000.0), ("bati-r", 900.0), ("recon", 800.0)):
        for seed in range(3):
            write_run(root, "HopperParam", method, seed, base + 10 * seed, base - 100 + 10 * seed, 0.5, 0.6,
                      new=False)
    return root


def read_csv(path):
    with path.open() as f:
        return list(csv.DictReader(f))


def table(report, family, noise=None):
    found = [t for t in report["tables"] if t["settings"]["family"] == family
             and (noise is None or t["settings"].get("noise") == noise)]
    assert len(found) == 1, [t["title"] for t in report["tables"]]
    return found[0]


def row(entry, method):
    return next(r for r in entry["rows"] if r["method"] == method)


def test_grouping_titles_and_order(results):
    report = build_report(results, reps=200)
    assert len(report["tables"]) == 3  # PointGoal eps 1, PointGoal eps 0.5, HopperParam
    eps1, eps05 = table(report, "PointGoal", 1.0), table(report, "PointGoal", 0.5)
    assert "eps = 1" in eps1["title"] and "eps = 0.5" in eps05["title"]
    for entry in (eps1, eps05):
        for needle in ("PointGoal", "quick scale", "3,000 steps", "20 episodes per task", "C = 200"):
            assert needle in entry["title"]
        assert "80,000 transitions" in entry["markdown"] and "16 tasks × 64 transitions" in entry["markdown"]
        assert [r["method"] for r in entry["rows"]] == ["bati", "recon", "no-context"]
    hopper = table(report, "HopperParam")
    assert [r["method"] for r in hopper["rows"]] == ["bati", "bati-r", "recon"]
    assert "3,000 steps" in hopper["title"] and "eps not recorded" in hopper["title"]
    assert "size not recorded" in hopper["markdown"]
    assert sorted(["recon", "oracle", "bati-r", "csro", "no-context", "bati"], key=method_order) == [
        "bati", "bati-r", "csro", "recon", "oracle", "no-context"]


def test_mean_std_normalisation_ratio(results):
    report = build_report(results, reps=200)
    entry = table(report, "PointGoal", 1.0)
    bati = row(entry, "bati")
    assert bati["seeds"] == [0, 1, 2] and bati["n_seeds"] == 3
    assert bati["p_test_mean"] == pytest.approx(-310.0)
    assert bati["p_test_std"] == pytest.approx(math.sqrt(200 / 3))  # population std of -300, -310, -320
    assert bati["p_train_mean"] == pytest.approx(-290.0)
    assert "| bati | 0, 1, 2 | -290.0 ± 8.2 | -310.0 ± 8.2 |" in entry["markdown"]
    # (x - random) / (expert - random), per run then averaged: -300 -> 0.8, -310 -> 0.76, -320 -> 0.72
    assert bati["p_test_normalised_mean"] == pytest.approx(0.76)
    assert bati["p_test_normalised_std"] == pytest.approx(np.std([0.8, 0.76, 0.72]))
    assert bati["p_train_normalised_mean"] == pytest.approx(0.84)
    assert bati["test_train_ratio_normalised"] == pytest.approx(0.76 / 0.84)
    assert bati["test_train_ratio"] == pytest.approx(-310.0 / -290.0)
    assert bati["p_test_inference_error_mean"] == pytest.approx(0.4)
    assert bati["p_train_inference_error_mean"] == pytest.approx(0.3)
    assert "p_test normalised" in entry["markdown"] and "0.76 ± 0.03" in entry["markdown"]
    nocontext = row(entry, "no-context")
    assert math.isnan(nocontext["p_test_inference_error_mean"])
    expected = ("| no-context | 0, 1, 2 | -360.0 ± 8.2 | -360.0 ± 8.2 | 0.56 ± 0.03 | 0.56 ± 0.03 | 1.00 "
                "| – | – |")
    assert expected in entry["markdown"]


def test_iqm_and_probability_of_improvement_in_report(results):
    report = build_report(results, reps=300)
    entry = table(report, "PointGoal", 1.0)
    bati, recon, nocontext = (row(entry, m) for m in ("bati", "recon", "no-context"))
    # 3 runs: int(0.25 * 3) = 0 cut at each end, so IQM = mean
    assert bati["iqm_p_test"] == pytest.approx(0.76)
    assert bati["iqm_low"] <= bati["iqm_p_test"] <= bati["iqm_high"]
    assert bati["iqm_score"] == "p_test_normalised"
    # bati beats recon and no-context in every seed pair
    assert recon["p_bati_better"] == 1.0 and recon["p_bati_better_low"] == 1.0
    assert nocontext["p_bati_better"] == 1.0
    assert math.isnan(bati["p_bati_better"])  # not against itself
    assert "P(bati > method) [95% CI]" in entry["markdown"] and "1.00 [1.00, 1.00]" in entry["markdown"]
    hopper = table(report, "HopperParam")
    assert hopper["rows"][0]["iqm_score"] == "p_test_return"
    # bati-r's p_test (800, 810, 820) against bati's (900, 910, 920): bati-r never better
    assert row(hopper, "bati")["p_bati_r_better"] == 0.0
    for r in hopper["rows"]:
        for col in ("p_bati_better", "p_bati_r_better"):
            assert math.isnan(r[col]) or 0.0 <= r[f"{col}_low"] <= r[col] <= r[f"{col}_high"] <= 1.0


def test_iqm_hand_checked():
    assert iqm(np.array([0.0, 1.0, 2.0, 3.0, 100.0])) == pytest.approx(2.0)  # 1 cut each end: mean(1, 2, 3)
    assert iqm(np.array([[1.0, 2.0], [3.0, 4.0]])) == pytest.approx(2.5)  # runs x tasks flattened
    assert iqm(np.arange(8.0)) == pytest.approx(np.mean([2.0, 3.0, 4.0, 5.0]))
    value, low, high = iqm_interval(np.array([1.0, 2.0, 3.0, 4.0, 5.0]), reps=500)
    assert value == 3.0 and 1.0 <= low <= value <= high <= 5.0
    assert iqm_interval(np.array([1.0, 2.0, 3.0, 4.0, 5.0]), reps=500) == (value, low, high)  # seeded
    constant = iqm_interval(np.full((4, 3), 7.0), reps=50)
    assert constant == (7.0, 7.0, 7.0)


def test_probability_of_improvement_hand_checked():
    assert probability_of_improvement([3.0, 4.0], [1.0, 2.0]) == 1.0
    assert probability_of_improvement([1.0, 2.0], [3.0, 4.0]) == 0.0
    assert probability_of_improvement([1.0, 3.0], [2.0, 2.0]) == 0.5
    assert probability_of_improvement([2.0], [2.0]) == 0.5  # ties count one half
    # per task, then averaged over tasks: task 0 always better (1), task 1 never (0)
    x, y = np.array([[5.0, 0.0], [6.0, 1.0]]), np.array([[1.0, 5.0], [2.0, 6.0]])
    assert probability_of_improvement(x, y) == 0.5
    rng = np.random.default_rng(1)
    p, low, high = improvement_interval(rng.normal(size=5), rng.normal(size=4), reps=300)
    assert 0.0 <= low <= p <= high <= 1.0
    assert improvement_interval([3.0, 4.0, 5.0], [0.0, 1.0], reps=100) == (1.0, 1.0, 1.0)


def test_missing_references_give_no_normalised_columns(results):
    report = build_report(results, reps=100)
    hopper = table(report, "HopperParam")
    assert "normalised" not in hopper["markdown"].split("\n| ---")[0].splitlines()[-1]
    assert "p_test / p_train (returns)" in hopper["markdown"]
    assert "References: not recorded" in hopper["markdown"]
    assert row(hopper, "bati")["test_train_ratio"] == pytest.approx(910.0 / 1010.0)
    rows = read_csv(hopper["csv"])
    assert all(r["p_test_normalised_mean"] == "" and r["expert_return"] == "" for r in rows)


def test_csv_columns_and_values(results):
    report = build_report(results, reps=100)
    entry = table(report, "PointGoal", 1.0)
    with entry["csv"].open() as f:
        assert tuple(next(csv.reader(f))) == CSV_COLUMNS
    rows = read_csv(entry["csv"])
    assert [r["method"] for r in rows] == ["bati", "recon", "no-context"]
    bati = rows[0]
    assert bati["seeds"] == "0 1 2" and bati["n_seeds"] == "3" and bati["missing_seeds"] == ""
    assert float(bati["p_test_mean"]) == pytest.approx(-310.0)
    assert float(bati["p_test_normalised_mean"]) == pytest.approx(0.76)
    assert bati["steps"] == "3000" and bati["n_episodes"] == "20" and bati["transitions"] == "80000"
    assert float(bati["noise"]) == 1.0 and float(bati["random_return"]) == RANDOM
    assert rows[2]["p_test_inference_error_mean"] == ""  # no-context infers no task
    runs = read_csv(report["out_dir"] / "runs.csv")
    assert len(runs) == 9 + 9 + 9
    assert {r["path"].endswith("eval.json") for r in runs} == {True}


def test_files_written(results, tmp_path):
    out = tmp_path / "elsewhere"
    report = build_report(results, out, reps=100)
    assert report["out_dir"] == out
    md = (out / "report.md").read_text()
    assert md == report["markdown"] and md.count("\n### ") == 3
    for entry in report["tables"]:
        assert entry["curves"].exists() and entry["curves"].suffix == ".png"
        assert entry["curves"].read_bytes()[:4] == b"\x89PNG"
        assert f"]({entry['curves'].name})" in md
        assert entry["csv"].exists()
    # inference-error curves only where the curves record the error (new format)
    assert table(report, "PointGoal", 1.0)["inference_curves"].exists()
    assert table(report, "HopperParam")["inference_curves"] is None
    assert not (results / "report").exists()


def test_default_out_dir_and_rerun(results):
    first = build_report(results, reps=100)
    assert first["out_dir"] == results / "report" and (results / "report" / "report.md").exists()
    # deterministic, and its own output directory is not read back
    assert build_report(results, reps=100)["markdown"] == first["markdown"]


def test_incomplete_groups_and_bad_files(tmp_path):
    root = tmp_path / "runs"
    for seed in range(3):
        write_run(root, "PointGoal", "bati", seed, -280.0, -300.0 - seed, 0.2, 0.3)
    write_run(root, "PointGoal", "recon", 0, -270.0, -400.0, 0.1, 1.2, evaluations=3)
    (root / "broken").mkdir()
    (root / "broken" / "eval.json").write_text("{not json")
    (root / "partial").mkdir()
    (root / "partial" / "eval.json").write_text(json.dumps({"family": "PointGoal"}))
    with pytest.warns(ReportWarning) as caught:
        runs = load_runs(root)
    messages = [str(w.message) for w in caught]
    assert len(runs) == 4
    assert any(str(root / "broken" / "eval.json") in m for m in messages)
    assert any(str(root / "partial" / "eval.json") in m and "missing key" in m for m in messages)
    with pytest.warns(ReportWarning):
        report = build_report(root, reps=100)
    entry = report["tables"][0]
    recon = row(entry, "recon")
    assert recon["missing_seeds"] == [1, 2] and recon["n_seeds"] == 1
    assert "missing seed(s) 1, 2; only 3 evaluation(s) averaged" in entry["markdown"]
    assert "| recon | 0 | -270.0 | -400.0 |" in entry["markdown"]  # one seed: no ± std
    assert math.isnan(recon["iqm_p_test"]) and math.isnan(recon["p_bati_better"])  # fewer than 2 runs


def test_cli_report(results, tmp_path, capsys):
    out = tmp_path / "cli-out"
    assert main(["report", str(results), "--out-dir", str(out)]) == 0
    stdout, stderr = capsys.readouterr()
    assert "PointGoal" in stdout and "HopperParam" in stdout and str(out) in stdout.replace("\n", "")
    assert stderr == ""
    assert (out / "report.md").exists()


@pytest.mark.parametrize("case", ["missing", "file", "empty", "unreadable"])
def test_cli_bad_input(tmp_path, capsys, case):
    target = tmp_path / "target"
    if case == "file":
        target.write_text("x")
    elif case == "empty":
        (target / "sub").mkdir(parents=True)
    elif case == "unreadable":
        (target / "run").mkdir(parents=True)
        (target / "run" / "eval.json").write_text("[]")
    before = sorted(p for p in tmp_path.rglob("*"))
    out = tmp_path / "out"
    assert main(["report", str(target), "--out-dir", str(out)]) == 2
    stdout, stderr = capsys.readouterr()
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("error:") and str(target.name) in lines[0], stderr
    assert "Traceback" not in stdout + stderr
    if case == "unreadable":
        assert "warning: skipping" in stderr and "eval.json" in stderr
    assert not out.exists() and sorted(p for p in tmp_path.rglob("*")) == before


def test_earlier_sessions_time_adds_the_sessions_before_each_restart(tmp_path):
    from bati.report.runs import earlier_sessions_time

    clock = [1.0, 2.0, 3.5, 0.5, 4.0, 1.0, 2.0]  # three sessions: 3.5 s, 4.0 s, then the last one (eval.json's)
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps({"step": i, "wall_time": t}) + "\n"
                                                    for i, t in enumerate(clock)))
    assert earlier_sessions_time(tmp_path) == 7.5
    assert earlier_sessions_time(tmp_path / "missing") == 0.0


def test_curve_records_normalise_by_the_runs_own_references():
    from bati.experiments.report import curve_records
    from bati.report.runs import RunResult

    run = RunResult(path=Path("r/eval.json"), family="AntDir", method="oracle", seed=1, p_test_return=0.0,
                    p_train_return=0.0, reference_returns={"random": -40.0, "expert": 60.0},
                    curve=[{"step": 10, "p_test_return": 40.0, "p_train_return": 50.0}])
    (row,) = curve_records("AntDir-cpu", run)
    assert row["p_test_normalised"] == 0.8 and (row["setting"], row["method"], row["seed"], row["step"]) == (
        "AntDir-cpu", "oracle", 1, 10)
    assert curve_records("x", RunResult(path=Path("r/eval.json"), family="F", method="m", seed=0, p_test_return=0.0,
                                        p_train_return=0.0, curve=[{"step": 1, "p_test_return": 3.0}]))[0][
        "p_test_normalised"] is None


def test_settings_added_later_at_their_old_value_do_not_split_a_group(tmp_path):
    from bati.report.build import group_runs
    from bati.report.runs import load_runs

    write_run(tmp_path, "PointGoal", "bati", 0, -280.0, -300.0, 0.2, 0.3)
    newer = write_run(tmp_path, "PointGoal", "recon", 0, -270.0, -400.0, 0.1, 1.2)
    summary = json.loads((newer / "eval.json").read_text())
    summary["config"].update(datasets=[], held_out=0.2, family_version=1)  # what a newer version records
    (newer / "eval.json").write_text(json.dumps(summary))
    assert len(group_runs(load_runs(tmp_path))) == 1
    summary["config"].update(eval_workers=4, zoo_dir="/elsewhere")  # not part of a run's identity
    (newer / "eval.json").write_text(json.dumps(summary))
    assert len(group_runs(load_runs(tmp_path))) == 1
    summary["config"]["family_version"] = 2  # another env version is another setting
    (newer / "eval.json").write_text(json.dumps(summary))
    assert len(group_runs(load_runs(tmp_path))) == 2


def test_a_damaged_eval_json_is_skipped_by_name_and_never_wins_over_a_valid_duplicate(tmp_path):
    from bati.report.runs import ReportWarning, load_runs

    valid = write_run(tmp_path, "PointGoal", "bati", 0, -280.0, -300.0, 0.2, 0.3, subdir="b")
    damaged = write_run(tmp_path, "PointGoal", "bati", 0, -280.0, -300.0, 0.2, 0.3, subdir="a")  # sorts first
    for edit, why in (({"p_test_return": "abc"}, "p_test_return is 'abc'"), ({"curve": [1, 2]}, "its curve"),
                      ({"p_train_return": None}, "p_train_return is None")):
        summary = json.loads((valid / "eval.json").read_text()) | edit
        (damaged / "eval.json").write_text(json.dumps(summary))
        with pytest.warns(ReportWarning, match=f"skipping {damaged / 'eval.json'}: {why}"):
            (run,) = load_runs(tmp_path)
        assert run.path == valid / "eval.json"


def test_a_runs_test_time_rules_read_as_runs_of_their_own_with_the_runs_shared_records(tmp_path):
    from bati.report.runs import ReportWarning, load_runs
    from bati.report.stored_plan import PlannedCell

    run_dir = write_run(tmp_path, "PointGoal", "bati", 0, -280.0, -300.0, 0.2, 0.3)
    summary = json.loads((run_dir / "eval.json").read_text())
    rule = {"p_test_return": -250.0, "p_train_return": -240.0, "p_test_inference_error": 0.1,
            "p_train_inference_error": 0.05, "p_test_task_returns": [-250.0] * 3, "p_train_task_returns": [-240.0] * 3,
            "evaluations_averaged": 5, "curve": [{"step": 3000, "p_test_return": -250.0}], "wall_time_s": 1.5}
    (run_dir / "eval.json").write_text(json.dumps({**summary, "rules": {"bati-r": rule}}))
    bati, bati_r = load_runs(tmp_path)
    assert (bati.method, bati.p_test_return, bati.wall_time_s) == ("bati", -300.0, 12.5)
    assert (bati_r.method, bati_r.p_test_return, bati_r.p_train_inference_error) == ("bati-r", -250.0, 0.05)
    assert (bati_r.curve, bati_r.wall_time_s) == (rule["curve"], 1.5)  # its own evaluations and their seconds
    assert (bati_r.reference_returns, bati_r.commit, bati_r.seed) == (bati.reference_returns, "abc1234", 0)  # shared
    assert bati_r.config["method"] == "bati-r" and bati_r.settings_key() == bati.settings_key()  # one table
    cell = lambda method: PlannedCell("id", "label", "PointGoal", method, 0, 1.0, 200, "conditioned", run_dir)  # noqa: E731
    assert cell("bati-r").result().p_test_return == -250.0 and cell("bati").result().p_test_return == -300.0
    assert cell("bati-auto").result() is None  # the run did not evaluate it: not finished, nothing said
    (run_dir / "eval.json").write_text(json.dumps({**summary, "rules": {"bati-r": {**rule, "p_test_return": None}}}))
    with pytest.warns(ReportWarning, match="p_test_return is None"):
        assert load_runs(tmp_path) == []  # a damaged rule: the file is named and skipped, as any damage


def test_a_full_disk_names_the_report_directory_and_keeps_the_previous_report(results, tmp_path, monkeypatch, capsys):
    import errno
    import os

    import bati.report.build as build_module

    out = tmp_path / "report-out"
    assert main(["report", str(results), "--out-dir", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = build_module.atomic_write_text, []

    def full_disk(path, text):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, text)

    monkeypatch.setattr(build_module, "atomic_write_text", full_disk)
    capsys.readouterr()
    assert main(["report", str(results), "--out-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {out}: no space left on device"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the previous report, whole
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no staging left


def test_a_method_setting_off_its_default_is_a_table_of_its_own_named_by_it(tmp_path):
    from bati.records import default_method_record

    root = tmp_path / "runs"
    today = default_method_record("PointGoal", "csro")  # club_negatives "same-task"
    for seed in range(3):
        write_run(root, "PointGoal", "bati", seed, -300.0, -310.0, 0.5, 0.6)
        for subdir, section in (("today", today), ("old", {**today, "club_negatives": "any-task"})):
            path = write_run(root, "PointGoal", "csro", seed, -320.0, -330.0, 0.5, 0.6, subdir=subdir) / "eval.json"
            summary = json.loads(path.read_text())
            summary["config"]["csro"] = section
            path.write_text(json.dumps(summary))
    report = build_report(root, tmp_path / "report")
    titles = {tuple(sorted(r["method"] for r in t["rows"])): t["title"] for t in report["tables"]}
    assert set(titles) == {("bati", "csro"), ("csro",)}  # today's CSRO beside BATI, the old one apart
    assert "club_negatives = any-task" in titles[("csro",)] and "club_weight" not in titles[("csro",)]
    assert "csro" not in titles[("bati", "csro")]


def test_runs_with_different_references_say_so_and_keep_their_own_normalisation(tmp_path):
    """Runs of one setting whose data were collected on different machines record different expert
    references (a chaotic rollout amplifies the last bits of a float): the report says the range."""
    write_run(tmp_path, "PointGoal", "bati", 0, -280.0, -300.0, 0.2, 0.3)
    other = write_run(tmp_path, "PointGoal", "recon", 0, -270.0, -400.0, 0.1, 1.2)
    summary = json.loads((other / "eval.json").read_text())
    summary["reference_returns"]["expert"] = -200.0
    (other / "eval.json").write_text(json.dumps(summary))
    report = build_report(tmp_path, reps=50)
    markdown = table(report, "PointGoal")["markdown"]
    assert "experts -225.0 (means over runs; the runs' own differ: expert -250.0 to -200.0" in markdown
    assert row(table(report, "PointGoal"), "recon")["p_test_normalised_mean"] == pytest.approx(100.0 / 300.0)
    (other / "eval.json").write_text(json.dumps({**summary, "reference_returns": {"random": RANDOM, "expert": EXPERT}}))
    assert "differ" not in table(build_report(tmp_path, reps=50), "PointGoal")["markdown"]
    # the same references but other numbers in the data (eval.json's data.fingerprint): said too
    for run, fingerprint in ((other, "0123456789abcdef"), (tmp_path / "PointGoal" / "bati-seed0", "fedcba9876543210")):
        summary = json.loads((run / "eval.json").read_text())
        (run / "eval.json").write_text(json.dumps({**summary, "data": {"fingerprint": fingerprint}}))
    assert "the runs' own differ: 2 different data fingerprints" in table(build_report(tmp_path, reps=50),
                                                                          "PointGoal")["markdown"]


def test_the_device_names_the_cpu_model(tmp_path):
    from bati.device import cpu_model

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC   7B13\nflags\t: fpu\n")
    assert cpu_model(info) == "AMD EPYC 7B13"
    info.write_text("model name\t: AMD EPYC\nflags\t: fpu avx avx2 fma avx512f avx512ifma\n")
    assert cpu_model(info) == "AMD EPYC, AVX-512"  # XLA's kernels follow the vector width
    info.write_text("model name\t: AMD EPYC\nflags\t: fpu avx avx2 fma\n")
    assert cpu_model(info) == "AMD EPYC, AVX2"
    info.write_text("processor\t: 0\n")
    assert cpu_model(info) == "CPU" and cpu_model(tmp_path / "missing") == "CPU"


def test_wall_time_counts_a_vmapped_job_once_and_one_seed_jobs_each():
    """Seeds trained in one vmapped job record the job's time (counted once); seeds of the same setting trained
    one per job (the cpu queue) record their own times (each counted)."""
    vmapped = [(("AntDir/cpu", "bati"), 1200.0)] * 3
    one_per_job = [(("AntDir/cpu", "csro"), 5796.0), (("AntDir/cpu", "csro"), 3501.9)]
    assert jobs_wall_time(vmapped + one_per_job) == pytest.approx(1200.0 + 5796.0 + 3501.9)


def test_the_drift_over_the_scored_window_says_whether_a_number_still_moves(results, tmp_path):
    """The fixture's curves approach their number along a line of slope -/+1 per 100 steps (seeds 0, 2 / 1): over
    the 5 evaluations averaged (1,800-3,000 steps) the drift is -12, +12, -12 raw, -0.048 / +0.048 normalised."""
    report = build_report(results, out_dir=tmp_path / "report", reps=200)
    entry = table(report, "PointGoal", 1.0)
    bati = row(entry, "bati")
    assert bati["p_test_drift"] == pytest.approx(-4.0 / 250.0)
    assert bati["p_test_drift_low"] <= bati["p_test_drift"] <= bati["p_test_drift_high"]
    assert "p_test drift over the scored window [95% CI]" in entry["markdown"]
    assert "-0.02 [" in entry["markdown"] and "] flat |" in entry["markdown"]
    runs = read_csv(tmp_path / "report" / "runs.csv")
    drifts = sorted(float(r["p_test_drift"]) for r in runs if r["table"] == entry["slug"] and r["method"] == "bati")
    assert drifts == pytest.approx([-0.048, -0.048, 0.048])
    hopper = table(report, "HopperParam")  # old files without references: raw returns, -12 / +12 / -12
    assert row(hopper, "bati")["p_test_drift"] == pytest.approx(-4.0)


def test_runs_from_code_with_uncommitted_changes_are_flagged(results, tmp_path):
    flagged = results / "PointGoal" / "bati-seed0" / "eval.json"
    summary = json.loads(flagged.read_text())
    flagged.write_text(json.dumps({**summary, "uncommitted_changes": True}))
    older = results / "PointGoal" / "bati-seed1" / "eval.json"  # records before the flag: a "-dirty" commit
    older.write_text(json.dumps({**json.loads(older.read_text()), "commit": "abc1234-dirty"}))
    assert sorted(r.uncommitted_changes for r in load_runs(results)).count(True) == 2
    report = build_report(results, tmp_path / "report")
    assert "**2 run(s) from code with uncommitted changes**" in report["markdown"]


TRAINING_MODULES = ("bati.inference", "bati.train", "bati.trainer", "bati.checkpoints", "bati.methods",
                    "bati.evaluate", "bati.experiments")


def test_the_report_layer_imports_nothing_from_training():
    """bati.report reads result files only: no module of it imports (at the top or inside a function) the code
    that trains, evaluates or opens checkpoints, nor the experiments built on top of it."""
    import ast

    import bati.report

    package = Path(bati.report.__file__).parent
    imports = []
    for path in sorted(package.rglob("*.py")):
        parts = ["bati", *path.relative_to(package.parent).parent.parts]  # the package the file is in
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                imports += [(path.name, alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):  # `from bati import train` imports bati.train too
                base = ".".join(parts[:len(parts) + 1 - node.level]) if node.level else ""  # relative imports
                module = ".".join(filter(None, (base, node.module)))
                imports += [(path.name, module)] + [(path.name, f"{module}.{alias.name}") for alias in node.names]
    assert any(name.startswith("bati.") for _, name in imports)  # the walk sees bati's own imports
    wrong = [(file, name) for file, name in imports
             if any(name == module or name.startswith(module + ".") for module in TRAINING_MODULES)]
    assert not wrong, wrong


@pytest.mark.parametrize("shapes", [((5, 1), (4, 1)), ((3, 5), (3, 5)), ((7, 2), (2, 2))])
def test_intervals_are_rliables_own(shapes):
    """The replicates computed at once give rliable's numbers: the same draws, statistics and percentiles as
    rliable.library.get_interval_estimates (seeded numpy global generator, 95% percentile interval)."""
    import warnings

    from rliable import library, metrics

    from bati.report.stats import mean_interval

    def reference(scores, func, reps=300, seed=3):
        saved = np.random.get_state()
        np.random.seed(seed)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", FutureWarning)
                point, interval = library.get_interval_estimates({"x": scores}, func, reps=reps,
                                                                 random_state=np.random.RandomState(seed))
        finally:
            np.random.set_state(saved)
        return (float(np.asarray(point["x"]).reshape(())), *np.asarray(interval["x"]).reshape(2))

    rng = np.random.default_rng(sum(sum(s) for s in shapes))
    x = rng.normal(size=shapes[0]).round(1)  # rounded: ties between x and y occur
    y = rng.normal(size=shapes[1]).round(1)
    assert iqm_interval(x, reps=300, seed=3) == pytest.approx(
        reference(x, lambda s: np.array([metrics.aggregate_iqm(s)])), abs=1e-12)
    assert mean_interval(x, reps=300, seed=3) == pytest.approx(
        reference(x, lambda s: np.array([metrics.aggregate_mean(s)])), abs=1e-12)
    assert improvement_interval(x, y, reps=300, seed=3) == pytest.approx(
        reference([x, y], lambda a, b: np.array([metrics.probability_of_improvement(a, b)])), abs=1e-12)


def test_a_cpu_run_names_the_cores_it_used(tmp_path):
    """One CPU gives other numbers on one core than on two: the report's device says the cores where a run's
    record has them; a GPU run's device and an older record's stay as they are."""
    from bati.report.runs import RunResult

    cpu = "cpu: 2-core AMD EPYC, AVX-512 (x86_64) x1"
    base = {"family": "PointGoal", "method": "bati", "seed": 0, "p_test_return": 1.0, "p_train_return": 2.0}

    def run(**extra):
        return RunResult.from_dict({**base, **extra}, tmp_path / "eval.json")

    assert run(device=cpu, cpu_cores=1).machine == f"{cpu}, 1 core used"
    assert run(device=cpu, cpu_cores=2).machine == f"{cpu}, 2 cores used"
    assert run(device=cpu).machine == cpu  # recorded before the cores were
    assert run(device=cpu, cpu_cores="two").cpu_cores is None
    assert run(device="gpu: NVIDIA H200 x1", cpu_cores=16).machine == "gpu: NVIDIA H200 x1"


def test_an_unwritable_report_folder_is_named_not_its_staging_folder(results, tmp_path, monkeypatch):
    import os

    from bati.errors import BatiError

    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if mode & os.W_OK else real(path, mode, **kw))
    with pytest.raises(BatiError, match=r"the report directory .*/out is not writable") as caught:
        build_report(results, tmp_path / "out", reps=10)
    assert "/.out-" not in str(caught.value) and not (tmp_path / "out").exists()


def test_the_report_modules_import_no_jax():
    """`bati report` reads JSON files: importing its modules (and the experts' kinds they label data with) must not
    pull in JAX, whose import alone takes seconds."""
    import subprocess
    import sys

    code = "import sys, bati.report.build, bati.experts.kinds; print('jax' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "False", done.stderr[-2000:]
