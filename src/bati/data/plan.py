"""The Eq. 9 / Eq. 10 plan of a collection: which expert collects each episode of each dataset.

For the split `train, test = family.split_tasks(seed)` (20 + 20 tasks): training task i's dataset is
90% its own expert's episodes and 10% (at least 1) those of experts of other training tasks; test task
j's p_test contexts come from the expert of the training task most different from j (dynamics
families: 10% from the most similar one, App. C.2) and its p_train contexts from the most similar one.
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
    most_different: list[int]  # per test task: index of the most different training task
    most_similar: list[int]

    @property
    def n_episodes(self) -> int:
        return sum(len(d.collectors) for d in self.datasets)


def make_plan(family: TaskFamily, seed: int, n_episodes: int, n_context_episodes: int,
              tasks: TaskSplit | None = None) -> Plan:
    """The Eq. 9 / Eq. 10 assignment of collectors to episodes, reproducibly from `seed`; `tasks`
    picks the training and test tasks (default: 20 + 20 from `family.split_tasks(seed)`)."""
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
    for j, task in enumerate(test):
        collectors = np.full(n_context_episodes, most_different[j])
        if family.kind == "dynamics":  # keep p_test supported by p_train (App. C.2)
            collectors[: n_minority(n_context_episodes)] = most_similar[j]
        name = store.dataset_name("p_test", j)
        datasets.append(DatasetPlan(name, "p_test", j, task, rng.permutation(collectors)))
    for j, task in enumerate(test):
        collectors = np.full(n_context_episodes, most_similar[j])
        datasets.append(DatasetPlan(store.dataset_name("p_train", j), "p_train", j, task, collectors))
    # one distinct env reset seed per episode of the collection
    first = int(rng.integers(0, 2**31 - 1 - 10**8))
    start = 0
    for d in datasets:
        d.collectors = d.collectors.astype(np.int64)
        d.reset_seeds = first + start + np.arange(len(d.collectors), dtype=np.int64)
        start += len(d.collectors)
    return Plan(train, test, datasets, most_different, most_similar)
