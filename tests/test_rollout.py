"""The lockstep rollout engine (bati.envs.rollout): reuse, termination, errors."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from bati.data.own import OwnFamily
from bati.envs import get_family
from bati.envs.rollout import LockstepEnvs, ProcessLockstepEnvs, lockstep_envs, rollout

# docs/own-data.md's GoalLine (registered as GoalLine-v0 by the example): an env whose episodes terminate
_spec = importlib.util.spec_from_file_location("own_data_goalline",
                                               Path(__file__).parent.parent / "examples" / "own_data_goalline.py")
_spec.loader.exec_module(importlib.util.module_from_spec(_spec))


def _random_policy(seed: int, action_dim: int):
    rng = np.random.default_rng(seed)
    return lambda obs, _: rng.uniform(-1, 1, (len(obs), action_dim))


@pytest.mark.parametrize("family_name,action_dim", [("PointGoal", 2), ("HopperParam", 3)])
def test_a_reused_pool_plays_exactly_the_episodes_of_fresh_envs(family_name, action_dim):
    family = get_family(family_name)
    tasks = family.sample_tasks(5, seed=0)
    first, second = tasks[:3], [tasks[4], tasks[3], tasks[0], tasks[1]]  # other tasks, another count
    act = lambda seed: _random_policy(seed, action_dim)  # noqa: E731
    with LockstepEnvs(family, noise=None) as envs:
        reused = [rollout(family, first, act(0), None, seed=10, length=30, envs=envs),
                  rollout(family, second, act(1), None, seed=[7, 3, 9, 1], length=30, envs=envs)]
    fresh = [rollout(family, first, act(0), None, seed=10, length=30),
             rollout(family, second, act(1), None, seed=[7, 3, 9, 1], length=30)]
    for a, b in zip(reused, fresh):
        for name in ("observations", "actions", "rewards", "next_observations", "noise_free_rewards"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert a.alive.all()


def test_an_env_whose_episode_ends_stops_and_earns_nothing_more():
    family = OwnFamily(10, eval_env="GoalLine-v0", task_key="goal")
    tasks = [json.dumps(0.3), json.dumps(-0.8)]
    toward_goal = np.array([[1.0], [-1.0]])  # from x = +-1.5 toward each goal: some episodes end early
    episodes = rollout(family, tasks, lambda obs, _: np.sign(np.array([[0.3], [-0.8]]) - obs) * np.abs(toward_goal),
                       None, seed=[0, 1], length=40)
    for i in range(2):
        alive = episodes.alive[i]
        played = int(alive.sum())
        assert alive[:played].all() and not alive[played:].any()  # once ended, never stepped again
        assert np.all(episodes.rewards[i, played:] == 0.0)
        np.testing.assert_array_equal(episodes.next_observations[i, played:],
                                      np.broadcast_to(episodes.next_observations[i, played - 1],
                                                      episodes.next_observations[i, played:].shape))
    assert not episodes.alive.all(), "heading straight for the goal ends an episode before its 40 steps"
    # each env was reset with its task's goal (the reset options): the last reward of an ended episode
    # is minus its distance to that goal, under 0.05
    ended = [i for i in range(2) if not episodes.alive[i, -1]]
    for i in ended:
        assert -0.05 < episodes.rewards[i, int(episodes.alive[i].sum()) - 1] <= 0.0


def test_bad_calls_are_refused():
    envs = LockstepEnvs(get_family("PointGoal"))
    with pytest.raises(RuntimeError, match="reset"):
        envs.step(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="2 reset seeds for 1 tasks"):
        envs.reset(get_family("PointGoal").sample_tasks(1, 0), [1, 2])
    envs.reset(get_family("PointGoal").sample_tasks(2, 0), [1, 2])
    with pytest.raises(ValueError, match="3 actions for 2 envs"):
        envs.step(np.zeros((3, 2)))
    envs.close()


def test_envs_spread_over_processes_play_the_same_episodes_as_one_pool():
    """ProcessLockstepEnvs: the same numbers as LockstepEnvs whatever the number of workers (the shards are
    uneven here: 5 envs over 2 processes, then 3 envs over the same 2), with noise, reused across resets."""
    family = get_family("HopperParam")
    tasks = family.sample_tasks(5, seed=0)
    act = lambda seed: _random_policy(seed, 3)  # noqa: E731
    serial = [rollout(family, tasks, act(0), 1.0, seed=10, length=25),
              rollout(family, tasks[1:4], act(1), 1.0, seed=[7, 3, 9], length=25)]
    with lockstep_envs(family, 1.0, workers=2) as envs:
        assert isinstance(envs, ProcessLockstepEnvs)
        spread = [rollout(family, tasks, act(0), 1.0, seed=10, length=25, envs=envs),
                  rollout(family, tasks[1:4], act(1), 1.0, seed=[7, 3, 9], length=25, envs=envs)]
        assert len(envs) == 3
    for a, b in zip(serial, spread):
        for name in ("observations", "actions", "rewards", "next_observations", "noise_free_rewards", "alive"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert isinstance(lockstep_envs(family, None, workers=1), LockstepEnvs)


def test_a_process_pool_refuses_bad_calls_and_passes_on_a_worker_error():
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        lockstep_envs(get_family("PointGoal"), workers=0)
    family = get_family("PointGoal")
    with ProcessLockstepEnvs(family, workers=2) as envs:
        with pytest.raises(RuntimeError, match="reset"):
            envs.step(np.zeros((1, 2)))
        with pytest.raises(ValueError, match="2 reset seeds for 1 tasks"):
            envs.reset(family.sample_tasks(1, 0), [1, 2])
        envs.reset(family.sample_tasks(3, 0), [1, 2, 3])
        with pytest.raises(ValueError, match="2 actions for 3 envs"):
            envs.step(np.zeros((2, 2)))
        with pytest.raises(ValueError):  # raised in a worker (a malformed action), raised here
            envs.step(np.zeros((3, 5, 7)))
        envs.reset(family.sample_tasks(3, 0), [1, 2, 3])  # the pipes are still in step
        assert envs.step(np.zeros((3, 2))).observations.shape == (3, 2)
    assert not envs._processes, "close stops the workers"
