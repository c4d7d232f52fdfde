"""Experts: SAC training smoke test on PointGoal, exact resume, the policy interface, cards."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from bati.envs import TaskError
from bati.experts import load
from bati.experts.card import write_card
from bati.experts.train import ExpertTrainConfig, train_expert

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
    expert = load("PointGoal", trained / "zoo-straight")
    assert expert.meta["train_steps"] == 800


def test_resumed_training_gives_the_same_expert_as_an_uninterrupted_run(trained):
    a = load("PointGoal", trained / "zoo-straight").actor_params
    b = load("PointGoal", trained / "zoo-resumed").actor_params
    jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)


def test_policy_interface_single_batched_deterministic_and_stochastic(trained):
    expert = load("PointGoal", trained / "zoo-straight")
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
    card = write_card("PointGoal", seed=0, zoo_dir=trained / "zoo-straight")
    assert len(card["train_returns"]) == 20 and len(card["test_returns"]) == 20
    assert card["task_specificity_gap"] == pytest.approx(
        card["oracle_test_return"] - card["most_different_expert_test_return"])
    assert (trained / "zoo-straight" / "PointGoal" / "card.md").read_text().startswith("# Expert card: PointGoal")


def test_missing_expert_and_mismatched_run_directory_are_clear_errors(tmp_path, trained):
    with pytest.raises(FileNotFoundError, match="bati experts train --family PointGoal"):
        load("PointGoal", tmp_path)
    config = ExpertTrainConfig("PointGoal", total_steps=400, out_dir=trained / "straight", seed=3,
                               export_dir=tmp_path, **SMALL)
    with pytest.raises(ValueError, match="seed: 0 there, 3 now"):
        train_expert(config, show_progress=False)


def test_shipped_experts_load():
    expert = load("PointGoal")
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
])
def test_bad_expert_settings_are_refused_before_any_work(tmp_path, settings, message, capsys):
    from bati.cli import main

    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ExpertTrainConfig("PointGoal", out_dir=tmp_path / "run", **settings).resolved()
    args = ["experts", "train", "--family", "PointGoal", "--out-dir", str(tmp_path / "run")]
    for key, value in settings.items():
        args += [f"--{key.replace('_', '-')}"] if value is True else [f"--{key.replace('_', '-')}", str(value)]
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "run").exists()
