"""A family defined outside src/ (tests/example_family.py, the one docs/extending.md builds) runs through
collect -> train -> evaluate with every method, with one env file, one record and its registration."""

from __future__ import annotations

import json
import os
import textwrap

import example_family
import gymnasium as gym
import numpy as np
import pytest

from bati.config import TrainConfig
from bati.data.collect import collect
from bati.envs import TaskError, family_names, get_family, register_family
from bati.methods import METHODS
from bati.rl.iql import IQLConfig
from bati.train import train

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("extending")


@pytest.fixture(scope="module")
def line_goal():
    example_family.register()
    return get_family("LineGoal")


def test_a_registered_family_is_known_by_name_and_by_gymnasium(line_goal):
    assert "LineGoal" in family_names()
    assert line_goal.default_noise == 0.5 and line_goal.record.episode_length == 50
    env = gym.make("bati/LineGoal-v0", task=0.5, noise=0.0)
    env.reset(seed=0)
    steps, done = 0, False
    while not done:
        _, reward, terminated, truncated, _ = env.step(np.ones(1, np.float32))
        steps, done = steps + 1, terminated or truncated
    assert steps == 50  # the record's episode length is the env's time limit
    with pytest.raises(TaskError, match="outside the task space"):
        line_goal.validate_task(3.0)


def test_registering_needs_a_record_and_a_new_name(line_goal):
    class NoRecord(example_family.LineGoalFamily.__base__):  # a TaskFamily without a record
        pass

    with pytest.raises(TypeError, match="FamilyRecord"):
        register_family(NoRecord, example_family.LineGoalEnv)
    from bati.envs.point import PointGoalFamily

    with pytest.raises(ValueError, match="already exists"):
        register_family(PointGoalFamily, example_family.LineGoalEnv)
    register_family(example_family.LineGoalFamily, example_family.LineGoalEnv)  # again: a no-op


class WideGoalEnv(example_family.LineGoalEnv):
    """Its observation space says 3 numbers, its observations are 1."""

    def __init__(self, task, noise=None):
        super().__init__(task, noise)
        self.observation_space = gym.spaces.Box(-2.0, 2.0, (3,), np.float64)


def test_a_family_whose_env_breaks_its_observation_space_is_refused_at_registration():
    import dataclasses

    class WideGoal(example_family.LineGoalFamily):
        record = dataclasses.replace(example_family.LineGoalFamily.record, name="WideGoal")

    with pytest.raises(ValueError, match=r"bati/WideGoal-v0: reset\(\) returns observations of shape \(1,\) but its "
                                         r"observation_space has shape \(3,\)"):
        register_family(WideGoal, WideGoalEnv)
    assert "WideGoal" not in family_names() and "bati/WideGoal-v0" not in gym.registry


@pytest.fixture(scope="module")
def line_goal_data(line_goal, tmp_path_factory):
    root = tmp_path_factory.mktemp("line-goal") / "data"
    result = collect("LineGoal", "quick", seed=0, root=root, n_episodes=4, n_context_episodes=2, progress=False)
    manifest = result.manifest
    assert manifest["episode_length"] == 50 and manifest["transitions"] == (20 * 4 + 2 * 20 * 2) * 50
    return root


@pytest.mark.slow
@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_runs_collect_train_evaluate_on_a_family_defined_outside_src(method, line_goal, line_goal_data,
                                                                                  tmp_path):
    config = TrainConfig(family="LineGoal", method=method, steps=10, eval_every=10, log_every=5, task_batch=4,
                         batch_size=8, iql=IQLConfig(hidden_dims=(16, 16)), data_root=line_goal_data,
                         episodes_per_task=4, context_episodes=2, out_dir=tmp_path / "runs" / method)
    summary = train(config, show_progress=False)
    assert np.isfinite(summary["p_test_return"]) and np.isfinite(summary["p_train_return"])
    saved = json.loads((tmp_path / "runs" / method / "config.json").read_text())
    assert saved["family"] == "LineGoal" and saved["context_length"] == 50  # the record's context length
    # Table 3-style settings come from the record: the latent of BATI's table is the record's latent_dim
    assert config.resolved().family == "LineGoal" and line_goal.record.latent_dim == 2


def test_the_transferable_experiments_plan_a_registered_family(line_goal, tmp_path):
    from bati.experiments.pipeline import plan_experiment
    from bati.experiments.specs import ExperimentError, get_spec

    def plan(name):
        return plan_experiment(get_spec(name), "quick", tmp_path, families=("LineGoal",))

    assert {c.config.family for c in plan("main").cells} == {"LineGoal"}
    eps = line_goal.default_noise
    assert sorted({c.config.noise for c in plan("noise").cells}) == [0.0, eps / 2, eps]
    assert sorted({(c.config.n_train_tasks, c.config.n_test_tasks) for c in plan("splits").cells}) == [
        (10, 30), (20, 20), (30, 10)]
    context = plan("context-length")
    c = line_goal.default_context_length
    assert {cell.config.context_length for cell in context.cells} == {c // 4}
    assert {p.eval_context_length for probes in context.probes.values() for p in probes} == {c // 4, c, 2 * c}
    with pytest.raises(ExperimentError, match="a family of your own runs in: main, noise, context-length, splits"):
        plan("ood-tasks")


def test_an_experiment_plans_runs_and_reports_a_family_of_your_own_with_the_papers(line_goal, line_goal_data,
                                                                                   tmp_path):
    from bati.experiments.experiment import ExperimentJob, run_experiment_job

    job = ExperimentJob("main", families=("LineGoal",), methods=("oracle",), out_dir=tmp_path / "results",
                        data_root=line_goal_data, zoo_dir=tmp_path / "zoo",
                        settings=("steps=10", "eval_every=10", "log_every=5", "task_batch=4", "batch_size=8",
                                  "episodes_per_task=4", "context_episodes=2"))
    outcome = run_experiment_job(job, show_progress=False)
    assert not outcome.failures
    report = (outcome.report_dir / "report.md").read_text()
    # planned and counted with the paper's five families (55 cells) plus LineGoal's 11, one of them finished
    assert ("cells finished: 1 of the command's 1; the tables hold every finished cell of the experiment in this "
            "folder: 1 of 66") in report and "LineGoal" in report.split("**p test return")[1].splitlines()[2]
    command = report.split("command: ")[1].splitlines()[0]  # reruns exactly this job's cells
    assert "--methods oracle" in command and "--families LineGoal" in command
    config = json.loads(next((tmp_path / "results" / "LineGoal").rglob("config.json")).read_text())
    assert config["zoo_dir"] == str(tmp_path / "zoo")  # --zoo-dir reaches the cells (not part of their identity)
    assert "--zoo-dir" in job.command_line(whole=True)


METHOD_OF_ONES_OWN = textwrap.dedent('''
    from dataclasses import dataclass

    from bati.methods import METHODS
    from bati.methods.oracle import Oracle


    @dataclass(frozen=True)
    class MineConfig:
        """Mine's settings."""

        weight: float = 1.0
        """How much it weighs."""


    class Mine(Oracle):
        Config = MineConfig
        config_key = "mine"


    METHODS["mine"] = Mine  # before bati.config is imported: TrainConfig then has the section `mine`
''')


def test_a_registered_method_gets_its_section_of_train_config():
    """A method is one file plus one registry entry: its Config becomes TrainConfig's section named by its
    config_key (an option group of `bati train`, recorded in config.json, a dotted setting of sweeps)."""
    import subprocess
    import sys

    check = textwrap.dedent("""
        import contextlib, io, json
        import tyro
        from bati.cli_commands import Train
        from bati.config import TrainConfig, apply_settings, method_sections

        assert method_sections()["mine"] is MineConfig and TrainConfig().mine == MineConfig()
        parsed = tyro.cli(Train, args=["--method", "mine", "--mine.weight", "3"])
        assert parsed.mine == MineConfig(weight=3.0)
        config = apply_settings(TrainConfig(method="mine"), {"mine.weight": 2}).resolved()
        assert config.record()["mine"] == {"weight": 2.0}
        assert TrainConfig.from_record(config.record()).resolved() == config
        assert "mine" not in TrainConfig(method="bati").resolved().record()
        shown = io.StringIO()
        with contextlib.redirect_stdout(shown), contextlib.suppress(SystemExit):
            tyro.cli(Train, args=["--help"])
        print(json.dumps(shown.getvalue()))
    """)
    done = subprocess.run([sys.executable, "-c", METHOD_OF_ONES_OWN + check], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "COLUMNS": "200"}, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    shown = json.loads(done.stdout.strip().splitlines()[-1])
    assert "mine options" in shown and "Mine's settings." in shown and "--mine.weight FLOAT" in shown


def test_main_and_noise_plan_pointgoal_the_default_family_of_bati_run(tmp_path):
    from bati.experiments.pipeline import plan_experiment
    from bati.experiments.specs import get_spec

    for name in ("main", "noise"):
        cells = plan_experiment(get_spec(name), "quick", tmp_path, families=("PointGoal",)).cells
        assert cells and {c.config.family for c in cells} == {"PointGoal"}


def test_the_family_rules_give_the_paper_settings_back_on_the_paper_families():
    from bati.experiments.specs import get_spec

    for name, noises in (("AntDir", (0.0, 0.5, 1.0)), ("HalfCheetahDir", (0.0, 0.4, 0.8))):
        (part,) = get_spec("noise").for_family(get_family(name))
        paper = next(p for p in get_spec("noise").parts if p.families == (name,))
        assert part.noises == paper.noises == noises and part.methods == paper.methods
    (part,) = get_spec("context-length").for_family(get_family("HalfCheetahDir"))
    (paper,) = get_spec("context-length").parts
    assert part.probes == paper.probes and part.settings == paper.settings
    splits = get_spec("splits")
    assert [p.settings for p in splits.for_family(get_family("AntDir"))] == [p.settings for p in splits.parts]


def test_docs_extending_runs_as_written(tmp_path):
    """docs/extending.md's Python blocks, in order, in a fresh interpreter (its own LineGoal registration),
    all but the last (which collects and trains at the quick scale): then the family, its env and its
    expert work as the page says; the last block at least compiles and imports what it names."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    page = (Path(__file__).parents[1] / "docs" / "extending.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    *definitions, last = blocks
    check = textwrap.dedent("""
        import gymnasium, numpy
        from pathlib import Path
        from bati.envs import get_family
        from bati.experts import load
        register()
        family = get_family("LineGoal")
        task = family.sample_tasks(1, seed=0)[0]
        env = gymnasium.make("bati/LineGoal-v0", task=task, noise=0.0)
        obs, _ = env.reset(seed=0)
        action = load("LineGoal")(obs, task)
        assert action.shape == (1,) and env.step(action)[0].shape == (1,)
        from bati.experts.train import ExpertTrainConfig  # `bati experts train --family LineGoal`: the record's budget
        assert ExpertTrainConfig("LineGoal", out_dir=Path("expert")).resolved().total_steps == 20_000
        print("ok")
    """)
    imports = "\n".join(line for line in last.splitlines() if line.startswith("from ") or line.startswith("import "))
    compile(last, "extending.md (last block)", "exec")
    script = "\n\n".join(definitions) + "\n" + imports + "\n" + check
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]


def test_a_family_without_an_expert_budget_is_told_to_give_one(line_goal, monkeypatch):
    from dataclasses import replace

    from bati.experts.train import ExpertTrainConfig

    monkeypatch.setattr(type(line_goal), "record", replace(line_goal.record, expert_steps=None))
    with pytest.raises(ValueError, match=r"LineGoal has no expert budget \(its FamilyRecord.expert_steps is None\): "
                                         "give --total-steps"):
        ExpertTrainConfig("LineGoal").resolved()
    assert ExpertTrainConfig("LineGoal", total_steps=10_000).resolved().total_steps == 10_000
    with pytest.raises(ValueError, match="not a SAC"):
        ExpertTrainConfig("KuhnPoker").resolved()
