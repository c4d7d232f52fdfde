"""Lockstep rollouts: one episode in each of N tasks, one batched policy call per step."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from bati.envs.base import Task, TaskFamily

# act(observations (N, obs_dim), step) -> actions (N, act_dim)
ActFn = Callable[[np.ndarray, int], np.ndarray]


@dataclass
class Episodes:
    """N episodes of equal length T stepped in lockstep (arrays are (N, T, ...))."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    noise_free_rewards: np.ndarray
    """The reward without the step's noise (the env's info["reward_noise_free"]; the reward if it gives none)."""

    @property
    def returns(self) -> np.ndarray:
        return self.rewards.sum(axis=1)

    @property
    def noise_free_returns(self) -> np.ndarray:
        return self.noise_free_rewards.sum(axis=1)


def rollout(
    family: TaskFamily,
    tasks: Sequence[Task],
    act: ActFn,
    noise: float | None,
    seed: int | Sequence[int],
    length: int | None = None,
) -> Episodes:
    """Roll out `act` for one episode (`length` steps, default: the family's episode length) in each task.

    `seed`: an int (env i is reset with seed + i) or one reset seed per task.
    """
    reset_seeds = [seed + i for i in range(len(tasks))] if isinstance(seed, (int, np.integer)) else list(seed)
    if len(reset_seeds) != len(tasks):
        raise ValueError(f"{len(reset_seeds)} reset seeds for {len(tasks)} tasks")
    envs = [family.make_env(task, noise) for task in tasks]
    observations = np.stack([env.reset(seed=int(s))[0] for s, env in zip(reset_seeds, envs)])
    record: dict[str, list] = {k: [] for k in ("obs", "act", "rew", "next", "free")}
    for step in range(family.record.episode_length if length is None else length):
        actions = np.asarray(act(observations, step), dtype=np.float32)
        results = [env.step(a) for env, a in zip(envs, actions)]
        next_observations = np.stack([r[0] for r in results])
        record["obs"].append(observations)
        record["act"].append(actions)
        record["rew"].append([r[1] for r in results])
        record["next"].append(next_observations)
        record["free"].append([r[4].get("reward_noise_free", r[1]) for r in results])
        observations = next_observations
    for env in envs:
        env.close()
    stack = {k: np.swapaxes(np.asarray(v, dtype=np.float32), 0, 1) for k, v in record.items()}
    return Episodes(stack["obs"], stack["act"], stack["rew"], stack["next"], stack["free"])
