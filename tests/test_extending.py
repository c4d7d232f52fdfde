"""A family defined outside src/ (tests/example_family.py, the one docs/extending.md builds) runs through
collect -> train -> evaluate with every method, with one env file, one record and its registration."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

from bati.config import TrainConfig
from bati.data.collect import collect
from bati.envs import TaskError, family_names, get_family, register_family
from bati.methods import METHODS
from bati.rl.iql import IQLConfig
from bati.train import train
import example_family


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


@pytest.mark.slow
def test_every_method_runs_collect_train_evaluate_on_a_family_defined_outside_src(line_goal, tmp_path):
    result = collect("LineGoal", "quick", seed=0, root=tmp_path / "data", n_episodes=4, n_context_episodes=2,
                     progress=False)
    manifest = result.manifest
    assert manifest["episode_length"] == 50 and manifest["transitions"] == (20 * 4 + 2 * 20 * 2) * 50
    for method in sorted(METHODS):
        config = TrainConfig(family="LineGoal", method=method, steps=10, eval_every=10, log_every=5, task_batch=4,
                             batch_size=8, iql=IQLConfig(hidden_dims=(16, 16)), data_root=tmp_path / "data",
                             episodes_per_task=4, context_episodes=2, out_dir=tmp_path / "runs" / method)
        summary = train(config, show_progress=False)
        assert np.isfinite(summary["p_test_return"]) and np.isfinite(summary["p_train_return"])
        saved = json.loads((tmp_path / "runs" / method / "config.json").read_text())
        assert saved["family"] == "LineGoal" and saved["context_length"] == 50  # the record's context length
    # Table 3-style settings come from the record: the latent of BATI's table is the record's latent_dim
    assert config.resolved().family == "LineGoal" and line_goal.record.latent_dim == 2
