"""A user's own Minari datasets (bati.data.own, `bati train --datasets`), built here as docs/own-data.md does."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.cli import main
from bati.data.batch import sample_batch, sample_contexts
from bati.data.own import load_own_data
from bati.data.store import DatasetError
from bati.rl.iql import IQL, IQLConfig, critic_loss

# the example of docs/own-data.md, run as written (examples/own_data_goalline.py)
_spec = importlib.util.spec_from_file_location("own_data_goalline",
                                               Path(__file__).parent.parent / "examples" / "own_data_goalline.py")
example = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(example)
GOALS = example.GOALS
pytestmark = pytest.mark.filterwarnings("ignore::UserWarning:minari.utils")  # Minari nags about authorship


@pytest.fixture
def dataset(tmp_path):
    return str(example.build(tmp_path / "minari", episodes=6))


def test_episodes_are_grouped_by_task_key_and_cut_into_segments(dataset):
    data = load_own_data((dataset,), "goal", segment_length=10, held_out=0.25)
    assert data.train_tasks == sorted(json.dumps(g) for g in GOALS) and data.task_dim == 4
    assert data.manifest["transitions_kept"] <= data.manifest["transitions_read"]
    counts, held = np.asarray(data.train.counts), np.asarray(data.held_out.counts)
    assert np.all(counts % 10 == 0) and np.all(counts >= 10) and np.all(held >= 10)
    for task in data.manifest["tasks"]:
        assert task["episodes"] == 6 and task["held_out"] >= 1
    # the episodes that reached the goal terminated: their last kept transition may carry the flag
    assert 0 < float(jnp.sum(data.train.terminals)) <= 4 * 6


def test_samplers_draw_only_valid_transitions_and_windows_inside_segments(dataset):
    data = load_own_data((dataset,), "goal", segment_length=10, held_out=0.25)
    batch = sample_batch(data.train, jax.random.PRNGKey(0), task_batch=4, batch_size=512)
    assert "terminals" in batch
    contexts = sample_contexts(data.train, jax.random.PRNGKey(1), jnp.arange(4).repeat(50), 10)
    # consecutive observations of a window follow each other (next_obs[t] == obs[t + 1]): never two segments
    np.testing.assert_array_equal(contexts["next_observations"][:, :-1], contexts["observations"][:, 1:])
    # no transition beyond a task's count: every sampled observation is one of the task's own valid rows
    for task in range(4):
        valid = np.asarray(data.train.observations[task, : int(data.train.counts[task])])
        rows = np.asarray(batch["observations"][list(np.asarray(batch["task_ids"])).index(task)])
        assert all((np.abs(valid - row).sum(-1) == 0).any() for row in rows)


def test_bad_own_data_gets_one_clear_error(dataset, tmp_path):
    with pytest.raises(DatasetError, match="1 task in"):  # one dataset, no task key: one task
        load_own_data((dataset,), None, segment_length=10, held_out=0.25)
    with pytest.raises(DatasetError, match="has no 'nope' in its options"):
        load_own_data((dataset,), "nope", segment_length=10, held_out=0.25)
    with pytest.raises(DatasetError, match="segment"):  # episodes shorter than a segment
        load_own_data((dataset,), "goal", segment_length=1000, held_out=0.25)
    assert main(["train", "--datasets", str(tmp_path / "missing"), "--task-key", "goal"]) == 2


def test_iql_does_not_bootstrap_past_a_terminal():
    iql = IQL(1, 2, 1, IQLConfig(hidden_dims=(8,)))
    state = iql.init(jax.random.PRNGKey(0))
    batch = {"observations": jnp.zeros((3, 1)), "actions": jnp.zeros((3, 1)), "rewards": jnp.ones(3),
             "next_observations": jnp.ones((3, 1))}
    z = jnp.zeros((3, 2))
    ended = critic_loss(state.critic.params, state, {**batch, "terminals": jnp.ones(3)}, z, iql.config)[0]
    q = iql.critic_net.apply(state.critic.params, jnp.concatenate([batch["observations"], z, batch["actions"]], -1))
    np.testing.assert_allclose(ended, ((q - 1.0) ** 2).mean(), rtol=1e-6)  # target = reward alone
    going = critic_loss(state.critic.params, state, {**batch, "terminals": jnp.zeros(3)}, z, iql.config)[0]
    np.testing.assert_allclose(going, critic_loss(state.critic.params, state, batch, z, iql.config)[0], rtol=1e-6)


@pytest.mark.slow
def test_bati_train_on_own_datasets_reports_offline_diagnostics(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["train", "--datasets", dataset, "--task-key", "goal", "--context-length", "10", "--task-batch", "4",
                 "--batch-size", "16", "--steps", "20", "--eval-every", "10", "--log-every", "10",
                 "--iql.hidden-dims", "16", "16", "--out-dir", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "held-out task-inference accuracy" in capsys.readouterr().out
    evals = [json.loads(line) for line in (out / "eval.jsonl").read_text().splitlines()]
    assert [e["step"] for e in evals] == [10, 20]
    assert all(0.0 <= e["held_out_inference_accuracy"] <= 1.0 for e in evals)
    config = json.loads((out / "config.json").read_text())
    assert config["family"] == "own" and config["datasets"] == [dataset] and config["task_key"] == "goal"


@pytest.mark.slow
def test_returns_in_your_env_and_bati_infer_on_an_own_data_run(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["train", "--datasets", dataset, "--task-key", "goal", "--eval-env", "GoalLine-v0",
                 "--context-length", "10", "--task-batch", "4", "--batch-size", "16", "--steps", "20",
                 "--eval-every", "10", "--log-every", "10", "--iql.hidden-dims", "16", "16", "--out-dir", str(out)])
    assert code == 0, capsys.readouterr().err
    assert "return in your env" in capsys.readouterr().out
    evals = [json.loads(line) for line in (out / "eval.jsonl").read_text().splitlines()]
    for e in evals:  # 40-step episodes, reward = -distance to the goal (at most 3.5 away)
        assert -40 * 3.5 <= e["held_out_return"] <= 0.0 and len(e["held_out_task_returns"]) == len(GOALS)
        assert e["held_out_return"] == pytest.approx(np.mean(e["held_out_task_returns"]), abs=1e-3)
    summary = json.loads((out / "eval.json").read_text())
    assert summary["held_out_return"] == pytest.approx(np.mean([e["held_out_return"] for e in evals]))
    # bati report: a held-out table for own-data runs (no returns to normalise), not "missing keys"
    assert main(["report", str(out), "--out-dir", str(tmp_path / "report")]) == 0, capsys.readouterr().err
    md = (tmp_path / "report" / "report.md").read_text()
    assert "### own data (" in md and "held-out task-inference accuracy" in md and "return in your env" in md
    row = next(line for line in md.splitlines() if line.startswith("| bati |"))
    assert f"{summary['held_out_return']:.1f}" in row and f"{summary['held_out_inference_accuracy']:.3f}" in row
    assert (tmp_path / "report" / "runs.csv").read_text().count("\n") == 2  # header + the run
    assert (tmp_path / "report" / "own-quick-eps0-20steps_held_out.png").is_file()
    capsys.readouterr()
    assert all(t["episode_return_mean"] < 0 for t in summary["data"]["tasks"])
    assert json.loads((out / "config.json").read_text())["eval_env"] == "GoalLine-v0"

    # `bati infer` on the run: a held-out window of goal 0.8 is scored under the run's table
    data = load_own_data((dataset,), "goal", segment_length=10, held_out=0.2)
    task = data.train_tasks.index(json.dumps(0.8))
    window = {name: np.asarray(getattr(data.held_out, name)[task, :10]) for name in
              ("observations", "actions", "rewards", "next_observations")}
    np.savez(tmp_path / "context.npz", **window)
    assert main(["infer", "--run-dir", str(out), "--context", str(tmp_path / "context.npz")]) == 0
    inferred = json.loads(capsys.readouterr().out)
    assert inferred["family"] == "own" and inferred["task"] in data.train_tasks and inferred["context_length"] == 10
    # `bati likelihood` compares p_train and p_test contexts of test tasks, which own data does not have
    assert main(["likelihood", "--run-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "trained on your own datasets" in err[0] and "unknown task family" not in err[0]


class _NoLimit(gym.Env):  # spaces like GoalLine's, registered without a time limit
    observation_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)


class _Wider(_NoLimit):  # observations of 2 numbers: not your data's
    observation_space = gym.spaces.Box(-2.0, 2.0, (2,), np.float32)


class _BadReset(_NoLimit):  # spaces like your data's, but reset raises
    def reset(self, *, seed=None, options=None):
        raise RuntimeError("the simulator is not running")


gym.register("BatiTestNoLimit-v0", entry_point=_NoLimit)
gym.register("BatiTestBadReset-v0", entry_point=_BadReset, max_episode_steps=40)
gym.register("BatiTestWider-v0", entry_point=_Wider, max_episode_steps=40)


@pytest.mark.parametrize("extra,message", [
    (["--eval-env", "GoalLine-v0"], "--eval-env needs --task-key"),
    (["--task-key", "goal", "--eval-env", "NoSuchEnv-v0"], "cannot be made"),
    (["--task-key", "goal", "--eval-env", "BatiTestNoLimit-v0"], "no time limit"),
    (["--task-key", "goal", "--eval-env", "BatiTestWider-v0"], "observations (2,)"),
    (["--task-key", "goal", "--eval-env", "BatiTestBadReset-v0"], "failed to reset to your first task "
                                                                   "(RuntimeError: the simulator is not running)"),
])
def test_a_bad_eval_env_is_one_line_and_leaves_no_run(dataset, tmp_path, capsys, extra, message):
    out = tmp_path / "run"
    code = main(["train", "--datasets", dataset, *extra, "--context-length", "10", "--task-batch", "4",
                 "--steps", "20", "--out-dir", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists() or not any(out.iterdir())


def test_eval_env_is_for_own_data_only(capsys):
    assert main(["train", "--family", "PointGoal", "--eval-env", "GoalLine-v0"]) == 2
    assert "--eval-env is your own data's env" in capsys.readouterr().err


def _edit_episode(dataset: str, edit) -> None:
    import h5py

    with h5py.File(Path(dataset) / "data" / "main_data.hdf5", "a") as f:
        edit(f["episode_0"])


@pytest.mark.parametrize("edit, message", [
    (lambda ep: ep["observations"].__setitem__((3, 0), np.nan), "episode 0: observations holds NaN or infinite"),
    (lambda ep: ep["rewards"].__setitem__(2, np.inf), "episode 0: rewards holds NaN or infinite"),
    (lambda ep: ep.__delitem__("rewards"), "episode 0 cannot be read"),
])
def test_a_damaged_episode_is_one_line_naming_the_dataset_and_the_episode(dataset, edit, message):
    _edit_episode(dataset, edit)
    with pytest.raises(DatasetError) as caught:
        load_own_data((dataset,), "goal", segment_length=10, held_out=0.25)
    assert message in str(caught.value) and dataset in str(caught.value)


def test_a_run_refuses_to_resume_on_edited_datasets(dataset, tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train", "--datasets", dataset, "--task-key", "goal", "--context-length", "10", "--task-batch", "4",
            "--batch-size", "16", "--steps", "4", "--eval-every", "2", "--log-every", "2", "--iql.hidden-dims", "8",
            "--out-dir", str(out)]
    assert main(args) == 0, capsys.readouterr().err
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    _edit_episode(dataset, lambda ep: ep["rewards"].__setitem__(0, ep["rewards"][0] + 1.0))
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "changed since this run started" in err[0], err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # nothing touched
