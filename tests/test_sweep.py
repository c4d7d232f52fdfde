"""`bati sweep`: grid expansion, cell identity, skipping finished cells, failures, backends, bad input."""

from __future__ import annotations

import json
import os
import socket

import pytest

import bati.train as train_module
from bati.cli import main
from bati.data import Collection
from bati.experiments import sweep as sweep_module
from bati.experiments.sweep import Grid, SweepError, expand, make_jobs, sweep_grid

TINY = ("steps=10", "eval_every=5", "log_every=5", "task_batch=4", "batch_size=8", "context_length=20",
        "iql.hidden_dims=[32,32]")


def test_grid_expands_to_every_cell_with_its_own_directory(tmp_path):
    grid = Grid(families=("PointGoal", "HalfCheetahVel"), methods=("bati", "recon", "no-context"), seeds=(0, 1),
                noises=(0.0, 0.5), settings=("steps=40",))
    cells = expand(grid, tmp_path)
    assert len(cells) == 2 * 3 * 2 * 2
    assert len({c.id for c in cells}) == len(cells) == len({c.config.out_dir for c in cells})
    assert all(c.config.steps == 40 for c in cells)
    jobs = make_jobs(cells)
    assert len(jobs) == 2 * 3 * 2 and all(job.seeds == (0, 1) for job in jobs)
    cell = next(c for c in cells if (c.config.family, c.config.method, c.config.seed, c.config.noise)
                == ("HalfCheetahVel", "recon", 1, 0.5))
    assert cell.config.out_dir.parent.parent == tmp_path / "HalfCheetahVel"
    assert cell.config.out_dir.name == "recon-seed1" and cell.config.out_dir.parent.name.startswith("quick-eps0.5-")


def test_a_method_that_trains_as_another_joins_its_job_of_the_same_setting_and_seeds(tmp_path):
    def plan(*grids):
        jobs = make_jobs([c for g in grids for c in expand(g, tmp_path)])
        return sorted((j.config.method, j.seeds, j.rule_methods) for j in jobs)

    assert plan(Grid(methods=("bati", "bati-r", "bati-auto", "recon"), seeds=(0, 1))) == [
        ("bati", (0, 1), ("bati-r", "bati-auto")), ("recon", (0, 1), ())]
    # without its host in the grid, or with other seeds or settings, it trains on its own
    assert plan(Grid(methods=("bati-r",))) == [("bati-r", (0,), ())]
    # ... or hosts the other one that trains alike (no bati in the grid: one training for bati-r and bati-auto)
    assert plan(Grid(methods=("bati-auto", "bati-r", "recon"))) == [("bati-auto", (0,), ("bati-r",)),
                                                                  ("recon", (0,), ())]
    assert plan(Grid(methods=("bati",), seeds=(0, 1)), Grid(methods=("bati-r",), seeds=(0,))) == [
        ("bati", (0, 1), ()), ("bati-r", (0,), ())]
    assert plan(Grid(methods=("bati",)), Grid(methods=("bati-r",), settings=("steps=40",))) == [
        ("bati", (0,), ()), ("bati-r", (0,), ())]
    assert len(make_jobs(expand(Grid(methods=("bati", "bati-r")), tmp_path), share_training=False)) == 2


def test_a_rule_is_hosted_by_the_first_run_that_can_evaluate_it_from_its_start(tmp_path):
    grid = Grid(methods=("bati-auto", "bati-r", "bati"), settings=TINY)
    hosts = lambda: {c.config.method: (c.host, c.config.out_dir.name) for c in expand(grid, tmp_path)}  # noqa: E731
    assert hosts() == {"bati": ("", "bati-seed0"), "bati-r": ("bati", "bati-seed0"), "bati-auto": ("bati", "bati-seed0")}
    run = next(c for c in expand(grid, tmp_path) if c.config.method == "bati").config.out_dir
    run.mkdir(parents=True)
    (run / "eval.jsonl").write_text('{"step": 10, "p_test_return": 1.0, "rules": {"bati-r": {}}}\n')  # began with bati-r
    assert hosts()["bati-r"] == ("bati", "bati-seed0") and hosts()["bati-auto"] == ("", "bati-auto-seed0")
    (run / "eval.jsonl").write_text('{"step": 10, "p_test_return": 1.0}\n')  # began with no rule: the first rule hosts
    assert hosts()["bati-auto"] == ("", "bati-auto-seed0") and hosts()["bati-r"] == ("bati-auto", "bati-auto-seed0")
    (run.parent / "bati-r-seed0").mkdir()
    (run.parent / "bati-r-seed0" / "config.json").write_text("{}")  # a run of its own already: it stays one
    assert hosts()["bati-r"] == ("", "bati-r-seed0")


def test_default_noise_and_all_methods_resolve_like_explicit_ones(tmp_path):
    from bati.methods import METHODS

    implicit = expand(Grid(methods=("all",)), tmp_path)
    explicit = expand(Grid(methods=tuple(METHODS), noises=(1.0,)), tmp_path)  # PointGoal's default eps
    assert [c.id for c in implicit] == [c.id for c in explicit]


def test_a_cell_identity_is_its_whole_config(tmp_path):
    base = expand(Grid(), tmp_path)[0]
    for setting in ("steps=4000", "context_length=50", "eval_context_length=400", "learning_rate=0.001"):
        assert expand(Grid(settings=(setting,)), tmp_path)[0].id != base.id, setting


@pytest.mark.parametrize("grid, message", [
    (Grid(families=("Bogus",)), "Bogus"),
    (Grid(methods=("bati", "bogus")), "unknown method"),
    (Grid(seeds=()), "seeds are empty"),
    (Grid(families=()), "families are empty"),
    (Grid(noises=(-1.0,)), "noise"),
    (Grid(noises=(float("inf"),)), "noise eps=inf is outside"),
    (Grid(settings=("stepz=3",)), "unknown setting 'stepz'"),
    (Grid(settings=("seed=3",)), "seed cannot be set"),
    (Grid(settings=("steps",)), "not KEY=VALUE"),
    (Grid(settings=("steps=0",)), "steps must be an integer >= 1"),
    (Grid(seeds=(-1,)), "seed must be an integer >= 0"),
])
def test_bad_grids_are_refused_before_anything_is_written(tmp_path, grid, message):
    with pytest.raises(SweepError, match=message):
        sweep_grid(grid, tmp_path / "sweep", show_progress=False)
    assert not (tmp_path / "sweep").exists()


def test_bad_workers_backend_and_directories(tmp_path):
    with pytest.raises(SweepError, match="workers must be"):
        sweep_grid(Grid(), tmp_path / "s", workers=0, show_progress=False)
    with pytest.raises(SweepError, match="unknown backend"):
        sweep_grid(Grid(), tmp_path / "s", backend="slurm", show_progress=False)
    (tmp_path / "file").write_text("keep me")
    with pytest.raises(SweepError, match="is a file"):
        sweep_grid(Grid(), tmp_path / "file", show_progress=False)
    with pytest.raises(SweepError, match="is a file"):
        sweep_grid(Grid(), tmp_path / "file" / "sub", show_progress=False)
    assert (tmp_path / "file").read_text() == "keep me"
    assert not (tmp_path / "s").exists()


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_unreachable_ray_address_is_one_line_and_exit_2(tmp_path, capsys):
    pytest.importorskip("ray")
    code = main(["sweep", "--out-dir", str(tmp_path / "s"), "--backend", "ray", "--address",
                 f"127.0.0.1:{_closed_port()}"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "cannot reach a Ray cluster" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_cli_bad_grid_is_one_line_and_exit_2(tmp_path, capsys):
    code = main(["sweep", "--families", "PointGoal", "--methods", "bati", "bogus", "--out-dir", str(tmp_path / "s")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "unknown method" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s").exists()


# --- running cells (in this process, on synthetic data) ---------------------------------------
@pytest.fixture
def local(monkeypatch, synthetic_data):
    data = synthetic_data("PointGoal")
    monkeypatch.setattr(Collection, "ensure", lambda *a, **k: data)
    monkeypatch.setattr(sweep_module, "prepare_data", lambda cells, progress, check_only=False: None)
    return data


def _statuses(out, record="sweep.json"):
    return sorted(cell["status"] for cell in json.loads((out / record).read_text())["cells"].values())


def test_a_sweep_runs_every_cell_then_skips_finished_ones(tmp_path, local, monkeypatch):
    grid = Grid(methods=("bati", "no-context"), seeds=(0, 1), settings=TINY)
    out = tmp_path / "sweep"
    result = sweep_grid(grid, out, show_progress=False)
    assert result.count("done") == 4 and _statuses(out) == ["done"] * 4
    for cell in expand(grid, out):
        summary = json.loads((cell.config.out_dir / "eval.json").read_text())
        assert summary["seed"] == cell.config.seed and summary["steps"] == 10

    def no_training(*args, **kwargs):
        raise AssertionError("a finished cell was trained again")

    monkeypatch.setattr(sweep_module, "run_job", no_training)
    again = sweep_grid(grid, out, show_progress=False)
    assert again.count("skipped") == 4 and _statuses(out) == ["skipped"] * 4


def test_a_failed_job_is_recorded_and_the_rest_goes_on_and_a_rerun_completes_it(tmp_path, local, monkeypatch,
                                                                                capsys):
    grid = Grid(methods=("bati", "recon"), seeds=(0,), settings=TINY)
    out = tmp_path / "sweep"
    real = sweep_module.run_job

    def flaky(config, seeds, runs_dir, references=None, rules=()):
        if config.method == "recon":
            raise RuntimeError("disk on fire")
        return real(config, seeds, runs_dir, references, rules)

    monkeypatch.setattr(sweep_module, "run_job", flaky)
    result = sweep_grid(grid, out, show_progress=False)
    assert result.count("done") == 1 and result.count("failed") == 1
    cells = json.loads((out / "sweep.json").read_text())["cells"]
    failed = [c for c in cells.values() if c["status"] == "failed"]
    assert failed[0]["label"] == "PointGoal/recon/seed0" and failed[0]["error"] == "RuntimeError: disk on fire"
    # without a terminal (a background run's log), one line per job as it starts and ends
    lines = [line.split("] ", 1)[1] for line in capsys.readouterr().err.splitlines() if "] sweep: " in line]
    assert lines[0] == "sweep: PointGoal quick eps 1 (per-task experts) bati seeds 0: running"
    assert lines[1].startswith("sweep: PointGoal quick eps 1 (per-task experts) bati seeds 0: done after ")
    assert lines[2:] == ["sweep: PointGoal quick eps 1 (per-task experts) recon seeds 0: running",
                         "sweep: PointGoal quick eps 1 (per-task experts) recon seeds 0: failed (RuntimeError: disk on fire) after 0.0 min"]

    ran = []
    monkeypatch.setattr(sweep_module, "run_job", lambda config, seeds, runs_dir, references=None, rules=():
                        ran.append(config.method) or real(config, seeds, runs_dir, references, rules))
    rerun = sweep_grid(grid, out, show_progress=False)
    assert ran == ["recon"] and rerun.count("done") == 1 and rerun.count("skipped") == 1


def test_a_rules_cells_are_done_in_their_hosts_run_without_training_again(tmp_path, local, monkeypatch):
    grid = Grid(methods=("bati", "bati-r", "no-context"), seeds=(0,), settings=TINY)
    out = tmp_path / "sweep"
    real, ran = sweep_module.run_job, []
    monkeypatch.setattr(sweep_module, "run_job", lambda config, seeds, runs_dir, references=None, rules=():
                        ran.append((config.method, rules)) or real(config, seeds, runs_dir, references, rules))
    result = sweep_grid(grid, out, show_progress=False)
    assert sorted(ran) == [("bati", ("bati-r",)), ("no-context", ())]
    assert result.count("done") == 3 and _statuses(out) == ["done"] * 3
    cells = {c.config.method: c for c in expand(grid, out)}
    assert cells["bati-r"].config.out_dir == cells["bati"].config.out_dir and cells["bati-r"].host == "bati"
    assert not (cells["bati"].config.out_dir.parent / "bati-r-seed0").exists()  # one run directory per training
    saved = json.loads((cells["bati"].config.out_dir / "eval.json").read_text())
    assert saved["method"] == "bati" and set(saved["rules"]) == {"bati-r"}
    assert sweep_grid(grid, out, show_progress=False).count("skipped") == 3
    # bati-auto asked for later: bati's run has evaluations without it, so it trains on its own
    ran.clear()
    more = Grid(methods=("bati", "bati-auto"), seeds=(0,), settings=TINY)
    auto = next(c for c in expand(more, out) if c.config.method == "bati-auto")
    assert auto.host == "" and auto.config.out_dir.name == "bati-auto-seed0"
    assert sweep_grid(more, out, show_progress=False).count("done") == 1 and ran == [("bati-auto", ())]
    # bati-r alone asked for in a fresh setting: the bati run that evaluates it trains
    ran.clear()
    alone = Grid(methods=("bati", "bati-r"), seeds=(0,), settings=TINY + ("iql.tau=0.8",))
    rule = next(c for c in expand(alone, out) if c.config.method == "bati-r")
    assert sweep_module.sweep([rule], out, show_progress=False).count("done") == 1
    assert ran == [("bati", ("bati-r",))] and (rule.config.out_dir.name, rule.host) == ("bati-seed0", "bati")


def test_the_reference_returns_are_computed_once_per_collection(tmp_path, local, monkeypatch):
    calls = []
    real = train_module.reference_returns
    monkeypatch.setattr(train_module, "reference_returns", lambda *a, **k: calls.append(1) or real(*a, **k))
    grid = Grid(methods=("bati", "no-context", "oracle"), seeds=(0,), settings=TINY)
    sweep_grid(grid, tmp_path / "sweep", show_progress=False)
    saved = [json.loads((c.config.out_dir / "eval.json").read_text())["reference_returns"]
             for c in expand(grid, tmp_path / "sweep")]
    assert len(calls) == 1 and saved[0] == saved[1] == saved[2] and set(saved[0]) == {"random", "expert"}


def test_bati_run_is_a_sweep_plus_the_report_and_a_rerun_trains_nothing(tmp_path, local, monkeypatch, capsys):
    from bati.experiments import pipeline as pipeline_module

    split = []  # the main experiment keeps each BATI run's likelihood split (here on synthetic data: recorded)

    def save_split(run_dir, length):
        split.append(run_dir.name)
        from bati.report.likelihood import SOURCES, TERMS

        terms = {f"{s}_{t}_{k}": 0.0 for s in SOURCES for t in TERMS for k in ("error", "picks_collector")}
        (run_dir / "likelihood.json").write_text(json.dumps({"step": 10, "context_length": length, **terms}))

    monkeypatch.setattr(pipeline_module, "save_likelihood_split", save_split)
    out = tmp_path / "main"
    args = ["run", "--methods", "bati", "--seeds", "0", "1", "--out-dir", str(out),
            "--settings", *(s for s in TINY if not s.startswith("steps")), "--steps", "10"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "Reading (normalised" in printed and "results in" in printed
    results = json.loads((out / "results.json").read_text())
    assert [row["method"] for row in results["rows"]] == ["bati"]
    assert all(row["n_seeds"] == 2 for row in results["rows"]) and results["reading"].startswith("Reading")
    assert results["reading"] in (out / "results.md").read_text()
    assert (out / "report" / "report.md").is_file() and (out / "report" / "runs.csv").is_file()
    assert _statuses(out, "main.sweep.json") == ["done"] * 2  # the main experiment's cells on PointGoal
    assert sorted(split) == ["bati-seed0", "bati-seed1"]

    real = sweep_module.run_job
    monkeypatch.setattr(sweep_module, "run_job", lambda *a, **k: pytest.fail("a finished run was trained again"))
    assert main(args) == 0 and _statuses(out, "main.sweep.json") == ["skipped"] * 2

    other = [a if a != "10" else "15" for a in args]  # another setting into the same directory: its own table
    monkeypatch.setattr(sweep_module, "run_job", real)
    assert main(other) == 0
    assert json.loads((out / "results.json").read_text())["table"].find("15 steps") >= 0


def test_cli_sweep_ends_with_the_report(tmp_path, local, capsys):
    out = tmp_path / "sweep"
    args = ["sweep", "--methods", "bati", "--seeds", "0", "--out-dir", str(out), "--settings", *TINY]
    assert main(args) == 0
    assert (out / "report" / "report.md").exists()
    assert "1 cell(s) run" in capsys.readouterr().out


def test_a_second_sweep_on_the_same_record_is_refused_and_writes_nothing(tmp_path, local, monkeypatch):
    from bati.errors import LockedError
    from bati.experiments.sweep import record_lock

    out = tmp_path / "sweep"
    out.mkdir()
    (out / "sweep.json").write_text("the first sweep's record")
    monkeypatch.setattr(sweep_module, "run_job", lambda *a, **k: pytest.fail("the refused sweep trained a cell"))
    with record_lock(out, "sweep.json"):  # another sweep is running on this record
        with pytest.raises(LockedError, match=r"the sweep record .*sweep\.json is in use by pid \d+"):
            sweep_grid(Grid(methods=("bati",), settings=TINY), out, show_progress=False)
        # another record in the same directory (another experiment's) is free
        with record_lock(out, "main.sweep.json"):
            pass
    assert (out / "sweep.json").read_text() == "the first sweep's record"
    assert sorted(p.name for p in out.iterdir()) == ["sweep.json"]  # the lock went with its holder


def test_cli_experiment_on_a_held_record_is_one_line_and_exit_2(tmp_path, capsys):
    from bati.experiments.sweep import record_lock

    out = tmp_path / "out"
    out.mkdir()
    with record_lock(out, "ood-tasks.sweep.json"):
        code = main(["experiment", "ood-tasks", "--out-dir", str(out), "--data-root", str(tmp_path / "data")])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "ood-tasks.sweep.json is in use by pid" in lines[0], lines
    assert list(out.iterdir()) == [] and not (tmp_path / "data").exists()


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("BATI_TEST_RAY"), reason="starts a local Ray cluster (minutes on 2 cores): "
                    "BATI_TEST_RAY=1 python -m pytest tests/test_sweep.py -k ray")
def test_ray_backend_runs_a_tiny_grid_on_a_local_ray(tmp_path):
    ray = pytest.importorskip("ray")
    from bati.data.collect import collect

    root = tmp_path / "data"
    collect("PointGoal", "quick", 0, None, root, n_episodes=2, n_context_episodes=1, progress=False, workers=1)
    grid = Grid(methods=("bati",), seeds=(0, 1), settings=TINY + ("episodes_per_task=2", "context_episodes=1"))
    try:
        result = sweep_grid(grid, tmp_path / "sweep", data_root=root, backend="ray", workers=1, show_progress=False)
    finally:
        ray.shutdown()
    assert result.count("done") == 2, result.errors
    for cell in expand(grid, tmp_path / "sweep", root):
        assert json.loads((cell.config.out_dir / "eval.json").read_text())["steps"] == 10


def test_cli_experiment_report_only_trains_nothing_and_covers_every_cell(tmp_path, monkeypatch, capsys):
    from bati.experiments.pipeline import plan_experiment
    from bati.experiments.specs import get_spec

    monkeypatch.setattr(sweep_module, "run_job", lambda *a, **k: pytest.fail("--report-only trained a cell"))
    out, data = tmp_path / "out", tmp_path / "data"
    args = ["experiment", "ood-tasks", "--methods", "bati", "--report-only", "--out-dir", str(out), "--data-root", str(data)]
    assert main(args) == 0
    report = (out / "ood-tasks" / "report.md").read_text()
    n_cells = len(plan_experiment(get_spec("ood-tasks"), "quick", out).cells)  # every method, not only bati
    # the tables cover every cell of the experiment; the command is what reruns exactly this one's
    assert f"experiment in this folder: 0 of {n_cells}" in report and "--methods bati" in report
    assert "nothing trained" in capsys.readouterr().out and not data.exists()


def test_a_method_setting_goes_only_to_the_methods_that_read_it(tmp_path):
    """`--settings focal.distance=root-mean` on a focal + bati grid changes FOCAL's cells (a new setting
    directory) and leaves BATI's where the default puts them; a setting no method of the grid reads is refused."""
    default = {c.config.method: c for c in expand(Grid(methods=("focal", "bati")), tmp_path)}
    mixed = {c.config.method: c for c in expand(Grid(methods=("focal", "bati"), settings=("focal.distance=root-mean",)),
                                                 tmp_path)}
    assert mixed["focal"].config.focal.distance == "root-mean" and mixed["focal"].id != default["focal"].id
    assert mixed["focal"].config.out_dir.parent != default["focal"].config.out_dir.parent
    assert mixed["bati"].id == default["bati"].id and mixed["bati"].config.out_dir == default["bati"].config.out_dir
    with pytest.raises(SweepError, match=r"focal.distance is read by focal only; none of the grid's methods "
                                         r"\(bati, oracle\) reads it"):
        expand(Grid(methods=("bati", "oracle"), settings=("focal.distance=root-mean",)), tmp_path)


def test_an_int_for_a_float_setting_is_the_same_cell_as_its_float(tmp_path):
    # `ertrl.metric_weight=1` and `=1.0` are one setting: one run directory (the committed quick ER-TRL cells are
    # found by either); an int field stays an int
    one = {c.config.method: c for c in expand(Grid(methods=("er-trl",), settings=("ertrl.metric_weight=1",)), tmp_path)}
    same = {c.config.method: c for c in expand(Grid(methods=("er-trl",), settings=("ertrl.metric_weight=1.0",)),
                                                tmp_path)}
    assert one["er-trl"].id == same["er-trl"].id and one["er-trl"].config.out_dir == same["er-trl"].config.out_dir
    assert one["er-trl"].config.ertrl.metric_weight == 1.0 and isinstance(one["er-trl"].config.ertrl.metric_weight, float)
    steps = expand(Grid(methods=("bati",), settings=("steps=5",)), tmp_path)[0].config.steps
    assert steps == 5 and isinstance(steps, int)


def test_a_collection_of_other_sizes_in_the_data_root_is_one_line_before_the_record_is_touched(tmp_path, capsys):
    from bati.data.collect import collect

    collect("PointGoal", "quick", 0, root=tmp_path / "data", progress=False, n_episodes=2, n_context_episodes=1)
    out = tmp_path / "sweep"
    out.mkdir()
    (out / "sweep.json").write_text("the last sweep's record")
    code = main(["sweep", "--families", "PointGoal", "--methods", "bati", "--settings", "episodes_per_task=3",
                 "--data-root", str(tmp_path / "data"), "--out-dir", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "holds 2 episodes per training task" in err and "another data root" in err
    assert (out / "sweep.json").read_text() == "the last sweep's record"
    assert sorted(p.name for p in out.iterdir()) == ["sweep.json"]


def test_the_live_table_shows_a_running_jobs_steps_and_time_left(tmp_path, monkeypatch):
    """Each job's steps; a running job's logged steps of its total and the time left at its rate so far."""
    cells = expand(Grid(methods=("bati", "recon"), settings=("steps=1000",)), tmp_path)
    status = {c.id: "pending" for c in cells}
    table = sweep_module.LiveTable(cells, status, enabled=False)
    bati_job = next(job for job in make_jobs(cells) if job.config.method == "bati")
    clock = iter([100.0, 160.0, 160.0])  # started at 100 s; 60 s later, a quarter of the steps done
    monkeypatch.setattr(sweep_module.time, "perf_counter", lambda: next(clock))
    table.log(bati_job, "running")
    for cell in bati_job.cells:
        status[cell.id] = "running"
    run = bati_job.cells[0].config.out_dir
    run.mkdir(parents=True)
    (run / "metrics.jsonl").write_text('{"step": 100}\n{"step": 250}\n{"step": 2')  # the last line half written
    assert table.progress(bati_job) == "250 / 1,000, ~3 min left"  # 60 s for 250 steps: 180 s for 750
    rows = {tuple(row) for row in zip(*(column._cells for column in table.render().columns))}
    assert ("PointGoal", "quick", "1", "per-task experts", "recon", "0", "1,000", "pending") in rows
