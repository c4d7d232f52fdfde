"""Experts: SAC training smoke test on PointGoal, exact resume, the policy interface, cards."""

from __future__ import annotations

import re

import jax
import numpy as np
import pytest

from bati.envs import TaskError
from bati.experts import load
from bati.experts.card import write_card
from bati.experts.train import ExpertTrainConfig, train_expert

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("experts")

SMALL = dict(num_envs=2, start_steps=200, eval_every=400, checkpoint_every=400, eval_tasks=2)


def _train(tmp_path, name, total_steps):
    config = ExpertTrainConfig("PointGoal", total_steps=total_steps, out_dir=tmp_path / name,
                               export_dir=tmp_path / f"zoo-{name}", **SMALL)
    return train_expert(config, show_progress=False)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("experts")
    _train(tmp_path, "straight", 800)
    _train(tmp_path, "resumed", 400)  # interrupted after the first checkpoint ...
    _train(tmp_path, "resumed", 800)  # ... and resumed
    return tmp_path


def test_training_writes_checkpoints_metrics_and_an_exported_expert(trained):
    run = trained / "straight"
    assert (run / "checkpoint.npz").exists() and (run / "config.json").exists()
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 2
    expert = load("PointGoal", trained / "zoo-straight", "conditioned")
    assert expert.meta["train_steps"] == 800


def test_resumed_training_gives_the_same_expert_as_an_uninterrupted_run(trained):
    a = load("PointGoal", trained / "zoo-straight", "conditioned").actor_params
    b = load("PointGoal", trained / "zoo-resumed", "conditioned").actor_params
    jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)


def test_policy_interface_single_batched_deterministic_and_stochastic(trained):
    expert = load("PointGoal", trained / "zoo-straight", "conditioned")
    single = expert(np.zeros(2), [0.6, 0.8])
    assert single.shape == (2,) and np.all(np.abs(single) <= 1)
    batch = expert(np.zeros((3, 2)), [[1.0, 0.0], [0.6, 0.8], [-1.0, 0.0]])
    assert batch.shape == (3, 2)
    np.testing.assert_allclose(batch[1], single, rtol=1e-5)
    broadcast = expert(np.zeros((3, 2)), [0.6, 0.8])
    np.testing.assert_allclose(broadcast, np.repeat(single[None], 3, 0), rtol=1e-5)
    s1 = expert(np.zeros((3, 2)), [0.6, 0.8], deterministic=False, key=jax.random.PRNGKey(0))
    s2 = expert(np.zeros((3, 2)), [0.6, 0.8], deterministic=False, key=jax.random.PRNGKey(1))
    assert not np.allclose(s1, s2)
    with pytest.raises(ValueError, match="needs a PRNG key"):
        expert(np.zeros(2), [0.6, 0.8], deterministic=False)
    with pytest.raises(TaskError):
        expert(np.zeros(2), [0.0, -1.0])


def test_card_reports_returns_on_train_and_test_tasks_and_the_gap(trained):
    card = write_card("PointGoal", seed=0, zoo_dir=trained / "zoo-straight", experts="conditioned")
    assert len(card["train_returns"]) == 20 and len(card["test_returns"]) == 20
    assert card["task_specificity_gap"] == pytest.approx(
        card["oracle_test_return"] - card["most_different_expert_test_return"])
    assert (trained / "zoo-straight" / "PointGoal" / "card.md").read_text().startswith("# Expert card: PointGoal")


def test_missing_expert_and_mismatched_run_directory_are_clear_errors(tmp_path, trained):
    with pytest.raises(FileNotFoundError, match="bati experts train --family PointGoal") as err:
        load("PointGoal", tmp_path, "conditioned")
    assert "--zoo-dir runs/experts/PointGoal/zoo" in str(err.value)  # where training exports it, how to use it
    config = ExpertTrainConfig("PointGoal", total_steps=400, out_dir=trained / "straight", seed=3,
                               export_dir=tmp_path, **SMALL)
    with pytest.raises(ValueError, match="seed: 0 there, 3 now"):
        train_expert(config, show_progress=False)
    from bati.experts.sac import SACConfig

    other_nets = ExpertTrainConfig("PointGoal", total_steps=1200, out_dir=trained / "straight", export_dir=tmp_path,
                                   sac=SACConfig(hidden_dims=(8,)), **SMALL)
    with pytest.raises(ValueError, match="another config .*sac: "):  # it resumed the old nets as new sizes
        train_expert(other_nets, show_progress=False)
    assert not (tmp_path / "PointGoal").exists()


def test_shipped_experts_load():
    for kind in ("conditioned", "per-task"):
        expert = load("PointGoal", kind=kind)
        assert expert(np.zeros(2), [1.0, 0.0]).shape == (2,)


def test_an_expert_checkpoint_saved_before_train_states_loads_into_them():
    import flax

    from bati.experts.sac import SAC, SACConfig, state_from_bytes

    sac = SAC(2, 2, 2, SACConfig(hidden_dims=(8,)))
    state = sac.init(jax.random.PRNGKey(0))
    new = flax.serialization.to_state_dict(state)
    scalar_adam = {k: {**v, "mu": v["mu"]["log_alpha"], "nu": v["nu"]["log_alpha"]} if "mu" in v else v
                   for k, v in new["alpha"]["opt_state"].items()}
    old = {"actor": new["actor"]["params"], "critic": new["critic"]["params"],  # SACState before TrainStates
           "target_critic": new["critic"]["target_params"], "log_alpha": new["alpha"]["params"]["log_alpha"],
           "actor_opt": new["actor"]["opt_state"], "critic_opt": new["critic"]["opt_state"], "alpha_opt": scalar_adam}
    restored = state_from_bytes(sac.init(jax.random.PRNGKey(1)), flax.serialization.msgpack_serialize(old))
    jax.tree_util.tree_map(np.testing.assert_array_equal, restored, state)


def test_an_expert_is_exported_into_its_run_directory_unless_the_package_is_asked_for(tmp_path):
    from bati.experts.zoo import ZOO_DIR

    config = ExpertTrainConfig("PointGoal", out_dir=tmp_path / "run").resolved()
    assert config.export_dir == tmp_path / "run" / "zoo" and config.total_steps == 20_000  # the record's
    assert ExpertTrainConfig("PointGoal", export_dir=tmp_path / "z").resolved().export_dir == tmp_path / "z"
    assert ExpertTrainConfig("PointGoal", into_package=True).resolved().export_dir == ZOO_DIR


@pytest.mark.parametrize("settings, message", [
    ({"total_steps": 0}, "total_steps must be an integer >= 1, got 0 (leave it out for the family's 20,000)"),
    ({"total_steps": -5}, "total_steps must be an integer >= 1"),
    ({"num_envs": 0}, "num_envs must be an integer >= 1"),
    ({"eval_every": 0}, "eval_every must be an integer >= 1"),
    ({"into_package": True, "export_dir": "zoo"}, "either --export-dir or --into-package"),
    ({"total_steps": 10**20}, "total_steps must be at most 1,000,000,000"),
    ({"seed": -1}, "seed must be an integer >= 0, got -1"),
    ({"total_steps": 4000}, "total_steps (4,000) must exceed start_steps (5,000)"),
    ({"per_task": True, "tasks": (0, 0)}, "give distinct training-task indices in 0..19"),
    ({"updates_per_step": float("nan")}, "updates_per_step must be a finite number >= 0"),
    ({"sac.batch_size": 0}, "sac.batch_size must be an integer >= 1, got 0"),
    ({"sac.hidden_dims": (0,)}, "sac.hidden_dims must be one or more integers >= 1 (the hidden layers' sizes), got (0,)"),
    ({"sac.hidden_dims": ()}, "sac.hidden_dims must be one or more integers >= 1"),
    ({"sac.discount": 2.0}, "sac.discount must be a finite number > 0 and at most 1"),
])
def test_bad_expert_settings_are_refused_before_any_work(tmp_path, settings, message, capsys):
    from bati.cli import main

    from bati.experts.sac import SACConfig

    plain = {k: v for k, v in settings.items() if "." not in k}
    sac = SACConfig(**{k.split(".")[1]: v for k, v in settings.items() if "." in k})
    with pytest.raises(ValueError, match=re.escape(message)):
        ExpertTrainConfig("PointGoal", out_dir=tmp_path / "run", sac=sac, **plain).resolved()
    args = ["experts", "train", "--family", "PointGoal", "--out-dir", str(tmp_path / "run")]
    for key, value in settings.items():
        values = [] if value is True else list(map(str, value)) if isinstance(value, tuple) else [str(value)]
        args += [f"--{key.replace('_', '-')}", *values]
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "run").exists()


def test_experts_train_leaves_the_package_zoo_as_it_was_unless_asked(trained, tmp_path, capsys):
    """A run (a few more steps of the tiny one) exports into its own directory's zoo/; the shipped experts
    are byte for byte what they were (it once trained 20,000 steps into the package for --total-steps 0)."""
    import shutil

    from bati.cli import main
    from bati.experts.zoo import ZOO_DIR

    shipped = {p: p.read_bytes() for p in sorted(ZOO_DIR.rglob("*")) if p.is_file()}
    run = tmp_path / "run"
    shutil.copytree(trained / "straight", run)
    options = [f"--{k.replace('_', '-')}={v}" for k, v in SMALL.items()]
    assert main(["experts", "train", "--family", "PointGoal", "--total-steps", "1200", "--out-dir", str(run),
                 *options]) == 0
    assert f"exported to {run / 'zoo'}" in " ".join(capsys.readouterr().out.split())
    assert load("PointGoal", run / "zoo", "conditioned").meta["train_steps"] == 1200
    assert {p: p.read_bytes() for p in sorted(ZOO_DIR.rglob("*")) if p.is_file()} == shipped


def test_a_budget_is_collected_in_whole_episodes_and_said_so(tmp_path, capsys):
    from bati.experts.train import ExpertTrainConfig

    # PointGoal's episodes are 200 steps: per task 1,050 -> 6 episodes; 4 lockstep envs -> 2 rounds of 800
    assert ExpertTrainConfig("PointGoal", per_task=True, total_steps=1050, start_steps=100).resolve().collected_steps == 1200
    assert ExpertTrainConfig("PointGoal", total_steps=1050, start_steps=100).resolve().collected_steps == 1600
    assert ExpertTrainConfig("PointGoal", total_steps=1600, start_steps=100).resolve().collected_steps == 1600
