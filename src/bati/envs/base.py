"""The `TaskFamily` interface: a distribution of tasks sharing S, A and rho_0.

A task is the family's plain parameter (a float, +-1.0, or a 2-vector), so a user can type
it. Every family is registered with gymnasium as ``bati/<Name>-v0`` and made with
``gymnasium.make("bati/<Name>-v0", task=..., noise=...)``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from bati.checks import check_integer

EPISODE_LENGTH = 200

Task = Any  # float for scalar families, list[float] for vector tasks


class TaskError(ValueError):
    """A task, noise level or family name outside what the family allows."""


@dataclass(frozen=True)
class FamilyRecord:
    """Everything that differs per task family, in one place (Table 3 and our own choices).

    A family module defines one record beside its env; every module reads the family's settings from
    it (the network sizes of `bati.trainer`, the dataset sizes of `bati.data`, the expert's budget,
    the per-family weights of UNICORN and CSRO). Adding a family is one env file plus one record:
    docs/extending.md.
    """

    name: str
    task_space: str
    """Human-readable description of a task, shown by `bati envs` and in errors."""
    task_dim: int
    """Length of `task_to_array(task)` (what task-conditioned networks read)."""
    default_noise: float
    """The family's default eps (the paper's "high noise" setting)."""
    noise_meaning: str
    """What eps perturbs, for docs and `bati envs`."""
    max_noise: float = math.inf
    kind: str = "reward"
    """"reward" (tasks differ in R_M), "dynamics" (in P_M) or "opponent" (KuhnPoker: both)."""
    parameter_range: tuple[float, float] | None = None
    """The interval of the scalar parameter a task is drawn uniformly from, for families whose tasks
    have one (AntDir's angle, a target velocity, a log-friction); None: no task ranges (Table 2)."""
    discrete_actions: bool = False
    """Actions are one of `action_space.shape[0]` choices, stored one-hot (IQL's categorical actor)."""
    episode_length: int = EPISODE_LENGTH
    """Steps of an episode (the env's time limit)."""
    terminates: bool = False
    """Whether an episode can end before its time limit (no family of the paper does: every
    transition bootstraps in IQL)."""
    context_length: int = EPISODE_LENGTH
    """Transitions in a context unless a run says otherwise (one episode; KuhnPoker: 10 hands = 20)."""
    return_unit: str = "episode"
    """What an evaluation return sums over: an episode, or (KuhnPoker) one hand."""
    latent_dim: int = 5
    """Table 3: the task latent's size (reward families 5, Hopper / Walker 40)."""
    net_dims: tuple[int, ...] = (64, 64)
    """Table 3: hidden sizes of the context encoders and the dynamics decoders."""
    paper_episodes: int = 500
    """Episodes per training task at the paper scale (Table 3's "Dataset Size", read per task)."""
    expert_steps: int | None = None
    """Environment transitions for its SAC expert (None: the family's expert is not a SAC)."""
    per_task_expert_steps: int | None = None
    """Environment transitions per task for its per-task SAC experts (App. C.2's one SAC per training
    task: `bati experts train --per-task`); None: the family has none."""
    expert_name: str = ""
    """Who collects the family's data, in words, where its expert is not a SAC (KuhnPoker: "exact best
    responses"): live tables, progress bars and report headings name its data by it, not by an experts kind."""
    unicorn_weight: float = 0.15
    """Table 3: UNICORN's weight of the FOCAL term."""
    club_weight: float = 1.0
    """Table 3: CSRO's weight of the CLUB term."""
    entropy_weight: float = 5.0
    """ER-TRL's weight of the behaviour-entropy term (its code's `mir_loss_weight`: AntDir, Hopper and Walker
    5.0, HalfCheetahVel 2.5)."""
    version: int = 1
    """The env's version: bumped when its dynamics, rewards or tasks change, so that collections and
    experts made for another version are refused (their manifest / expert.json records it)."""


def record_default(field_name: str):
    """A FamilyRecord field's default (what a method uses when it is built without a family)."""
    return FamilyRecord.__dataclass_fields__[field_name].default


# The TaskFamily attributes that come from its record (kept as attributes: `family.default_noise`).
RECORD_ATTRIBUTES = ("name", "task_space", "task_dim", "default_noise", "noise_meaning", "max_noise", "kind",
                     "parameter_range", "discrete_actions", "return_unit")


class TaskFamily(abc.ABC):
    """A family of tasks: sampling, distance (App. C.2), validation and env construction.

    Subclasses set `record` (their FamilyRecord) and implement the abstract methods. Families are
    stateless; randomness always comes from an explicit seed or generator.
    """

    record: FamilyRecord

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        record = cls.__dict__.get("record")
        if record is not None:  # a concrete family: its record's facts readable as attributes
            for attribute in RECORD_ATTRIBUTES:
                setattr(cls, attribute, getattr(record, attribute))

    @property
    def default_context_length(self) -> int:
        return self.record.context_length

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

    def task_from_parameter(self, value: float) -> Task:
        """The task whose scalar parameter is `value` (identity unless the task is not the parameter)."""
        return float(value)

    def sample_tasks_in(self, n: int, seed: int | np.random.Generator, low: float, high: float) -> list[Task]:
        """n tasks whose parameter is uniform in [low, high), a sub-range of `parameter_range`."""
        check_parameter_range(self, (low, high))
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        return [self.validate_task(self.task_from_parameter(float(x))) for x in rng.uniform(low, high, size=n)]

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
        """A time-limited (`record.episode_length` steps) env of this task with per-step noise eps."""
        return gym.make(self.env_id, task=self.validate_task(task), noise=self.validate_noise(noise), **kwargs)

    def exact_returns(self, act, tasks: Sequence[Task], noise: float | None) -> np.ndarray | None:
        """The expected return (per `return_unit`) of a deterministic policy `act(observations) ->
        actions` in each task, computed exactly, or None where the family cannot (evaluate by rollouts).
        `act=None` stands for the uniformly random policy."""
        return None


def check_parameter_range(family: TaskFamily, task_range) -> tuple[float, float]:
    """A (low, high) sub-range of the family's task parameter, or TaskError saying why not."""
    if family.parameter_range is None:
        raise TaskError(f"{family.name}: its tasks ({family.task_space}) cannot be drawn from a range")
    try:
        low, high = (float(x) for x in task_range)
    except (TypeError, ValueError) as err:
        raise TaskError(f"{family.name}: task range {task_range!r} must be two numbers LOW HIGH") from err
    lo, hi = family.parameter_range
    if not (lo <= low < high <= hi):
        raise TaskError(f"{family.name}: task range [{low:g}, {high:g}) must be a non-empty sub-range of "
                        f"[{lo:g}, {hi:g}] ({family.task_space})")
    return low, high


@dataclass(frozen=True)
class TaskSplit:
    """Which tasks train and which test (Sec. 5.1: 20 + 20 drawn from one seed).

    `n_train` / `n_test` change the counts (App. D.3 splits the same 40 tasks 10/30 or 30/10);
    `train_range` / `test_range` draw each side uniformly from a sub-range of the family's task
    parameter instead (Sec. 5.7: AntDir trains on [0, pi) and tests on [pi, 2 pi)).
    """

    n_train: int = 20
    n_test: int = 20
    train_range: tuple[float, float] | None = None
    test_range: tuple[float, float] | None = None

    @property
    def is_default(self) -> bool:
        return self == TaskSplit()

    def checked(self, family: TaskFamily) -> TaskSplit:
        """This split with ranges as float pairs, or TaskError (one line) for a bad one."""
        for name in ("n_train", "n_test"):
            check_integer(name, getattr(self, name), error=TaskError)
        if self.n_train < 2:
            raise TaskError(f"n_train={self.n_train}: Eq. 9 needs at least 2 training tasks")
        ranges = {name: None if getattr(self, name) is None else check_parameter_range(family, getattr(self, name))
                  for name in ("train_range", "test_range")}
        return TaskSplit(self.n_train, self.n_test, **ranges)

    def draw(self, family: TaskFamily, seed: int) -> tuple[list[Task], list[Task]]:
        """The training and test tasks, reproducibly from `seed` (the default split is
        `family.split_tasks(seed)`, so existing collections keep their tasks)."""
        split = self.checked(family)
        if split.train_range is None and split.test_range is None:
            return family.split_tasks(seed, split.n_train, split.n_test)
        rng = np.random.default_rng(seed)
        draw = lambda n, r: family.sample_tasks_in(n, rng, *r) if r else family.sample_tasks(n, rng)  # noqa: E731
        return draw(split.n_train, split.train_range), draw(split.n_test, split.test_range)

    def label(self) -> str:
        """A suffix naming a non-default split in a collection's directory name ("" for the default)."""
        parts = []
        if (self.n_train, self.n_test) != (20, 20):
            parts.append(f"tasks{self.n_train}x{self.n_test}")
        for side, r in (("train", self.train_range), ("test", self.test_range)):
            if r is not None:
                parts.append(f"{side}{r[0]:.6g}to{r[1]:.6g}")
        return "".join(f"-{p}" for p in parts)

    def record(self) -> dict:
        return {"n_train": self.n_train, "n_test": self.n_test,
                "train_range": None if self.train_range is None else list(self.train_range),
                "test_range": None if self.test_range is None else list(self.test_range)}


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
