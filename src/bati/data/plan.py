"""The Eq. 9 / Eq. 10 plan of a collection: which expert collects each episode of each dataset.

For the split `train, test = family.split_tasks(seed)` (20 + 20 tasks): training task i's dataset is
90% its own expert's episodes and 10% (at least 1) those of experts of other training tasks; test task
j's p_test contexts come from the expert of the training task most different from j (dynamics
families: 10% from the most similar one, App. C.2) and its p_train contexts from the most similar one.
Where several training tasks tie (HalfCheetahDir's ten tasks of one direction), `ties="first"` names the
first of them for every episode and `ties="drawn"` draws one of them per episode (seeded, a stream of its
own: a plan without ties is the same either way). Per-task experts differ among tied tasks, so their
collections draw; the task-conditioned expert acts the same for equal tasks, so its collections take the first.
`bati.data.collect` carries the plan out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bati.data import store
from bati.envs import Task, TaskFamily, TaskSplit

N_TRAIN = 20
N_TEST = 20
OTHER_FRACTION = 0.1
PLAN_STREAM = 0xDA7A  # separates the plan's random stream from split_tasks(seed)'s
TIES_STREAM = 0x71E5  # the draws among tied collectors: a plan without ties consumes none of the plan's stream
TIES = ("first", "drawn")


def n_minority(n: int) -> int:
    """The "10%" of a mixture: round(0.1 n) episodes, at least 1."""
    return max(1, round(OTHER_FRACTION * n))


@dataclass
class DatasetPlan:
    name: str  # Minari dataset id, e.g. "train-03-v0"
    split: str  # "train" | "p_test" | "p_train"
    task_index: int  # index into the split's tasks (train tasks for "train", test tasks otherwise)
    task: Task
    collectors: np.ndarray  # (E,) index of the training task whose expert collects each episode
    reset_seeds: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


@dataclass
class Plan:
    train_tasks: list
    test_tasks: list
    datasets: list[DatasetPlan]
    most_different: list[int]  # per test task: index of the most different training task (the first on ties)
    most_similar: list[int]
    ties: str = "first"  # how an episode's collector is picked among tied training tasks (TIES)

    @property
    def n_episodes(self) -> int:
        return sum(len(d.collectors) for d in self.datasets)


def tied(family: TaskFamily, task: Task, candidates: list, farthest: bool) -> np.ndarray:
    """Indices of the candidates at the largest (`farthest`) or smallest distance from `task`, in order."""
    distances = np.array([family.distance(task, c) for c in candidates])
    return np.flatnonzero(distances == (distances.max() if farthest else distances.min()))


def make_plan(family: TaskFamily, seed: int, n_episodes: int, n_context_episodes: int,
              tasks: TaskSplit | None = None, ties: str = "first") -> Plan:
    """The Eq. 9 / Eq. 10 assignment of collectors to episodes, reproducibly from `seed`; `tasks`
    picks the training and test tasks (default: 20 + 20 from `family.split_tasks(seed)`); `ties`: the first
    of tied collectors for every episode, or one drawn per episode (module docstring)."""
    if ties not in TIES:
        raise ValueError(f"ties={ties!r}: choose one of {', '.join(TIES)}")
    if n_episodes < 2:
        raise ValueError(f"n_episodes={n_episodes}: Eq. 9 needs at least 2 episodes per training task")
    if n_context_episodes < 1 or (family.kind == "dynamics" and n_context_episodes < 2):
        raise ValueError(f"n_context_episodes={n_context_episodes} is too small for {family.name}")
    train, test = (tasks or TaskSplit(N_TRAIN, N_TEST)).draw(family, seed)
    rng = np.random.default_rng([seed, PLAN_STREAM])
    datasets = []
    for i, task in enumerate(train):
        n_other = n_minority(n_episodes)
        others = np.array([j for j in range(len(train)) if j != i])
        collectors = np.concatenate([np.full(n_episodes - n_other, i), rng.choice(others, n_other)])
        name = store.dataset_name("train", i)
        datasets.append(DatasetPlan(name, "train", i, task, rng.permutation(collectors)))
    most_different = [family.most_different(task, train) for task in test]
    most_similar = [family.most_similar(task, train) for task in test]
    tie_rng = np.random.default_rng([seed, PLAN_STREAM, TIES_STREAM])

    def collectors_of(task, n: int, farthest: bool) -> np.ndarray:
        candidates = tied(family, task, train, farthest)
        if ties == "first" or len(candidates) == 1:
            return np.full(n, candidates[0])
        return tie_rng.choice(candidates, n)

    for j, task in enumerate(test):
        collectors = collectors_of(task, n_context_episodes, farthest=True)
        if family.kind == "dynamics":  # keep p_test supported by p_train (App. C.2)
            k = n_minority(n_context_episodes)
            collectors[:k] = collectors_of(task, k, farthest=False)
        name = store.dataset_name("p_test", j)
        datasets.append(DatasetPlan(name, "p_test", j, task, rng.permutation(collectors)))
    for j, task in enumerate(test):
        collectors = collectors_of(task, n_context_episodes, farthest=False)
        datasets.append(DatasetPlan(store.dataset_name("p_train", j), "p_train", j, task, collectors))
    # one distinct env reset seed per episode of the collection
    first = int(rng.integers(0, 2**31 - 1 - 10**8))
    start = 0
    for d in datasets:
        d.collectors = d.collectors.astype(np.int64)
        d.reset_seeds = first + start + np.arange(len(d.collectors), dtype=np.int64)
        start += len(d.collectors)
    return Plan(train, test, datasets, most_different, most_similar, ties)
