"""A user's own multi-task offline data: Minari datasets read into bati's training layout.

`bati train --datasets ID [ID ...]` trains on them instead of a family's collection (docs/own-data.md):

- tasks: each dataset is one task, or (`task_key`) the episodes of all datasets are grouped by the value
  of that key in each episode's Minari `options` (what `env.reset(options=...)` was given);
- episodes of any length, terminations honoured: each episode is cut into segments of `segment_length`
  transitions ending where the episode ends (a context never spans two episodes); the shorter
  remainder at an episode's start and episodes shorter than a segment are dropped, and the counts are
  recorded; a transition where the episode terminated keeps its terminal flag, so IQL does not
  bootstrap past it;
- a share `held_out` of each task's segments (at least one) is kept out of training for the offline
  diagnostics (`bati.evaluate.OfflineEvaluator`: task-inference accuracy on held-out contexts and the
  representation loss on held-out data);
- returns are measured only when the user names their env (`eval_env`, with `task_key`): the policy acts
  in it on each held-out context's inferred latent, the env told its task as the data recorded it,
  `reset(options={task_key: value})` (`TaskOptions`). Without one, no returns are measured.

Tasks hold different numbers of segments: each task's arrays are padded to the largest, and the
samplers draw only from each task's valid part (`TaskData.counts`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import jax.numpy as jnp
import numpy as np

from bati.data.batch import FamilyData, TaskData
from bati.data.store import DatasetError, DatasetNotFoundError
from bati.envs import FamilyRecord, TaskFamily, get_family
from bati.errors import BatiError

OWN_FAMILY = "own"
"""TrainConfig.family of a run on a user's own datasets (no env: offline diagnostics only)."""


def own_record(segment_length: int) -> FamilyRecord:
    """The record of a user's data: the reward families' Table 3 sizes, the given segment length."""
    return FamilyRecord(name=OWN_FAMILY, task_space="a task of your datasets (one-hot by task index)", task_dim=1,
                        default_noise=0.0, max_noise=0.0, noise_meaning="none (your data is as it was recorded)",
                        episode_length=segment_length, context_length=segment_length)


class OwnFamily(TaskFamily):
    """What bati knows of a user's data as a family: its record (segments of `segment_length`) and task
    labels, told apart by identity (distance 0 or 1). Its env is the user's `eval_env` (a gymnasium id),
    told its task through reset options; without one it has none."""

    record = own_record(200)

    def __init__(self, segment_length: int = 200, eval_env: str | None = None, task_key: str | None = None):
        self.record = own_record(segment_length)
        self.eval_env, self.task_key = eval_env, task_key

    def _sample(self, n, rng):
        raise TypeError("your own data's tasks are its datasets' (or --task-key's): none can be sampled")

    def _check(self, task):
        return task

    def distance(self, a, b):
        return float(a != b)

    def make_env(self, task, noise=None, **kwargs):
        if self.eval_env is None:
            raise TypeError("your own data comes without an env: runs on it report offline diagnostics only "
                            "(give --eval-env to measure returns)")
        return TaskOptions(gym.make(self.eval_env, **kwargs), self.task_key, task)


class TaskOptions(gym.Wrapper):
    """A user's env told its task the way their data recorded it: `reset(options={task_key: value})`,
    where the task is the JSON label `read_episodes` made of that value."""

    def __init__(self, env: gym.Env, task_key: str, task: str):
        super().__init__(env)
        self.task_key = task_key
        self.set_task(task)

    def set_task(self, task: str) -> None:
        self.task, self._value = task, json.loads(task)

    def reset(self, *, seed=None, options=None):
        return self.env.reset(seed=seed, options={**(options or {}), self.task_key: self._value})


def family_of(name: str, context_length: int | None = None) -> TaskFamily:
    """The family called `name`; for `own` (a user's datasets) a family-like holder of its record, whose
    episodes are segments of `context_length` transitions (default 200)."""
    if name != OWN_FAMILY:
        return get_family(name)
    return OwnFamily(context_length or 200)


def check_eval_env(eval_env: str, task_key: str | None) -> int:
    """The episode length of the user's env `eval_env` (its time limit); EnvError (one line) if it cannot be
    made, has no time limit, or cannot be told its task (no --task-key)."""
    if task_key is None:
        raise EnvError("--eval-env needs --task-key: the env is told each task by reset(options={KEY: value}), "
                       "as your data recorded it")
    try:
        env = gym.make(eval_env)
    except Exception as err:  # an unknown id, a module that does not import, the env's own error
        raise EnvError(f"--eval-env {eval_env!r} cannot be made ({type(err).__name__}: {err}); give a registered "
                       "gymnasium id, or 'package.module:Env-v0' to import its module first") from err
    limit = env.spec.max_episode_steps if env.spec is not None else None
    env.close()
    if not limit:
        raise EnvError(f"--eval-env {eval_env!r} has no time limit: register it with max_episode_steps")
    return int(limit)


class EnvError(BatiError, ValueError):
    """The user's --eval-env cannot serve the evaluation (one line; nothing was done)."""


@dataclass
class OwnData(FamilyData):
    """FamilyData of a user's datasets: `train` and `held_out` segments of the same tasks, no test tasks."""

    held_out: TaskData | None = None


def check_own_data(datasets: tuple[str, ...], eval_env: str | None, task_key: str | None) -> None:
    """Your own data checked before any work (one line): every dataset at hand (DatasetNotFoundError), the env to
    evaluate in, if given, made (EnvError)."""
    for dataset in datasets:
        dataset_path(dataset)
    if eval_env is not None:
        check_eval_env(eval_env, task_key)


def dataset_path(dataset: str) -> Path:
    """Where a dataset given by directory or by Minari id lives; DatasetNotFoundError (one line) if nowhere."""
    import os

    path = Path(dataset)
    if path.is_dir():
        return path
    root = Path(os.environ.get("MINARI_DATASETS_PATH", Path.home() / ".minari" / "datasets"))
    if (root / dataset).is_dir():
        return root / dataset
    raise DatasetNotFoundError(f"no Minari dataset {dataset!r} (neither a dataset directory nor an id under "
                               f"{root}; MINARI_DATASETS_PATH sets that root)")


def _open(dataset: str):
    """A Minari dataset by id (under MINARI_DATASETS_PATH) or by directory (the one holding data/)."""
    import minari

    path = dataset_path(dataset)
    try:
        return minari.MinariDataset(path / "data" if (path / "data").is_dir() else path)
    except Exception as err:  # h5py / json / Minari errors on a damaged or foreign file
        raise DatasetError(f"cannot read the Minari dataset {dataset!r} ({type(err).__name__}: {err})") from err


def _task_label(options: dict, task_key: str, dataset: str, episode: int):
    if task_key not in options:
        raise DatasetError(f"{dataset}: episode {episode} has no {task_key!r} in its options "
                           f"(it has: {', '.join(sorted(options)) or 'none'}); give another --task-key")
    return json.dumps(options[task_key], sort_keys=True, default=str)


EPISODE_FIELDS = ("observations", "actions", "rewards", "terminations")


def _checked_episode(episode, dataset: str, index: int, spaces: tuple) -> dict:
    """One episode's arrays, or DatasetError naming the dataset and the episode: every field present, T >= 1
    transitions with T + 1 observations, the dataset's shapes, finite numbers."""
    where = f"{dataset}: episode {index}"
    try:
        raw = {name: np.asarray(episode[name]) for name in EPISODE_FIELDS}
    except (KeyError, TypeError) as err:
        raise DatasetError(f"{where} lacks {err} (an episode holds {', '.join(EPISODE_FIELDS)})") from err
    steps = raw["actions"].shape[0] if raw["actions"].ndim else 0
    expected = {"observations": (steps + 1,) + spaces[0], "actions": (steps,) + spaces[1],
                "rewards": (steps,), "terminations": (steps,)}
    for name, shape in expected.items():
        if raw[name].reshape(-1).shape == (steps,) and name in ("rewards", "terminations"):
            continue  # (T,) or (T, 1)
        if raw[name].shape != shape:
            raise DatasetError(f"{where}: {name} has shape {raw[name].shape}, expected {shape} ({steps} transitions; "
                               "a truncated or short episode?)")
    if steps < 1:
        raise DatasetError(f"{where} has no transitions")
    arrays = {"observations": raw["observations"].astype(np.float32), "actions": raw["actions"].astype(np.float32),
              "rewards": raw["rewards"].astype(np.float32).reshape(-1),
              "terminations": raw["terminations"].astype(bool).reshape(-1)}
    for name in ("observations", "actions", "rewards"):
        if not np.all(np.isfinite(arrays[name])):
            raise DatasetError(f"{where}: {name} holds NaN or infinite values")
    return arrays


def dataset_fingerprint(datasets: tuple[str, ...]) -> dict[str, str]:
    """Each dataset's sha256 over its files (names and bytes): what a run on it records, so that a dataset
    edited before a resume is noticed."""
    import hashlib

    prints = {}
    for dataset in dict.fromkeys(datasets):
        digest, root = hashlib.sha256(), dataset_path(dataset)
        for file in sorted(p for p in root.rglob("*") if p.is_file()):
            digest.update(str(file.relative_to(root)).encode())
            with open(file, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    digest.update(block)
        prints[dataset] = digest.hexdigest()
    return prints


def read_episodes(datasets: tuple[str, ...], task_key: str | None) -> tuple[list[str], list[list[dict]]]:
    """(task labels, per task its episodes as dicts of arrays), tasks in a stable order."""
    if not datasets:
        raise ValueError("--datasets needs at least one Minari dataset")
    grouped: dict[str, list[dict]] = {}
    shapes = None
    for dataset in dict.fromkeys(datasets):
        data = _open(dataset)
        storage = data.storage
        spaces = (tuple(storage.observation_space.shape or ()), tuple(storage.action_space.shape or ()))
        if len(spaces[0]) != 1 or len(spaces[1]) != 1:
            raise DatasetError(f"{dataset}: observations {spaces[0]} and actions {spaces[1]} must be flat Box "
                               "vectors (bati's networks read vectors)")
        if shapes not in (None, spaces):
            raise DatasetError(f"{dataset}: observation/action shapes {spaces} differ from the other datasets' {shapes}")
        shapes = spaces
        indices = range(storage.total_episodes)
        metadata = list(storage.get_episode_metadata(indices))
        try:
            episodes = list(storage.get_episodes(indices))
        except Exception as err:  # a truncated or damaged file, a missing field: name the episode
            for index in indices:
                try:
                    list(storage.get_episodes([index]))
                except Exception as one:
                    raise DatasetError(f"{dataset}: episode {index} cannot be read ({type(one).__name__}: "
                                       f"{one})") from one
            raise DatasetError(f"{dataset}: its episodes cannot be read ({type(err).__name__}: {err})") from err
        for e, (episode, meta) in enumerate(zip(episodes, metadata)):
            label = dataset if task_key is None else _task_label(meta.get("options") or {}, task_key, dataset, e)
            grouped.setdefault(label, []).append(_checked_episode(episode, dataset, e, spaces))
    labels = sorted(grouped) if task_key is not None else list(grouped)
    if len(labels) < 2:
        raise DatasetError(f"{len(labels)} task in {', '.join(datasets)}: task inference needs at least 2 tasks "
                           "(one dataset per task, or --task-key naming the episodes' task)")
    return labels, [grouped[label] for label in labels]


def segments(episodes: list[dict], length: int) -> dict[str, np.ndarray]:
    """Each episode cut into segments of `length` transitions, concatenated. The segments end where the
    episode ends, so a terminal transition is always kept; the remainder dropped is the episode's start."""
    parts: dict[str, list] = {k: [] for k in ("observations", "actions", "rewards", "next_observations", "terminals")}
    for episode in episodes:
        total = len(episode["rewards"])
        first = total % length
        if total < length:
            continue
        obs = episode["observations"]
        parts["observations"].append(obs[first:total])
        parts["next_observations"].append(obs[first + 1:total + 1])
        parts["actions"].append(episode["actions"][first:])
        parts["rewards"].append(episode["rewards"][first:])
        parts["terminals"].append(episode["terminations"][first:].astype(np.float32))
    return {k: np.concatenate(v) if v else np.zeros((0,)) for k, v in parts.items()}


def load_own_data(datasets: tuple[str, ...], task_key: str | None, segment_length: int, held_out: float,
                  seed: int = 0) -> OwnData:
    """The datasets' tasks as training and held-out segments (see the module docstring)."""
    if not 0.0 < held_out < 1.0:
        raise ValueError(f"held_out must be in (0, 1), got {held_out!r}")
    labels, per_task = read_episodes(tuple(datasets), task_key)
    rng = np.random.default_rng(seed)
    train_parts, held_parts, report = [], [], {"tasks": [], "transitions_read": 0, "transitions_kept": 0}
    for label, episodes in zip(labels, per_task):
        cut = segments(episodes, segment_length)
        n_seg = len(cut["rewards"]) // segment_length
        read = sum(len(e["rewards"]) for e in episodes)
        report["transitions_read"] += read
        report["transitions_kept"] += n_seg * segment_length
        if n_seg < 2:
            raise DatasetError(f"task {label}: {n_seg} segment(s) of {segment_length} transitions in {read} "
                               "transitions; it needs 2 (one to train, one held out): give a shorter "
                               "--context-length or more episodes")
        order = rng.permutation(n_seg)
        n_held = min(max(1, round(held_out * n_seg)), n_seg - 1)
        pick = lambda which: {k: v.reshape((n_seg, segment_length) + v.shape[1:])[np.sort(which)].reshape(  # noqa: E731
            (-1,) + v.shape[1:]) for k, v in cut.items()}
        train_parts.append(pick(order[n_held:]))
        held_parts.append(pick(order[:n_held]))
        report["tasks"].append({"task": label, "episodes": len(episodes), "segments": n_seg, "held_out": n_held,
                                "episode_return_mean": float(np.mean([e["rewards"].sum() for e in episodes]))})
    obs_dim, action_dim = train_parts[0]["observations"].shape[-1], train_parts[0]["actions"].shape[-1]
    n_tasks = len(labels)
    task_arrays = np.eye(n_tasks, dtype=np.float32)
    manifest = {"datasets": list(datasets), "fingerprint": dataset_fingerprint(tuple(datasets)),
                "task_key": task_key, "segment_length": segment_length,
                "held_out": held_out, **report, "transitions": report["transitions_kept"],
                "n_episodes": None, "n_context_episodes": None}
    return OwnData(
        family=OWN_FAMILY, scale="own", seed=seed, noise=0.0, train_tasks=labels, test_tasks=[],
        train_task_arrays=task_arrays, test_task_arrays=np.zeros((0, n_tasks), np.float32),
        train=_padded(train_parts, segment_length), p_test=None, p_train=None,
        obs_dim=int(obs_dim), action_dim=int(action_dim), task_dim=n_tasks, path=None, manifest=manifest,
        held_out=_padded(held_parts, segment_length),
    )


def _padded(parts: list[dict], segment_length: int) -> TaskData:
    """Per-task arrays padded (with each task's first transitions) to the longest task; counts mark the valid part."""
    longest = max(len(p["rewards"]) for p in parts)

    def pad(v):
        reps = -(-longest // len(v))
        return np.concatenate([v] * reps)[:longest]

    stacked = {k: np.stack([pad(p[k]) for p in parts]) for k in parts[0]}
    counts = np.array([len(p["rewards"]) for p in parts], np.int32)
    collector = np.broadcast_to(np.arange(len(parts), dtype=np.int32)[:, None], stacked["rewards"].shape)
    return TaskData(observations=jnp.asarray(stacked["observations"]), actions=jnp.asarray(stacked["actions"]),
                    rewards=jnp.asarray(stacked["rewards"]), next_observations=jnp.asarray(stacked["next_observations"]),
                    collector=jnp.asarray(collector), episode_length=segment_length,
                    terminals=jnp.asarray(stacked["terminals"]), counts=jnp.asarray(counts))
