"""`bati experiment`: the specs expand to the paper's cells; tiny variants run end to end; bad input."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace
import math
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.cli import main
from bati.envs import TaskError, TaskSplit, get_family
from bati.evaluate import Evaluator, mixed_context_lengths
from bati.experiments.pipeline import plan_experiment, run_experiment
from bati.experiments.report import experiment_report
from bati.experiments.specs import (
    ABLATION_METHODS,
    MAIN_METHODS,
    MUJOCO,
    NOISE_METHODS,
    SPECS,
    ExperimentError,
    get_spec,
)
from bati.report.probes import Probe, ProbeError, read_probe

OUT = Path("/nonexistent-out")  # planning writes nothing: any path will do


def configs(name: str, scale: str = "quick", **kwargs):
    return [c.config for c in plan_experiment(get_spec(name), scale, OUT, **kwargs).cells]


# --- the specs expand to the paper's cells -----------------------------------------------------
def test_main_spec_cells():
    quick, cpu, paper = configs("main"), configs("main", "cpu"), configs("main", "paper")
    assert len(quick) == 5 * 11 and len(cpu) == 5 * 11 * 3 and len(paper) == 5 * 11 * 5
    assert {c.family for c in paper} == set(MUJOCO) and {c.method for c in paper} == set(MAIN_METHODS)
    assert {c.seed for c in paper} == {0, 1, 2, 3, 4} and {c.seed for c in quick} == {0}
    first = paper[0]  # the paper variant down to its first cell: Table 3's settings
    assert (first.scale, first.steps, first.batch_size, first.task_batch, first.iql.hidden_dims) == \
        ("paper", 100_000, 256, 16, (256, 256))
    assert {(c.steps, c.batch_size, c.iql.hidden_dims, c.data_scale) for c in cpu} == {(100_000, 64, (128, 128), "paper")}
    assert {c.seed for c in cpu} == {0, 1, 2}
    assert all(c.noise == get_family(c.family).default_noise for c in quick)


def test_noise_spec_cells():
    cells = configs("noise")
    levels = {(c.family, c.noise) for c in cells}
    assert levels == {("AntDir", 0.0), ("AntDir", 0.5), ("AntDir", 1.0), ("HalfCheetahDir", 0.0),
                      ("HalfCheetahDir", 0.4), ("HalfCheetahDir", 0.8)}
    for family in ("AntDir", "HalfCheetahDir"):  # 0 and the family's default among three levels
        assert {0.0, get_family(family).default_noise} <= {n for f, n in levels if f == family}
    assert len(cells) == 6 * len(NOISE_METHODS) and "er-trl" in NOISE_METHODS


def test_context_length_spec_cells_and_probes():
    plan = plan_experiment(get_spec("context-length"), "quick", OUT)
    assert len(plan.cells) == len(ABLATION_METHODS)
    for cell in plan.cells:
        c = cell.config
        assert (c.family, c.noise, c.context_length) == ("HalfCheetahDir", 0.9, 50)
        assert [p.eval_context_length for p in plan.probes[cell.id]] == [50, 200, 400]


def test_ood_and_splits_spec_cells():
    ood = configs("ood-tasks")
    assert all(c.train_task_range == (0.0, math.pi) and c.test_task_range == (math.pi, 2 * math.pi) for c in ood)
    splits = configs("splits")
    assert sorted({(c.n_train_tasks, c.n_test_tasks) for c in splits}) == [(10, 30), (20, 20), (30, 10)]
    assert all(c.task_batch == min(16, c.n_train_tasks) for c in splits)
    main_antdir = {c.out_dir for c in configs("main") if c.family == "AntDir"}
    assert {c.out_dir for c in splits if c.n_train_tasks == 20} <= main_antdir  # shared cells run once


def test_interpolated_and_noiseless_spec_cells():
    plan = plan_experiment(get_spec("interpolated-contexts"), "quick", OUT)
    assert {c.config.method for c in plan.cells} == {"bati", "bati-r", "recon"}
    assert all([p.context_mix for p in plan.probes[c.id]] == [0.0, 0.25, 0.5, 0.75, 1.0] for c in plan.cells)
    hopper = configs("noiseless-hopper")
    assert {(c.family, c.noise) for c in hopper} == {("HopperParam", 0.0)} and len(hopper) == len(MAIN_METHODS)


def test_kuhn_spec_cells():
    quick, paper = configs("kuhn"), configs("kuhn", "paper")
    assert {c.family for c in paper} == {"KuhnPoker"} and {c.method for c in paper} == set(MAIN_METHODS)
    assert {c.seed for c in quick} == {0, 1, 2} and len(quick) == 3 * len(MAIN_METHODS)
    assert len(paper) == 5 * len(MAIN_METHODS) and all(c.noise == 0.0 for c in paper)
    assert all(c.resolved().context_length == 20 for c in quick)  # 10 hands (App. D.4)


def test_state_term_spec_cells_share_main_cells():
    cells = configs("state-term")
    assert {(c.family, c.method) for c in cells} == {(f, m) for f in ("PointGoal",) + MUJOCO
                                                      for m in ("bati", "bati-r", "bati-auto")}
    main_dirs = {c.out_dir for c in configs("main")}
    assert {c.out_dir for c in cells if c.method != "bati-auto" and c.family != "PointGoal"} <= main_dirs


def test_unknown_tasks_spec_cells_and_probes():
    plan = plan_experiment(get_spec("unknown-tasks"), "quick", OUT)
    ranges = {(c.config.train_task_range, c.config.test_task_range) for c in plan.cells}
    assert ranges == {(None, None), ((0.0, math.pi), (math.pi, 2 * math.pi))}
    assert {c.config.method for c in plan.cells} == {"bati", "bati-r", "bati-auto"}
    assert all([p.name for p in plan.probes[c.id]] == ["novelty"] for c in plan.cells)
    ood = {c.out_dir for c in configs("ood-tasks")}
    assert {c.config.out_dir for c in plan.cells if c.config.train_task_range and c.config.method != "bati-auto"} <= ood


def test_refined_inference_spec_and_probe_settings():
    plan = plan_experiment(get_spec("refined-inference"), "quick", OUT)
    assert {(c.config.family, c.config.method) for c in plan.cells} == {("PointGoal", "bati-auto"),
                                                                          ("HopperParam", "bati-auto")}
    names = [p.name for p in plan.probes[plan.cells[0].id]]
    assert names == ["final", "N10", "N160", "refine10", "refine50"]
    with pytest.raises(ProbeError, match="refine_steps must be an integer >= 0"):
        Probe(refine_steps=-1).check()
    with pytest.raises(ProbeError, match="latent_samples must be an integer >= 1"):
        Probe(latent_samples=0).check()


def test_self_collected_spec_reuses_main_and_state_term_cells():
    plan = plan_experiment(get_spec("self-collected"), "quick", OUT)
    methods = ("bati", "bati-r", "recon", "focal", "unicorn", "csro", "oracle", "no-context")
    assert {(c.config.family, c.config.method) for c in plan.cells} == {(f, m) for f in ("HopperParam", "PointGoal")
                                                                          for m in methods}
    assert all([p.name for p in plan.probes[c.id]] == ["final", "self10x3", "self200x3"] for c in plan.cells)
    trained = {c.out_dir for c in configs("main") + configs("state-term")}
    assert {c.config.out_dir for c in plan.cells if c.config.family == "HopperParam"} <= trained
    assert {c.config.out_dir for c in plan.cells if c.config.method in ("bati", "bati-r")} <= trained


def test_spec_filters_and_seed_override():
    cells = configs("main", methods=("bati", "recon"), families=("AntDir",), seeds=(3, 4))
    assert [(c.method, c.seed) for c in cells] == [("bati", 3), ("bati", 4), ("recon", 3), ("recon", 4)]
    # a chosen subset keeps the order it was chosen in (the sweep's jobs follow the cells)
    cells = configs("main", "paper", methods=("csro", "focal", "bati"), families=("HopperParam", "AntDir"), seeds=(0,))
    assert [(c.family, c.method) for c in cells] == [(f, m) for f in ("HopperParam", "AntDir")
                                                     for m in ("csro", "focal", "bati")]


# --- bad input: one line, exit 2, nothing written ------------------------------------------------
@pytest.mark.parametrize("args, message", [
    (["experiment", "tabel4"], "unknown experiment 'tabel4'"),
    (["experiment", "splits", "--settings", "n_train_tasks=15"], "sets n_train_tasks itself"),
    (["experiment", "main", "--methods", "bati", "bogus"], "has no method 'bogus'"),
    (["experiment", "ood-tasks", "--families", "HopperParam"], "has no family 'HopperParam'"),
    (["experiment", "main", "--settings", "steps=0"], "steps must be an integer >= 1"),
    (["experiment", "main", "--seeds", "-1"], "seeds must be distinct integers >= 0"),
    (["experiment", "main", "--seeds", "1", "1"], "seeds must be distinct integers >= 0"),
])
def test_experiment_bad_input(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    code = main(args + ["--out-dir", str(out), "--data-root", str(tmp_path / "data")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not out.exists() and not (tmp_path / "data").exists()


def test_scale_a_spec_lacks():
    spec = dataclasses.replace(get_spec("main"), scales=("quick",))
    with pytest.raises(ExperimentError, match="has no 'paper' scale"):
        plan_experiment(spec, "paper", OUT)


@pytest.mark.parametrize("split, message", [
    (TaskSplit(train_range=(1.0, 1.0)), "non-empty sub-range"),
    (TaskSplit(train_range=(0.0, 7.0)), "non-empty sub-range"),
    (TaskSplit(n_train=1), "at least 2 training tasks"),
    (TaskSplit(n_test=0), "n_test must be an integer >= 1"),
])
def test_bad_task_splits(split, message):
    with pytest.raises(TaskError, match=message):
        split.checked(get_family("AntDir"))


def test_task_range_on_a_family_without_one(tmp_path, capsys):
    code = main(["data", "collect", "--family", "HalfCheetahDir", "--train-range", "0", "1", "--root", str(tmp_path)])
    assert code == 2 and "cannot be drawn from a range" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_experiment_list(capsys):
    assert main(["experiment", "list"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in SPECS)


# --- task splits and interpolated contexts -------------------------------------------------------
def test_task_split_draws():
    family = get_family("AntDir")
    default = TaskSplit().draw(family, 3)
    assert default == family.split_tasks(3)  # existing collections keep their tasks
    train, test = TaskSplit(train_range=(0.0, math.pi), test_range=(math.pi, 2 * math.pi)).draw(family, 3)
    assert len(train) == len(test) == 20
    assert all(0 <= t < math.pi for t in train) and all(math.pi <= t < 2 * math.pi for t in test)
    ten, thirty = TaskSplit(10, 30).draw(family, 3)
    assert len(ten) == 10 and len(thirty) == 30
    assert sorted(ten + thirty) == sorted(family.split_tasks(3, 20, 20)[0] + family.split_tasks(3, 20, 20)[1])
    assert TaskSplit(10, 30).label() == "-tasks10x30" and TaskSplit().label() == ""


def test_collected_data_honours_the_task_split(tmp_path):
    from bati.data.batch import ensure_family_data

    split = TaskSplit(n_train=3, n_test=2, train_range=(0.0, 1.0), test_range=(2.0, 3.0))
    data = ensure_family_data("PointGoal", root=tmp_path, n_episodes=2, n_context_episodes=1, progress=False,
                              workers=1, tasks=split)
    angle = lambda tasks: np.arctan2(np.asarray(tasks)[:, 1], np.asarray(tasks)[:, 0])  # noqa: E731
    assert data.train.n_tasks == 3 and data.p_test.n_tasks == data.p_train.n_tasks == 2
    assert np.all((angle(data.train_tasks) >= 0) & (angle(data.train_tasks) < 1))
    assert np.all((angle(data.test_tasks) >= 2) & (angle(data.test_tasks) < 3))
    assert data.path.name == "quick-seed0-eps1-tasks3x2-train0to1-test2to3"
    assert data.manifest["task_split"] == split.record() | {"train_range": [0.0, 1.0], "test_range": [2.0, 3.0]}
    assert "--n-train 3 --n-test 2 --train-range 0 1 --test-range 2 3" in data.manifest["command"]


@pytest.mark.parametrize("length, mix, expected", [(200, 0.25, (150, 50)), (50, 0.5, (25, 25)), (10, 1.0, (0, 10)),
                                                   (10, 0.0, (10, 0)), (7, 0.5, (3, 4))])
def test_mixed_context_lengths(length, mix, expected):
    assert mixed_context_lengths(length, mix) == expected


STUB_METHOD = SimpleNamespace(acts_itself=False)  # only the context sampler is exercised
STUB_IQL = SimpleNamespace(act=lambda params, obs, z: obs)


def test_interpolated_context_has_n_r_p_test_transitions(synthetic_data):
    data = synthetic_data("PointGoal")
    # mark the two sources apart: p_test rewards +1000, p_train rewards -1000
    data = dataclasses.replace(data, p_test=data.p_test.replace(rewards=jnp.full_like(data.p_test.rewards, 1000.0)),
                               p_train=data.p_train.replace(rewards=jnp.full_like(data.p_train.rewards, -1000.0)))
    for mix in (0.0, 0.25, 0.5, 1.0):
        evaluator = Evaluator(STUB_METHOD, STUB_IQL, data, context_length=20, context_mix=mix, family=get_family(data.family))
        ctx = evaluator.contexts("mixed", jax.random.PRNGKey(0))
        rewards = np.asarray(ctx["rewards"])
        assert rewards.shape == (data.p_test.n_tasks, 20)
        assert np.all((rewards == 1000).sum(1) == round(20 * mix)) and np.all((rewards == -1000).sum(1) == 20 - round(20 * mix))
    with pytest.raises(ValueError, match="context_mix must be in"):
        Evaluator(STUB_METHOD, STUB_IQL, data, context_length=20, context_mix=1.5, family=get_family(data.family))


def test_probe_refuses_a_missing_run(tmp_path):
    with pytest.raises(ProbeError, match="no readable run config"):
        from bati.experiments.probes import run_probe

        run_probe(tmp_path, Probe(eval_context_length=50))
    with pytest.raises(ProbeError, match="context_mix"):
        Probe(context_mix=2.0).check()


# --- report figures ----------------------------------------------------------------------------
def test_vs_figure_puts_each_column_at_its_number_and_orders_columns_numerically(tmp_path, monkeypatch):
    from bati.experiments import report as report_module

    spec = get_spec("noise")
    records = [{"family": family, "method": "bati", "seed": 0, "family_noise": f"{family} eps={eps:g}",
                spec.metric: float(10 * eps)}
               for family, noises in (("AntDir", (1.0, 0.25, 0.0, 0.5)), ("HalfCheetahDir", (0.8, 0.0, 0.4)))
               for eps in noises]
    figures = []
    monkeypatch.setattr(report_module, "save_figure", lambda fig, path, dpi: figures.append(fig))
    assert report_module.plot_vs(spec, records, spec.metric, tmp_path / "vs.png")
    (antdir, cheetah) = figures[0].axes[:2]
    assert list(antdir.lines[0].get_xdata()) == [0.0, 0.25, 0.5, 1.0]  # eps, not a 0 for every text column
    assert list(antdir.lines[0].get_ydata()) == [0.0, 2.5, 5.0, 10.0]
    assert list(cheetah.lines[0].get_xdata()) == [0.0, 0.4, 0.8]
    position = report_module.column_position
    assert (position("10/30"), position("200"), position("AntDir eps=0.5"), position("final")) == (10, 200, 0.5, None)


def test_returns_by_task_value_average_the_test_tasks_of_each_value():
    from bati.experiments.report import by_task_value_section, returns_by_task_value

    cheetah = plan_experiment(get_spec("experts"), "cpu", OUT, families=["HalfCheetahDir"], methods=["focal"],
                              seeds=[0]).cells[0]
    test_tasks = np.array(cheetah.config.task_split().draw(get_family("HalfCheetahDir"), cheetah.config.data_seed)[1])
    returns = np.where(test_tasks > 0, 10.0, -4.0)
    returns[np.flatnonzero(test_tasks > 0)[0]] = 30.0  # one right-running task differs: the mean moves
    right = np.flatnonzero(test_tasks > 0)
    raw = {"p_train_task_returns": returns.tolist(), "p_test_task_returns": (-returns).tolist()}
    values = returns_by_task_value(cheetah, raw)
    expected_right = (30.0 + 10.0 * (len(right) - 1)) / len(right)
    assert values == pytest.approx({"by_task_p_train_-1": -4.0, "by_task_p_train_1": expected_right,
                                    "by_task_p_test_-1": 4.0, "by_task_p_test_1": -expected_right})
    assert returns_by_task_value(cheetah, {"p_train_task_returns": [1.0, 2.0]}) == {}  # not one per test task
    ant = plan_experiment(get_spec("experts"), "cpu", OUT, families=["AntDir"], methods=["focal"], seeds=[0]).cells[0]
    assert returns_by_task_value(ant, {"p_train_task_returns": [1.0] * 20}) == {}  # directions: a continuum

    spec = get_spec("experts")
    records = [{"method": "focal", "seed": seed, "family_experts": "HalfCheetahDir per-task",
                **{k: v + seed for k, v in values.items()}} for seed in (0, 1)]
    section, csv_rows = by_task_value_section(spec, records)
    row = next(line for line in section.splitlines() if line.startswith("| HalfCheetahDir per-task | focal"))
    assert row.split(" | ")[2:4] == ["0 1", "-3.50 ± 0.50"]  # seeds, then p_train on task -1 first
    assert {r["metric"] for r in csv_rows} == set(values)
    assert by_task_value_section(spec, [{"method": "focal", "seed": 0}]) == ("", [])


def test_a_bati_runs_likelihood_split_is_saved_before_the_next_job_starts(tmp_path, monkeypatch):
    """The split needs the run's checkpoint, which a GPU machine that may be taken away keeps only while it lives: it
    is written as each job ends, not after the whole sweep (at the paper scale no BATI run had one: every machine
    went away first).
    No training here: the jobs write their eval.json, the split records its call."""
    from bati.experiments import pipeline as pipeline_module
    from bati.experiments import sweep as sweep_module

    events = []
    plan = plan_experiment(get_spec("main"), "quick", tmp_path, families=("AntDir",),
                           methods=("bati", "bati-r", "focal"), seeds=(0,))
    records = {c.config.out_dir: c.config.record() for c in plan.cells if not c.host}

    def fake_job(config, seeds, runs_dir, references=None, rules=()):
        events.append(f"train {config.method}")
        for seed in seeds:
            run = runs_dir / f"{config.method}-seed{seed}"
            run.mkdir(parents=True, exist_ok=True)
            (run / "eval.json").write_text(json.dumps({"config": records[run], "rules": {r: {} for r in rules}}))
        return [{}]

    monkeypatch.setattr(sweep_module, "run_job", fake_job)
    monkeypatch.setattr(sweep_module, "prepare_data", lambda cells, progress, check_only=False: None)
    monkeypatch.setattr(sweep_module, "check_experts", lambda cells: None)
    monkeypatch.setattr(pipeline_module, "likelihood_split_due",  # due until saved, as the real one (a file)
                        lambda run, step, length: f"split {Path(run).name}" not in events)
    monkeypatch.setattr(pipeline_module, "save_likelihood_split",
                        lambda run, length: events.append(f"split {Path(run).name}"))
    result = run_experiment(plan, tmp_path, show_progress=False)
    assert result.sweep.count("done") == 3 and not result.probe_errors
    # bati-r trained with bati: bati's run holds the model, so one split, before FOCAL's job
    assert events == ["train bati", "split bati-seed0", "train focal"]


# --- tiny variants end to end (PointGoal stands in for the MuJoCo families) ---------------------
TINY = ("steps=10", "eval_every=10", "log_every=10", "batch_size=8", "iql.hidden_dims=[32,32]", "task_batch=2",
        "episodes_per_task=2", "context_episodes=2")


def shrink_task_count(setting: str) -> str:
    key, _, value = setting.partition("=")
    return f"{key}={int(value) // 5}" if key in ("n_train_tasks", "n_test_tasks") else setting


def tiny_spec(name: str):
    spec = get_spec(name)
    parts = []
    # noise's two parts differ only in their family, which PointGoal replaces here: one part tests them; experts'
    # second part differs in who collects (per-task experts: tests/test_per_task_experts.py collects with them)
    for part in spec.parts[:1] if name in ("noise", "experts") else spec.parts:
        settings = tuple(s for s in part.settings if not s.startswith(("train_task_range", "test_task_range")))
        if len(settings) != len(part.settings):  # PointGoal's parameter is an angle in [0, pi]
            settings += ("train_task_range=[0.0, 1.5]", "test_task_range=[1.5, 3.1]")
        # 4 + 4 tasks test the same code as 20 + 20; BATI's Eq. 8 scores every test context under every
        # training task's latent: at 20 + 20 a third of a tiny run's time (self-collected: 24 of 72 s). The
        # splits' 10 + 30, 20 + 20 and 30 + 10 shrink to 2 + 6, 4 + 4 and 6 + 2 (three collections of 8 tasks)
        if name != "kuhn" and not any(s.startswith("n_train_tasks") for s in settings):
            settings += ("n_train_tasks=4", "n_test_tasks=4")
        elif name != "kuhn":
            settings = tuple(shrink_task_count(s) for s in settings)
        methods = {"interpolated-contexts": ("bati", "recon"), "state-term": ("bati-auto",),
                   "unknown-tasks": ("bati-auto",), "refined-inference": ("bati-auto",)}.get(name, ("bati",))
        # five mixes or refinements test no more code than three: every other one (the first and last kept)
        kept = part.probes[::2] if len(part.probes) > 3 else part.probes
        probes = tuple(dataclasses.replace(p, repeats=2) if p.self_collect_every is None else
                       dataclasses.replace(p, repeats=2, self_collect_episodes=2) for p in kept)
        families = part.families if name == "kuhn" else ("PointGoal",)  # KuhnPoker is cheap: itself
        parts.append(dataclasses.replace(part, families=families, methods=methods, settings=settings,
                                         probes=probes))
    return dataclasses.replace(spec, parts=tuple(parts))


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SPECS))
def test_tiny_experiment_end_to_end(tmp_path, name):
    spec = tiny_spec(name)
    out, data_root = tmp_path / "out", tmp_path / "data"
    plan = plan_experiment(spec, "quick", out, settings=TINY, data_root=data_root)
    result = run_experiment(plan, out, data_root=data_root, show_progress=False)
    assert result.sweep.count("failed") == 0 and not result.probe_errors
    assert json.loads((out / f"{name}.sweep.json").read_text())["cells"]
    for cell in plan.cells:
        assert (cell.config.out_dir / "eval.json").exists()
        for probe in plan.probes.get(cell.id, ()):
            saved = read_probe(cell.config.out_dir, probe)
            assert saved is not None
            if probe.novelty:
                assert 0.0 <= saved["p_train_auroc"] <= 1.0 and saved["repeats"] == 2
            else:
                source = ("self" if probe.self_collect_every is not None else
                          "mixed" if probe.context_mix is not None else "p_test")
                assert len(saved[f"{source}_returns"]) == 2
    for cell in plan.cells:  # main and noise keep the likelihood split of each BATI run (tiny_spec: bati only)
        assert (cell.config.out_dir / "likelihood.json").exists() == spec.likelihood_split
    stale = out / name / "curves-AntDir-quick-eps1-12000steps.png"  # an earlier report's figure of another family
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_bytes(b"png")
    report = experiment_report(plan, out / name, command=f"bati experiment {name}")
    assert all(path.exists() for path in report["files"])
    assert not stale.exists()
    assert sorted(p.name for p in (out / name).iterdir()) == sorted(p.name for p in report["files"])
    assert report["cells_done"] == len(plan.cells)
    markdown = report["markdown"]
    assert f"Experiment `{name}`" in markdown and f"| {get_spec(name).rows} |" in markdown
    if name == "unknown-tasks":  # AUROC tables, one column per task range
        assert "**p train auroc**" in markdown and "train [0, 1.5), test [1.5, 3.1)" in markdown
    if name == "self-collected":  # self-collected returns per probe, the given-context ones beside them
        assert "**self return**" in markdown and "PointGoal self10x2" in markdown and "PointGoal final" in markdown
    assert ("**Which term of Eq. 8 picks the task**" in markdown) == spec.likelihood_split
    if name == "state-term":  # BATI-auto's calibrated weight is reported beside its returns
        assert "**state weight**" in markdown and "p test inference error" in markdown
    if spec.paper:
        # PointGoal's columns are not the paper's, so the paper's rows are listed below the table
        assert "Paper rows without a run here" in markdown or "/ " in markdown
    # a rerun finds everything done: nothing is trained or probed again
    splits = {p: p.stat().st_mtime_ns for p in out.rglob("likelihood.json")}
    again = run_experiment(plan, out, data_root=data_root, show_progress=False)
    assert again.sweep.count("skipped") == len(plan.cells)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("likelihood.json")} == splits


def test_a_probe_saved_before_a_new_probe_setting_is_read_back(tmp_path):
    from dataclasses import asdict

    from bati.report.probes import probe_path

    probe = Probe(eval_context_length=50)
    old = {k: v for k, v in asdict(probe).items() if k != "novelty"}  # saved before `novelty` existed
    probe_path(tmp_path, probe).parent.mkdir()
    probe_path(tmp_path, probe).write_text(json.dumps({"probe": old, "step": 10}))
    assert read_probe(tmp_path, probe) == {"probe": old, "step": 10}
    assert read_probe(tmp_path, Probe(eval_context_length=200)) is None


def test_an_experiment_writes_under_runs_never_into_the_committed_results_unless_asked(tmp_path, monkeypatch):
    from bati.experiments.experiment import ExperimentJob, run_experiment_job

    monkeypatch.chdir(tmp_path)
    (tmp_path / "results" / "quick" / "experiments").mkdir(parents=True)  # a checkout's committed studies
    outcome = run_experiment_job(ExperimentJob("main", families=("PointGoal",), methods=("bati",), report_only=True),
                                 show_progress=False)
    assert outcome.report_dir == Path("runs/experiments/quick/main") and (tmp_path / outcome.report_dir).is_dir()
    assert not any((tmp_path / "results").rglob("*.*"))


def test_the_experiment_list_keeps_its_counts_on_an_80_column_terminal():
    from rich.console import Console

    from bati.experiments.experiment import experiment_list, show_experiment_list

    console = Console(width=80, record=True, color_system=None)
    show_experiment_list(console=console)
    text = console.export_text()
    assert "…" not in text and all(len(line) <= 80 for line in text.splitlines() if line.startswith(("┃", "│")))
    main_row = next(line for line in text.splitlines() if line.startswith("│ main "))
    cells = next(r["cells"] for r in experiment_list() if r["name"] == "main")
    assert [int(x) for x in main_row.split("│")[3:6]] == [cells["quick"], cells["cpu"], cells["paper"]]


def test_bati_runs_closing_table_fits_80_columns_and_says_its_seeds_and_units():
    from rich.console import Console
    from rich.markdown import Markdown

    from bati.experiments.main_job import compact_table

    def row(method, n, train, test, error):
        return {"method": method, "n_seeds": n, "seeds": list(range(n)), "p_train_normalised_mean": train,
                "p_train_normalised_std": 0.0 if n == 1 else 0.1, "p_test_normalised_mean": test,
                "p_test_normalised_std": 0.0 if n == 1 else 0.2, "p_test_inference_error_mean": error}

    text = compact_table([row("bati", 1, 0.47, 0.63, 0.65), row("recon", 3, 0.51, -0.17, float("nan"))])
    console = Console(width=80, record=True, color_system=None)
    console.print(Markdown(text))
    shown = console.export_text()
    assert "nan" not in shown and "…" not in shown and "distance)" in shown
    assert all(len(line) <= 80 for line in shown.splitlines())
    assert "| bati | 1 seed (0) | 0.47 | 0.63 | 0.65 |" in text
    assert "| recon | 3 seeds (0 1 2) | 0.51 ± 0.10 | -0.17 ± 0.20 | – |" in text


def test_an_experiment_refuses_to_replace_the_report_of_other_settings(tmp_path):
    """The committed conditioned tables sit where the default (per-task) run would write its report: refused, one
    line before any work; the same settings (in any order) rewrite it."""
    from bati.experiments.experiment import ExperimentJob, run_experiment_job
    from bati.experiments.specs import ExperimentError

    report = tmp_path / "main" / "report.md"
    report.parent.mkdir()
    report.write_text("# Experiment `main`\n\n- command: `bati experiment main --scale quick --settings "
                      "experts=conditioned steps=12000 --out-dir X`\n")
    job = dict(families=("PointGoal",), methods=("bati",), report_only=True, out_dir=tmp_path)
    with pytest.raises(ExperimentError, match="with the settings experts=conditioned steps=12000 .* would replace it"):
        run_experiment_job(ExperimentJob("main", **job), show_progress=False)
    assert report.read_text().startswith("# Experiment `main`\n\n- command")  # untouched
    run_experiment_job(ExperimentJob("main", settings=("steps=12000", "experts=conditioned"), **job),
                       show_progress=False)
    assert "experts=conditioned" in report.read_text()


@pytest.mark.parametrize("name, methods, families", [
    ("main", ("focal", "bati"), ("HalfCheetahDir", "AntDir")),  # the order chosen, not the spec's
    ("main", ("csro",), ()),
    ("noise", (), ("HalfCheetahDir",)),
    ("experts", ("bati-r", "oracle"), ("AntDir",)),
    ("context-length", ("bati",), ()),
    ("main", (), ("PointGoal",)),  # a family of one's own: the spec's parts for it
])
def test_a_selection_of_the_whole_plan_is_the_plan_made_with_it(name, methods, families):
    """`bati experiment` plans once: the cells it runs are a selection of the whole plan its report covers, the
    same cells, grids and probes in the same order as planning with the selection."""
    from bati.experiments.experiment import ExperimentJob, job_plans

    spec = get_spec(name)
    planned = plan_experiment(spec, "quick", OUT, methods=methods, families=families)
    selected, whole = job_plans(ExperimentJob(name, methods=methods, families=families), OUT)
    assert [c.id for c in selected.cells] == [c.id for c in planned.cells]
    assert selected.grids == planned.grids and selected.probes == planned.probes
    assert {c.id for c in selected.cells} <= {c.id for c in whole.cells}
    # a test-time rule selected without its host keeps the whole plan's place for it: the host's run evaluates it
    hosts = {c.id: (c.config.out_dir, c.host) for c in whole.cells}
    assert [replace(c, run_dir=hosts[c.id][0], host=hosts[c.id][1]) for c in planned.stored().cells] == \
        list(selected.stored().cells)
    if name == "experts":  # bati-r selected without bati: in bati's run, as the whole plan has it
        assert {c.host for c in selected.cells if c.config.method == "bati-r"} == {"bati"}


def test_a_selection_the_experiment_lacks_is_one_line():
    from bati.experiments.experiment import ExperimentJob, job_plans

    with pytest.raises(ExperimentError, match="experiment 'noise' has no method 'dpt'"):
        job_plans(ExperimentJob("noise", methods=("dpt",)), OUT)
    with pytest.raises(ExperimentError, match="experiment 'kuhn' has no family 'AntDir'"):
        job_plans(ExperimentJob("kuhn", families=("AntDir",)), OUT)
