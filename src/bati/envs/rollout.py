"""The lockstep rollout engine: N envs of one family stepped together, one batched action array per step.

`LockstepEnvs` is the one place where envs are stepped: evaluation and the probes (`rollout`), data
collection (bati.data.collect) and expert training (bati.experts.train) all drive it. It makes its envs
once and reuses them: `reset(tasks, seeds)` switches env i to tasks[i] and resets it with seeds[i], so
an episode depends only on its task, its reset seed, the noise and the actions, never on which env of
the pool played it (a family whose env cannot `set_task` gets a fresh env per episode). An env whose
episode ends (terminated or truncated) stops: it is not stepped again until the next reset, its reward
is 0 and its observation stays the last one (`alive` says which steps were played).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from bati.envs.base import Task, TaskFamily

# act(observations (N, obs_dim), step) -> actions (N, act_dim)
ActFn = Callable[[np.ndarray, int], np.ndarray]


@dataclass
class Step:
    """What one lockstep step returns (arrays over the N envs)."""

    observations: np.ndarray  # (N, obs_dim) the next observations
    rewards: np.ndarray  # (N,) float64; 0 for an env whose episode had already ended
    noise_free_rewards: np.ndarray  # (N,) the env's info["reward_noise_free"] (the reward if it gives none)
    alive: np.ndarray  # (N,) bool: whether the env was stepped (its episode had not ended before)
    done: np.ndarray  # (N,) bool: whether the env's episode has ended (now or before)


class LockstepEnvs:
    """A reusable pool of a family's envs, reset to N tasks and stepped together (see the module)."""

    def __init__(self, family: TaskFamily, noise: float | None = None):
        self.family, self.noise = family, noise
        self._pool: list = []
        self._observations: np.ndarray | None = None
        self._done = np.zeros(0, bool)

    def __len__(self) -> int:
        return len(self._done)

    def reset(self, tasks: Sequence[Task], seeds: Sequence[int]) -> np.ndarray:
        """Start one episode in each task, env i reset with seeds[i]; returns the observations (N, obs_dim)."""
        if len(seeds) != len(tasks):
            raise ValueError(f"{len(seeds)} reset seeds for {len(tasks)} tasks")
        observations = [self._env(i, task).reset(seed=int(seed))[0] for i, (task, seed) in enumerate(zip(tasks, seeds))]
        self._observations = np.stack(observations)
        self._done = np.zeros(len(tasks), bool)
        return self._observations

    def step(self, actions: np.ndarray) -> Step:
        """Step every env whose episode goes on with its row of `actions`."""
        if self._observations is None:
            raise RuntimeError("reset the envs before stepping them")
        n = len(self._done)
        if len(actions) != n:
            raise ValueError(f"{len(actions)} actions for {n} envs")
        alive = ~self._done
        observations = self._observations.copy()
        rewards, noise_free = np.zeros(n), np.zeros(n)
        for i in np.flatnonzero(alive):
            obs, reward, terminated, truncated, info = self._pool[i].step(actions[i])
            observations[i], rewards[i] = obs, reward
            noise_free[i] = info.get("reward_noise_free", reward)
            self._done[i] = terminated or truncated
        self._observations = observations
        return Step(observations, rewards, noise_free, alive, self._done.copy())

    def close(self) -> None:
        for env in self._pool:
            env.close()
        self._pool, self._observations, self._done = [], None, np.zeros(0, bool)

    def __enter__(self) -> LockstepEnvs:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _env(self, i: int, task: Task):
        """Env i of the pool, switched to `task` (made for it when the pool is short or it cannot switch)."""
        if i == len(self._pool):
            self._pool.append(self.family.make_env(task, self.noise))
        elif hasattr(self._pool[i].unwrapped, "set_task"):
            self._pool[i].unwrapped.set_task(task)
        else:
            self._pool[i].close()
            self._pool[i] = self.family.make_env(task, self.noise)
        return self._pool[i]


@dataclass
class Episodes:
    """N episodes stepped in lockstep for T steps (arrays are (N, T, ...))."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_observations: np.ndarray
    noise_free_rewards: np.ndarray
    """The reward without the step's noise (the env's info["reward_noise_free"]; the reward if it gives none)."""
    alive: np.ndarray
    """(N, T) bool: the steps each episode played (all True unless an env's episode ended early)."""

    @property
    def returns(self) -> np.ndarray:
        return self.rewards.sum(axis=1)

    @property
    def noise_free_returns(self) -> np.ndarray:
        return self.noise_free_rewards.sum(axis=1)


# on_step(step, observations, actions, Step): called after every lockstep step
StepHook = Callable[[int, np.ndarray, np.ndarray, Step], None]


def rollout(
    family: TaskFamily,
    tasks: Sequence[Task],
    act: ActFn,
    noise: float | None,
    seed: int | Sequence[int],
    length: int | None = None,
    *,
    envs: LockstepEnvs | None = None,
    on_step: StepHook | None = None,
) -> Episodes:
    """Roll out `act` for one episode (`length` steps, default: the family's episode length) in each task.

    `seed`: an int (env i is reset with seed + i) or one reset seed per task. `envs`: a pool to reuse
    (its noise is used; default: a pool made and closed here). `on_step` sees every step as it is taken.
    """
    reset_seeds = [seed + i for i in range(len(tasks))] if isinstance(seed, (int, np.integer)) else list(seed)
    pool = envs if envs is not None else LockstepEnvs(family, noise)
    try:
        observations = pool.reset(tasks, reset_seeds)
        record: dict[str, list] = {k: [] for k in ("obs", "act", "rew", "next", "free", "alive")}
        for t in range(family.record.episode_length if length is None else length):
            actions = np.asarray(act(observations, t), dtype=np.float32)
            step = pool.step(actions)
            for name, value in zip(record, (observations, actions, step.rewards, step.observations,
                                            step.noise_free_rewards, step.alive)):
                record[name].append(value)
            if on_step is not None:
                on_step(t, observations, actions, step)
            observations = step.observations
    finally:
        if envs is None:
            pool.close()
    stack = {k: np.swapaxes(np.asarray(v, dtype=np.float32), 0, 1) for k, v in record.items() if k != "alive"}
    return Episodes(stack["obs"], stack["act"], stack["rew"], stack["next"], stack["free"],
                    np.swapaxes(np.asarray(record["alive"], bool), 0, 1))
