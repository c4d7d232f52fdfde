"""The `TaskFamily` interface: a distribution of tasks sharing S, A and rho_0.

A task is the family's plain parameter (a float, +-1.0, or a 2-vector), so a user can type
it. Every family is registered with gymnasium as ``bati/<Name>-v0`` and made with
``gymnasium.make("bati/<Name>-v0", task=..., noise=...)``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

EPISODE_LENGTH = 200

Task = Any  # float for scalar families, list[float] for vector tasks


class TaskError(ValueError):
    """A task, noise level or family name outside what the family allows."""


class TaskFamily(abc.ABC):
    """A family of tasks: sampling, distance (App. C.2), validation and env construction.

    Subclasses set the class attributes and implement the abstract methods. Families are
    stateless; randomness always comes from an explicit seed or generator.
    """

    name: str
    task_space: str  # human-readable description, shown by `bati envs` and in errors
    task_dim: int  # length of `task_to_array(task)`
    default_noise: float  # the family's default eps ("high noise" setting)
    noise_meaning: str  # what eps perturbs, for docs and `bati envs`
    max_noise: float = math.inf
    kind: str = "reward"  # "reward" (tasks differ in R_M) or "dynamics" (tasks differ in P_M)

    @property
    def env_id(self) -> str:
        return f"bati/{self.name}-v0"

    # --- tasks -------------------------------------------------------------------------
    @abc.abstractmethod
    def _sample(self, n: int, rng: np.random.Generator) -> list[Task]:
        """Draw n tasks from the family's task distribution."""

    @abc.abstractmethod
    def _check(self, task: Task) -> Task:
        """Return the task in canonical form or raise TaskError naming the allowed range."""

    @abc.abstractmethod
    def distance(self, a: Task, b: Task) -> float:
        """Task distance of App. C.2 (used to pick the most similar / different expert)."""

    def task_to_array(self, task: Task) -> np.ndarray:
        """The task as a float32 vector (what task-conditioned networks read)."""
        return np.atleast_1d(np.asarray(self.validate_task(task), dtype=np.float32))

    def sample_tasks(self, n: int, seed: int | np.random.Generator) -> list[Task]:
        """n tasks drawn reproducibly from `seed` (an int or a numpy Generator)."""
        if n < 0:
            raise TaskError(f"cannot sample {n} tasks: n must be >= 0")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        return [self.validate_task(t) for t in self._sample(n, rng)]

    def split_tasks(self, seed: int, n_train: int = 20, n_test: int = 20) -> tuple[list[Task], list[Task]]:
        """The training and test tasks of Sec. 5.1, drawn together from one seed.

        Continuous task spaces give disjoint sets (with probability 1); HalfCheetahDir has only
        two tasks, so its 20 + 20 draws repeat them, as in the paper.
        """
        tasks = self.sample_tasks(n_train + n_test, seed)
        return tasks[:n_train], tasks[n_train:]

    def most_different(self, task: Task, candidates: Sequence[Task]) -> int:
        """Index of the candidate farthest from `task` (App. C.2 distance; first on ties)."""
        return int(np.argmax([self.distance(task, c) for c in candidates]))

    def most_similar(self, task: Task, candidates: Sequence[Task]) -> int:
        """Index of the candidate closest to `task` (first on ties)."""
        return int(np.argmin([self.distance(task, c) for c in candidates]))

    def validate_task(self, task: Task) -> Task:
        try:
            return self._check(task)
        except TaskError:
            raise
        except (TypeError, ValueError) as err:
            raise TaskError(
                f"{self.name}: task {task!r} is not a valid task; expected {self.task_space}"
            ) from err

    def validate_noise(self, noise: float | None) -> float:
        if noise is None:
            return self.default_noise
        noise = float(noise)
        if not (0.0 <= noise <= self.max_noise) or not math.isfinite(noise):
            upper = "inf" if math.isinf(self.max_noise) else f"{self.max_noise:g}"
            raise TaskError(f"{self.name}: noise eps={noise:g} is outside the allowed range [0, {upper}]")
        return noise

    def distance_matrix(self, tasks_a: Sequence[Task], tasks_b: Sequence[Task]) -> np.ndarray:
        return np.array([[self.distance(a, b) for b in tasks_b] for a in tasks_a], dtype=np.float64)

    # --- environments ------------------------------------------------------------------
    def make_env(self, task: Task, noise: float | None = None, **kwargs: Any) -> gym.Env:
        """A time-limited (200 steps) env of this task with per-step noise eps."""
        return gym.make(self.env_id, task=self.validate_task(task), noise=self.validate_noise(noise), **kwargs)


def scalar_task(family: TaskFamily, task: Task, low: float, high: float, closed_high: bool = True) -> float:
    """Validate a scalar task in [low, high] (or [low, high) when `closed_high` is False)."""
    if isinstance(task, (list, tuple, np.ndarray)):
        arr = np.asarray(task, dtype=np.float64).reshape(-1)
        if arr.size != 1:
            raise TaskError(f"{family.name}: task {task!r} must be a single number in {family.task_space}")
        task = arr[0]
    value = float(task)
    inside = low <= value <= high if closed_high else low <= value < high
    if not inside or math.isnan(value):
        raise TaskError(f"{family.name}: task {value!r} is outside the task space {family.task_space}")
    return value


class TaskEnvMixin:
    """Gives an env its validated `task` and `noise`; per-step noise draws use `np_random`."""

    family: TaskFamily

    def _set_task(self, task: Task, noise: float | None) -> None:
        self.set_task(task)
        self.noise = self.family.validate_noise(noise)

    def set_task(self, task: Task) -> None:
        """Switch the env to another task of its family (takes effect at the next step)."""
        self.task = self.family.validate_task(task)
