"""Build a family's offline datasets (Eq. 9) and test-time context data (Eq. 10).

For the split `train, test = family.split_tasks(seed)` (20 + 20 tasks):

- ``train-i``: the offline dataset of training task i. n_episodes episodes in task i; 10% of them
  (round(0.1 n), at least 1) are collected by the experts of other training tasks, each drawn
  uniformly among the other 19, and the rest by the expert for task i (Eq. 9).
- ``p_test-j``: context data of test task j, collected in task j by the expert of the training
  task most different from j (Eq. 10). For dynamics families (HopperParam, WalkerParam) 10%
  (at least 1 episode) come from the expert of the most similar training task instead (App. C.2).
- ``p_train-j``: context data of test task j collected by the expert of the most similar training
  task (the "primary" context collector of App. C.2).

"The expert for task M" is the family's task-conditioned SAC conditioned on M's parameters
(design deviation: one expert per family). Experts act stochastically; every episode is run in
the family's env with its default eps (or `noise`). All episodes are stepped in lockstep chunks
(one batched expert call per step) and each dataset is written as soon as its episodes are done.
"""

from __future__ import annotations

import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bati.data import store
from bati.envs import EPISODE_LENGTH, Task, TaskFamily, get_family
from bati.io import atomic_write_json, git_commit

N_TRAIN = 20
N_TEST = 20
OTHER_FRACTION = 0.1
# Episodes per task. `paper`: App. C Table 3 "Dataset Size" read as transitions PER TASK
# (AntDir 1e5 = 500 episodes of 200 steps, HalfCheetah 2e5 = 1000, Hopper/Walker 3e5 = 1500).
SCALES: dict[str, dict[str, Any]] = {
    "quick": {"n_episodes": 20, "n_context_episodes": 5},
    "paper": {
        "n_episodes": {"AntDir": 500, "HalfCheetahVel": 1000, "HalfCheetahDir": 1000, "HopperParam": 1500,
                       "WalkerParam": 1500, "PointGoal": 500},
        "n_context_episodes": 20,
    },
}
CHUNK = 256  # envs stepped in lockstep (fixed: the stochastic actions depend on it)
_PLAN_STREAM = 0xDA7A  # separates the plan's random stream from split_tasks(seed)'s


def scale_sizes(family: str, scale: str) -> tuple[int, int]:
    """(n_episodes per training task, n_context_episodes per test task) of a scale."""
    if scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; choose one of: {', '.join(SCALES)}")
    sizes = SCALES[scale]
    n = sizes["n_episodes"]
    return int(n[family] if isinstance(n, dict) else n), int(sizes["n_context_episodes"])


def n_minority(n: int) -> int:
    """The "10%" of a mixture: round(0.1 n) episodes, at least 1."""
    return max(1, round(OTHER_FRACTION * n))


# --- the plan: who collects which episode ----------------------------------------------------
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


def make_plan(family: TaskFamily, seed: int, n_episodes: int, n_context_episodes: int) -> Plan:
    """The Eq. 9 / Eq. 10 assignment of collectors to episodes, reproducibly from `seed`."""
    if n_episodes < 2:
        raise ValueError(f"n_episodes={n_episodes}: Eq. 9 needs at least 2 episodes per training task")
    if n_context_episodes < 1 or (family.kind == "dynamics" and n_context_episodes < 2):
        raise ValueError(f"n_context_episodes={n_context_episodes} is too small for {family.name}")
    train, test = family.split_tasks(seed, N_TRAIN, N_TEST)
    rng = np.random.default_rng([seed, _PLAN_STREAM])
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


# --- collection -------------------------------------------------------------------------------
@dataclass
class CollectResult:
    path: Path
    manifest: dict
    cached: bool  # True when the collection was already on disk
    wall_time_s: float


def collect(
    family: str,
    scale: str = "quick",
    seed: int = 0,
    noise: float | None = None,
    root: str | Path = store.DEFAULT_ROOT,
    *,
    n_episodes: int | None = None,
    n_context_episodes: int | None = None,
    zoo_dir: str | Path | None = None,
    progress: bool = True,
) -> CollectResult:
    """Collect (or find cached) the datasets of `family` under `<root>/<Family>/<scale>-seed<S>-eps<eps>`.

    `n_episodes` / `n_context_episodes` override the scale's sizes (for tests and experiments);
    `zoo_dir` is where the expert is loaded from (default: the package zoo).
    """
    start = time.perf_counter()
    fam = get_family(family)
    noise = fam.validate_noise(noise)
    default_n, default_ctx = scale_sizes(family, scale)
    n_episodes = default_n if n_episodes is None else int(n_episodes)
    n_context_episodes = default_ctx if n_context_episodes is None else int(n_context_episodes)
    target = store.collection_dir(root, family, scale, seed, noise)

    cached = _cached(target, fam, scale, seed, noise, root, n_episodes, n_context_episodes)
    if cached is not None:
        return CollectResult(target, cached, True, time.perf_counter() - start)

    plan = make_plan(fam, seed, n_episodes, n_context_episodes)
    load_start = time.perf_counter()
    expert = load_expert(family, zoo_dir)  # FileNotFoundError naming `bati experts train --family X`
    timings = {"expert_load_s": time.perf_counter() - load_start}
    probe = fam.make_env(plan.train_tasks[0], noise)
    obs_dim, action_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    probe.close()
    if (expert.meta["obs_dim"], expert.meta["action_dim"]) != (obs_dim, action_dim):
        raise ValueError(
            f"the {family} expert reads obs_dim={expert.meta['obs_dim']} / writes action_dim="
            f"{expert.meta['action_dim']}, but the env has {obs_dim} / {action_dim}; retrain it with "
            f"`bati experts train --family {family}`"
        )

    target.parent.mkdir(parents=True, exist_ok=True)
    store.remove_stale_partials(target)
    cached = _cached(target, fam, scale, seed, noise, root, n_episodes, n_context_episodes)
    if cached is not None:  # another process finished the same collection meanwhile
        return CollectResult(target, cached, True, time.perf_counter() - start)
    if target.exists():  # no manifest: an incomplete or foreign directory; start over
        stale = store.partial_dir(target)
        target.rename(stale)
        shutil.rmtree(stale, ignore_errors=True)
    tmp = store.partial_dir(target)
    tmp.mkdir()
    try:
        commit = git_commit()
        collection_id = uuid.uuid4().hex
        base_meta = {"family": family, "scale": scale, "seed": seed, "noise": noise, "commit": commit,
                     "collection_id": collection_id}
        timings.update(run_collection(fam, plan, expert, noise, seed, tmp, base_meta, progress=progress))
        manifest = {
            "format": store.FORMAT_VERSION,
            **base_meta,
            "n_episodes": n_episodes,
            "n_context_episodes": n_context_episodes,
            "episode_length": EPISODE_LENGTH,
            "obs_dim": obs_dim,
            "action_dim": action_dim,
            "task_dim": fam.task_dim,
            "kind": fam.kind,
            "train_tasks": plan.train_tasks,
            "test_tasks": plan.test_tasks,
            "p_test_most_different": plan.most_different,
            "p_train_most_similar": plan.most_similar,
            "datasets": {s: [d.name for d in plan.datasets if d.split == s] for s in store.SPLITS},
            "transitions": plan.n_episodes * EPISODE_LENGTH,
            "expert": {"train_steps": expert.meta.get("train_steps"), "seed": expert.meta.get("seed")},
            "collect_wall_time_s": round(time.perf_counter() - start, 2),
            "timings_s": {k: round(v, 2) for k, v in timings.items()},
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": store.collect_command(fam, scale, seed, noise, root),
        }
        atomic_write_json(tmp / store.MANIFEST, manifest)  # written last
        try:
            tmp.rename(target)
        except OSError:  # a concurrent collection finished first: keep its (identical) data
            existing = _cached(target, fam, scale, seed, noise, root, n_episodes, n_context_episodes)
            if existing is None:
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return CollectResult(target, existing, True, time.perf_counter() - start)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return CollectResult(target, manifest, False, time.perf_counter() - start)


_EXPERTS: dict[tuple, Any] = {}


def load_expert(family: str, zoo_dir: str | Path | None = None):
    """`bati.experts.load`, memoised per process while the expert's files are unchanged."""
    from bati.experts import load
    from bati.experts.zoo import ZOO_DIR

    directory = Path(zoo_dir or ZOO_DIR) / family
    try:
        stamp = tuple((directory / name).stat().st_mtime_ns for name in ("expert.json", "actor.msgpack"))
    except OSError:
        return load(family, zoo_dir)  # raises the zoo's own error (e.g. no expert for the family)
    key = (family, str(directory.resolve()), stamp)
    if key not in _EXPERTS:
        for stale in [k for k in _EXPERTS if k[:2] == key[:2]]:  # the expert was re-exported
            del _EXPERTS[stale]
        _EXPERTS[key] = load(family, zoo_dir)
    return _EXPERTS[key]


def _cached(target, fam, scale, seed, noise, root, n_episodes, n_context_episodes) -> dict | None:
    """The manifest of a complete collection at `target`, None if there is none."""
    if not (target / store.MANIFEST).is_file():
        return None
    manifest = store.read_manifest(target, fam, scale, seed, noise, root)
    sizes = (manifest.get("n_episodes"), manifest.get("n_context_episodes"))
    if sizes != (n_episodes, n_context_episodes):
        raise ValueError(
            f"{target} holds {sizes[0]} episodes per training task and {sizes[1]} per context dataset, "
            f"not the requested {n_episodes} / {n_context_episodes}; delete it or use another --root"
        )
    return manifest


def run_collection(
    family: TaskFamily,
    plan: Plan,
    expert,
    noise: float,
    seed: int,
    out_dir: Path,
    base_meta: dict,
    progress: bool = True,
) -> dict[str, float]:
    """Roll out every planned episode (lockstep chunks of CHUNK envs) and write the datasets.

    Returns wall times: rollout_s (envs + expert), write_s (Minari datasets).
    """
    import jax

    start, write_s = time.perf_counter(), 0.0

    jobs = [(d, e) for d in plan.datasets for e in range(len(d.collectors))]
    train_arrays = np.stack([family.task_to_array(t) for t in plan.train_tasks])
    n_jobs = len(jobs)
    pool: list = []
    buffers: dict[str, dict[str, list]] = {}
    base_key = jax.random.fold_in(jax.random.PRNGKey(seed), _PLAN_STREAM)

    bar = _progress(progress, f"{family.name} data")
    try:
        with bar:
            task_id = bar.add_task("collect", total=n_jobs * EPISODE_LENGTH)
            for chunk_index, first in enumerate(range(0, n_jobs, CHUNK)):
                chunk = jobs[first : first + CHUNK]
                while len(pool) < len(chunk):
                    pool.append(family.make_env(chunk[len(pool)][0].task, noise))
                envs = pool[: len(chunk)]
                policy_tasks = np.zeros((CHUNK, family.task_dim), np.float32)  # padded: one jit shape
                policy_tasks[: len(chunk)] = train_arrays[[d.collectors[e] for d, e in chunk]]
                obs = np.zeros((len(chunk), EPISODE_LENGTH + 1, envs[0].observation_space.shape[0]))
                actions = np.zeros((len(chunk), EPISODE_LENGTH, envs[0].action_space.shape[0]), np.float32)
                rewards = np.zeros((len(chunk), EPISODE_LENGTH), np.float32)
                for k, (env, (d, e)) in enumerate(zip(envs, chunk)):
                    env.unwrapped.set_task(d.task)
                    obs[k, 0] = env.reset(seed=int(d.reset_seeds[e]))[0]
                chunk_key = jax.random.fold_in(base_key, chunk_index)
                padded = np.zeros((CHUNK, obs.shape[-1]), np.float32)
                for t in range(EPISODE_LENGTH):
                    padded[: len(chunk)] = obs[:, t]
                    step_key = jax.random.fold_in(chunk_key, t)
                    act = expert.act_from_arrays(padded, policy_tasks, False, step_key)
                    actions[:, t] = act[: len(chunk)]
                    for k, env in enumerate(envs):
                        next_obs, reward, _, _, _ = env.step(actions[k, t])
                        obs[k, t + 1] = next_obs
                        rewards[k, t] = reward
                    bar.advance(task_id, len(chunk))
                for k, (d, e) in enumerate(chunk):
                    buf = buffers.setdefault(d.name, {"obs": [], "act": [], "rew": []})
                    buf["obs"].append(obs[k])
                    buf["act"].append(actions[k])
                    buf["rew"].append(rewards[k])
                for d in {d.name: d for d, _ in chunk}.values():
                    if len(buffers.get(d.name, {"obs": []})["obs"]) == len(d.collectors):
                        write_start = time.perf_counter()
                        _write(family, plan, d, buffers.pop(d.name), noise, out_dir, base_meta)
                        write_s += time.perf_counter() - write_start
    finally:
        for env in pool:
            env.close()
    return {"rollout_s": time.perf_counter() - start - write_s, "write_s": write_s}


def _write(family: TaskFamily, plan: Plan, d: DatasetPlan, buf: dict, noise: float, out_dir: Path,
           base_meta: dict) -> None:
    options = [
        {
            "split": d.split,
            "task": d.task,
            "task_index": d.task_index,
            "collector": int(c),
            "collector_task": plan.train_tasks[int(c)],
        }
        for c in d.collectors
    ]
    descriptions = {
        "train": "Eq. 9 offline dataset of training task {i}: 90% expert for the task, "
        "10% experts of other training tasks",
        "p_test": "Eq. 10 context data of test task {i}: expert of the most different training task"
        + (" (10% most similar, App. C.2)" if family.kind == "dynamics" else ""),
        "p_train": "p_train-style context data of test task {i}: expert of the most similar training task",
    }
    metadata = {
        **base_meta,
        "split": d.split,
        "task_index": d.task_index,
        "task": d.task,
        "task_array": family.task_to_array(d.task).tolist(),
        "collectors": d.collectors.tolist(),
        "description": descriptions[d.split].format(i=d.task_index),
    }
    store.write_dataset(
        out_dir, d.name, family, d.task, noise,
        np.stack(buf["obs"]), np.stack(buf["act"]), np.stack(buf["rew"]),
        options, d.reset_seeds.tolist(), metadata,
    )


class _NoProgress:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, *args, **kwargs):
        return 0

    def advance(self, *args, **kwargs):
        pass


def _progress(enabled: bool, description: str):
    if not enabled:
        return _NoProgress()
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn(description),
        BarColumn(bar_width=24),
        MofNCompleteColumn(),
        TextColumn("transitions"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
    )
