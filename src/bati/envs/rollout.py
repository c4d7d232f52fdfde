"""The lockstep rollout engine: N envs of one family stepped together, one batched action array per step.

`LockstepEnvs` is the one place where envs are stepped: evaluation and the probes (`rollout`), data
collection (bati.data.collect) and expert training (bati.experts.train) all drive it. It makes its envs
once and reuses them: `reset(tasks, seeds)` switches env i to tasks[i] and resets it with seeds[i], so
an episode depends only on its task, its reset seed, the noise and the actions, never on which env of
the pool played it (a family whose env cannot `set_task` gets a fresh env per episode). An env whose
episode ends (terminated or truncated) stops: it is not stepped again until the next reset, its reward
is 0 and its observation stays the last one (`alive` says which steps were played).

`lockstep_envs(family, noise, workers)` gives the same pool spread over worker processes
(`ProcessLockstepEnvs`): env i of N lives in one of `workers` spawned processes, each stepping its
contiguous share of the N envs with its own `LockstepEnvs`. Since an episode depends only on its task,
reset seed, noise and actions, the numbers are the same whatever the number of workers; only the wall
time changes (MuJoCo stepping is what evaluation spends its time on: docs/performance.md).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np

from bati.checks import check_integer
from bati.envs.base import Task, TaskFamily

# What a worker process that steps envs sets first, so that N workers use N cores (collection's workers too).
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}

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


def lockstep_envs(family: TaskFamily, noise: float | None = None, workers: int = 1):
    """A lockstep pool of `family`'s envs: in this process (workers = 1) or over `workers` processes."""
    check_integer("workers", workers)
    return LockstepEnvs(family, noise) if workers == 1 else ProcessLockstepEnvs(family, noise, workers)


class ProcessLockstepEnvs:
    """`LockstepEnvs` over `workers` spawned processes (see the module): same interface, same numbers.

    The processes start at the first reset and live until `close` (or this process's exit: they are
    daemonic, and each also stops when its pipe closes). `family` must be picklable (every registered
    family is)."""

    def __init__(self, family: TaskFamily, noise: float | None = None, workers: int = 2):
        self.family, self.noise = family, noise
        self.workers = check_integer("workers", workers)
        self._processes: list = []
        self._pipes: list = []
        self._shards: list[slice] = []

    def __len__(self) -> int:
        return self._shards[-1].stop if self._shards else 0

    def reset(self, tasks: Sequence[Task], seeds: Sequence[int]) -> np.ndarray:
        if len(seeds) != len(tasks):
            raise ValueError(f"{len(seeds)} reset seeds for {len(tasks)} tasks")
        self._start()
        bounds = np.linspace(0, len(tasks), min(self.workers, len(tasks)) + 1).astype(int)
        self._shards = [slice(int(a), int(b)) for a, b in zip(bounds, bounds[1:])]
        tasks, seeds = list(tasks), [int(s) for s in seeds]
        for pipe, shard in zip(self._pipes, self._shards):
            pipe.send(("reset", (tasks[shard], seeds[shard])))
        return np.concatenate(self._receive())

    def step(self, actions: np.ndarray) -> Step:
        if not self._shards:
            raise RuntimeError("reset the envs before stepping them")
        if len(actions) != len(self):
            raise ValueError(f"{len(actions)} actions for {len(self)} envs")
        actions = np.asarray(actions)
        for pipe, shard in zip(self._pipes, self._shards):
            pipe.send(("step", actions[shard]))
        steps = self._receive()
        return Step(*(np.concatenate([getattr(s, f.name) for s in steps]) for f in fields(Step)))

    def close(self) -> None:
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
                pipe.close()
            except OSError:  # the worker is gone already
                pass
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
        self._processes, self._pipes, self._shards = [], [], []

    def __enter__(self) -> ProcessLockstepEnvs:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start(self) -> None:
        if self._processes:
            return
        context = multiprocessing.get_context("spawn")  # JAX (in this process) is not fork-safe
        for _ in range(self.workers):
            parent, child = context.Pipe()
            process = context.Process(target=_serve_envs, args=(child, self.family, self.noise), daemon=True)
            process.start()
            child.close()
            self._processes.append(process)
            self._pipes.append(parent)

    def _receive(self) -> list:
        """Every worker's answer (all of them read first, so that the pipes stay in step), or the first error."""
        answers = []
        for pipe in self._pipes[:len(self._shards)]:
            try:
                answers.append(pipe.recv())
            except EOFError:
                self.close()
                raise RuntimeError("an env worker process died (out of memory?); the pool is closed") from None
        for ok, answer in answers:
            if not ok:
                raise answer
        return [answer for _, answer in answers]


def _serve_envs(pipe, family: TaskFamily, noise: float | None) -> None:
    """A worker of ProcessLockstepEnvs: one thread, no accelerator; answers (ok, result) per message."""
    os.environ.update(ONE_THREAD_ENV, JAX_PLATFORMS="cpu")
    envs = LockstepEnvs(family, noise)
    try:
        while True:
            try:
                command, argument = pipe.recv()
            except (EOFError, KeyboardInterrupt):
                return
            if command == "close":
                return
            try:
                answer = envs.reset(*argument) if command == "reset" else envs.step(argument)
            except Exception as error:  # noqa: BLE001  (the caller raises it)
                pipe.send((False, error))
            else:
                pipe.send((True, answer))
    finally:
        envs.close()


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
    envs: LockstepEnvs | ProcessLockstepEnvs | None = None,
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
