"""A collection as flat jax arrays, and jittable samplers of training batches and contexts.

>>> data = ensure_family_data("PointGoal", scale="quick", seed=0)   # collects if missing
>>> batch = sample_batch(data.train, key, task_batch=16, batch_size=256)
>>> ctx = sample_contexts(data.p_test, key, jnp.arange(20), length=50)

The Minari datasets are read once (Minari's per-episode reads are slow) and cached as
`arrays.npz` next to the manifest. Every task of a split has the same number n of transitions,
stored episode after episode (n = episodes x 200), so `observations[k, e * 200 + t]` is step t
of episode e of task k.
"""

from __future__ import annotations

import functools
import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import flax
import jax
import jax.numpy as jnp
import numpy as np

from bati.data import store
from bati.errors import BatiWarning
from bati.envs import EPISODE_LENGTH, TaskFamily, TaskSplit, as_family
from bati.experts.kinds import ExpertsKind, family_experts

TRANSITION_FIELDS = ("observations", "actions", "rewards", "next_observations")
FIELDS = TRANSITION_FIELDS + ("collector",)


@flax.struct.dataclass
class TaskData:
    """Transitions of n_tasks tasks, n per task (jax arrays; episodes are contiguous blocks)."""

    observations: jax.Array  # (n_tasks, n, obs_dim) float32
    actions: jax.Array  # (n_tasks, n, action_dim) float32
    rewards: jax.Array  # (n_tasks, n) float32
    next_observations: jax.Array  # (n_tasks, n, obs_dim) float32
    collector: jax.Array  # (n_tasks, n) int32: training task whose expert collected the transition
    episode_length: int = flax.struct.field(pytree_node=False, default=EPISODE_LENGTH)
    terminals: jax.Array | None = None
    """(n_tasks, n) float32: 1 where the episode terminated at this transition (a user's own data,
    `bati.data.own`); None: episodes end only by their time limit (every transition bootstraps)."""
    counts: jax.Array | None = None
    """(n_tasks,) int32: valid transitions of each task, a multiple of episode_length, the rest padding
    (a user's own data, whose tasks hold different amounts); None: all n are valid."""

    @property
    def n_tasks(self) -> int:
        return self.rewards.shape[0]

    @property
    def n_transitions(self) -> int:
        """Transitions per task."""
        return self.rewards.shape[1]

    @property
    def n_episodes(self) -> int:
        """Episodes per task."""
        return self.rewards.shape[1] // self.episode_length


@dataclass
class FamilyData:
    family: str
    scale: str
    seed: int
    noise: float
    train_tasks: list
    test_tasks: list
    train_task_arrays: np.ndarray  # (20, task_dim)
    test_task_arrays: np.ndarray  # (20, task_dim)
    train: TaskData  # Eq. 9 datasets of the training tasks
    p_test: TaskData  # Eq. 10 context data of the test tasks
    p_train: TaskData  # p_train-style context data of the test tasks
    obs_dim: int
    action_dim: int
    task_dim: int
    path: Path | None = None  # the collection directory
    manifest: dict = field(default_factory=dict)

    def fingerprint(self) -> str:
        """sha256 (16 hex digits) of the transitions a run trains and is evaluated on: the training data and
        both context sources, field by field. Two runs with the same fingerprint saw the same numbers; the same
        collection command gives other numbers on another CPU model (docs/reliability.md), and this says so."""
        digest = hashlib.sha256()
        for split in (self.train, self.p_test, self.p_train):
            for name in TRANSITION_FIELDS:
                value = np.ascontiguousarray(jax.device_get(getattr(split, name)))
                digest.update(f"{name}{value.shape}{value.dtype}".encode())
                digest.update(value.tobytes())
        return digest.hexdigest()[:16]


# --- samplers ----------------------------------------------------------------------------------
@functools.partial(jax.jit, static_argnames=("task_batch", "batch_size"))
def sample_batch(data: TaskData, key: jax.Array, task_batch: int, batch_size: int) -> dict:
    """`task_batch` distinct tasks, then `batch_size` transitions of each, uniformly.

    Returns task_ids (T,), observations (T, B, obs_dim), actions (T, B, action_dim),
    rewards (T, B), next_observations (T, B, obs_dim).
    """
    n_tasks, n = data.rewards.shape
    if not 0 < task_batch <= n_tasks:
        raise ValueError(
            f"task_batch={task_batch} must be in [1, {n_tasks}] (tasks are drawn without replacement)"
        )
    k_tasks, k_steps = jax.random.split(key)
    task_ids = jax.random.choice(k_tasks, n_tasks, (task_batch,), replace=False)
    if data.counts is None:
        steps = jax.random.randint(k_steps, (task_batch, batch_size), 0, n)
    else:  # uniform over each task's valid transitions
        steps = _uniform_below(k_steps, (task_batch, batch_size), data.counts[task_ids][:, None])
    rows = task_ids[:, None]
    batch = {
        "task_ids": task_ids,
        "observations": data.observations[rows, steps],
        "actions": data.actions[rows, steps],
        "rewards": data.rewards[rows, steps],
        "next_observations": data.next_observations[rows, steps],
    }
    if data.terminals is not None:
        batch["terminals"] = data.terminals[rows, steps]
    return batch


def _uniform_below(key: jax.Array, shape: tuple, high: jax.Array) -> jax.Array:
    """Integers uniform in [0, high) (high broadcast against `shape`, >= 1)."""
    return jnp.minimum(jnp.floor(jax.random.uniform(key, shape) * high), high - 1).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("length",))
def sample_contexts(data: TaskData, key: jax.Array, task_ids: jax.Array, length: int) -> dict:
    """For each task id, `length` consecutive transitions of that task's data.

    Up to one episode (length <= episode_length): the window's episode and start (0 ..
    episode_length - length) are uniform, so every window inside one episode is equally likely and a
    context never spans two episodes (whose collectors may differ). Longer contexts (Table 1's
    C = 400) are the first `length` steps of ceil(length / episode_length) consecutive episodes,
    the first of them uniform. Returns observations (K, C, obs_dim), actions, rewards (K, C),
    next_observations.
    """
    n = data.rewards.shape[1]
    n_episodes, episode_length = n // data.episode_length, data.episode_length
    spanned = -(-length // episode_length) if length > 0 else 0
    if length < 1 or spanned > n_episodes:
        raise ValueError(f"context length {length} must be in [1, {n_episodes * episode_length}] "
                         f"({n_episodes} episodes of {episode_length} steps per task)")
    k_episode, k_start = jax.random.split(key)
    shape = task_ids.shape
    if data.counts is None:
        episode = jax.random.randint(k_episode, shape, 0, n_episodes - spanned + 1)
    else:  # among each task's valid episodes (at least one: `bati.data.own` keeps no empty task)
        valid = data.counts[task_ids] // episode_length
        episode = _uniform_below(k_episode, shape, jnp.maximum(valid - spanned + 1, 1))
    start = jax.random.randint(k_start, shape, 0, max(episode_length - length, 0) + 1)
    steps = (episode * episode_length + start)[..., None] + jnp.arange(length)
    rows = task_ids[..., None]
    return {
        "observations": data.observations[rows, steps],
        "actions": data.actions[rows, steps],
        "rewards": data.rewards[rows, steps],
        "next_observations": data.next_observations[rows, steps],
    }


@functools.partial(jax.jit, static_argnames=("length",))
def sample_off_policy_contexts(data: TaskData, key: jax.Array, length: int) -> dict:
    """One context of `length` (<= an episode) per task from an episode of that task that ANOTHER
    task's expert collected (Eq. 9's 10% share): the task's dynamics and rewards under a foreign
    behaviour, as a p_test context has them. A task without such an episode gets one of its own."""
    n_episodes, episode_length = data.n_episodes, data.episode_length
    if not 1 <= length <= episode_length:
        raise ValueError(f"an off-policy context holds 1 to {episode_length} transitions, got {length}")
    firsts = data.collector[:, ::episode_length][:, :n_episodes]  # (n_tasks, n_episodes) collectors
    foreign = firsts != jnp.arange(data.n_tasks)[:, None]
    valid = True if data.counts is None else jnp.arange(n_episodes)[None] < (data.counts // episode_length)[:, None]
    foreign = foreign & valid
    foreign = jnp.where(foreign.any(axis=1, keepdims=True), foreign, valid)
    k_episode, k_start = jax.random.split(key)
    episode = jax.random.categorical(k_episode, jnp.where(foreign, 0.0, -jnp.inf), axis=1)
    start = jax.random.randint(k_start, episode.shape, 0, episode_length - length + 1)
    steps = (episode * episode_length + start)[:, None] + jnp.arange(length)
    rows = jnp.arange(data.n_tasks)[:, None]
    return {name: getattr(data, name)[rows, steps] for name in TRANSITION_FIELDS}


# --- loading -----------------------------------------------------------------------------------
def load_family_data(
    family: str | TaskFamily,
    scale: str = "quick",
    seed: int = 0,
    noise: float | None = None,
    root: str | Path = store.DEFAULT_ROOT,
    *,
    cache: bool = True,
    tasks: TaskSplit | None = None,
    experts: ExpertsKind | None = None,
) -> FamilyData:
    """Read a complete collection (see `bati data collect`) into flat arrays.

    Raises DatasetNotFoundError (with the collect command) if it is missing, DatasetError if a
    file is damaged or its shapes do not match the family's env.
    """
    fam = as_family(family)  # the caller's resolved family, or one looked up by name here
    family = fam.name
    noise = fam.validate_noise(noise)
    tasks = (tasks or TaskSplit()).checked(fam)
    experts = family_experts(fam, experts, seed, tasks)
    path = store.collection_dir(root, fam, scale, seed, noise, tasks, experts)
    manifest = store.read_manifest(path, fam, scale, seed, noise, root, tasks, experts)
    redo = store.collect_command(fam, scale, seed, noise, root, tasks, experts)
    store.require_intact(path, manifest, redo)  # sizes only (a stat per file): a truncated or missing file
    obs_dim, action_dim = store.require_env_dims(path, manifest, fam, noise)
    length = int(manifest.get("episode_length", EPISODE_LENGTH))

    arrays = _load_cache(path, manifest, obs_dim, action_dim) if cache else None
    if arrays is None:  # the datasets themselves are read: check every byte against the manifest first
        store.require_intact(path, manifest, redo, checksums=True)
        arrays = _read_minari(path, manifest, obs_dim, action_dim, length)
        if cache:
            try:
                collection_id = np.array(manifest["collection_id"])
                stamps = np.array(store.file_stamps(path, manifest))
                store.save_npz(path / store.ARRAY_CACHE, {"collection_id": collection_id, "source_stamps": stamps,
                                                          **arrays})
            except OSError as err:  # a read-only data directory is fine
                warnings.warn(f"could not write the array cache {path / store.ARRAY_CACHE}: {err}", BatiWarning)

    def task_data(split: str) -> TaskData:
        return TaskData(
            **{name: jnp.asarray(arrays[f"{split}__{name}"]) for name in FIELDS}, episode_length=length
        )

    train_tasks, test_tasks = manifest["train_tasks"], manifest["test_tasks"]
    return FamilyData(
        family=family,
        scale=scale,
        seed=seed,
        noise=noise,
        train_tasks=train_tasks,
        test_tasks=test_tasks,
        train_task_arrays=np.stack([fam.task_to_array(t) for t in train_tasks]),
        test_task_arrays=np.stack([fam.task_to_array(t) for t in test_tasks]),
        train=task_data("train"),
        p_test=task_data("p_test"),
        p_train=task_data("p_train"),
        obs_dim=obs_dim,
        action_dim=action_dim,
        task_dim=fam.task_dim,
        path=path,
        manifest=manifest,
    )


def ensure_family_data(
    family: str | TaskFamily,
    scale: str = "quick",
    seed: int = 0,
    noise: float | None = None,
    root: str | Path = store.DEFAULT_ROOT,
    *,
    n_episodes: int | None = None,
    n_context_episodes: int | None = None,
    zoo_dir: str | Path | None = None,
    progress: bool = True,
    cache: bool = True,
    workers: int | None = None,
    tasks: TaskSplit | None = None,
    experts: ExpertsKind | None = None,
) -> FamilyData:
    """Collect the data if it is not on disk yet (see `collect`; `workers`: its worker processes,
    default all cores), then load it."""
    from bati.data.collect import collect

    collect(family, scale, seed, noise, root, n_episodes=n_episodes, n_context_episodes=n_context_episodes,
            zoo_dir=zoo_dir, progress=progress, workers=workers, tasks=tasks, experts=experts)
    return load_family_data(family, scale, seed, noise, root, cache=cache, tasks=tasks, experts=experts)


@dataclass(frozen=True)
class Collection:
    """Which collection a run trains on, its family resolved (`TrainConfig.resolve`): what `load` reads and
    `ensure` collects first when it is missing. `n_episodes` / `n_context_episodes`: sizes other than the
    scale's (a collection of other sizes needs its own root)."""

    family: TaskFamily
    scale: str
    seed: int
    noise: float
    root: Path
    tasks: TaskSplit
    experts: ExpertsKind | None = None
    """Who collected it (default: the family's for these tasks, `family_experts`)."""
    n_episodes: int | None = None
    n_context_episodes: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "experts", family_experts(self.family, self.experts, self.seed, self.tasks))

    def load(self) -> FamilyData:
        """The collection as it is on disk (DatasetNotFoundError, with the collect command, if missing)."""
        return load_family_data(self.family, self.scale, self.seed, self.noise, self.root, tasks=self.tasks,
                                experts=self.experts)

    def collect(self, progress: bool = True, zoo_dir: str | Path | None = None, check_only: bool = False):
        """Collect it if it is not on disk yet (`bati.data.collect.collect`; `check_only`: only raise what
        collecting would raise before any work)."""
        from bati.data.collect import collect

        return collect(self.family, self.scale, self.seed, self.noise, self.root, n_episodes=self.n_episodes,
                       n_context_episodes=self.n_context_episodes, zoo_dir=zoo_dir, progress=progress,
                       tasks=self.tasks, experts=self.experts, check_only=check_only)

    @property
    def sizes(self) -> tuple[int, int]:
        """(episodes per training task, episodes per test task's context dataset): the given ones, else the
        scale's."""
        from bati.data.collect import scale_sizes

        default_n, default_ctx = scale_sizes(self.family, self.scale)
        return (default_n if self.n_episodes is None else self.n_episodes,
                default_ctx if self.n_context_episodes is None else self.n_context_episodes)

    def check_fits(self) -> None:
        """ValueError (one line) where its sizes cannot be held in memory or on the data root's disk
        (`bati.data.collect.check_fits`); nothing to check for a collection already on disk."""
        from bati.data.collect import check_fits

        if (store.collection_dir(self.root, self.family, self.scale, self.seed, self.noise, self.tasks, self.experts)
                / store.MANIFEST).is_file():
            return
        check_fits(self.family, *self.sizes, self.tasks, self.root)

    def check_context_length(self, setting: str, length: int) -> None:
        """ValueError (one line) where a context of `length` transitions is longer than a test task's context
        data, from which every context is cut."""
        episodes = self.sizes[1]
        held = episodes * self.family.record.episode_length
        if length > held:
            raise ValueError(f"{setting} ({length}) must be at most the {held:,} transitions of a test task's "
                             f"context data ({episodes} episodes of {self.family.record.episode_length}; more: "
                             "--context-episodes)")

    def ensure(self, progress: bool = True, zoo_dir: str | Path | None = None) -> FamilyData:
        """Collect it if missing, then load it."""
        self.collect(progress, zoo_dir)
        return self.load()


def _read_minari(path: Path, manifest: dict, obs_dim: int, action_dim: int, length: int) -> dict:
    arrays = {}
    n_train = len(manifest["train_tasks"])
    for split in store.SPLITS:
        names = manifest["datasets"][split]
        expected_episodes = manifest["n_episodes"] if split == "train" else manifest["n_context_episodes"]
        parts: dict[str, list] = {name: [] for name in FIELDS}
        for index, name in enumerate(names):
            episodes = store.read_dataset(path / name, obs_dim, action_dim, length)
            file = path / name / "data" / "main_data.hdf5"
            n_eps = episodes["rewards"].shape[0]
            if n_eps != expected_episodes:
                raise store.DatasetError(f"{file}: {n_eps} episodes, the manifest says {expected_episodes}")
            collectors = []
            for e, options in enumerate(episodes["options"]):
                if int(options.get("task_index", -1)) != index or options.get("split") != split:
                    raise store.DatasetError(f"{file}: episode {e} belongs to {options.get('split')} task "
                                             f"{options.get('task_index')}, not {split} task {index}")
                collector = int(options.get("collector", -1))
                if not 0 <= collector < n_train:
                    raise store.DatasetError(f"{file}: episode {e} has no valid collector ({collector})")
                collectors.append(collector)
            obs = episodes["observations"]
            parts["observations"].append(obs[:, :-1].reshape(-1, obs_dim))
            parts["next_observations"].append(obs[:, 1:].reshape(-1, obs_dim))
            parts["actions"].append(episodes["actions"].reshape(-1, action_dim))
            parts["rewards"].append(episodes["rewards"].reshape(-1))
            parts["collector"].append(np.repeat(np.asarray(collectors, np.int32), length))
        for name in FIELDS:
            arrays[f"{split}__{name}"] = np.stack(parts[name])
    return arrays


def _load_cache(path: Path, manifest: dict, obs_dim: int, action_dim: int) -> dict | None:
    """The cached arrays if they belong to this collection and look sane, else None."""
    file = path / store.ARRAY_CACHE
    if not file.is_file():
        return None
    try:
        with np.load(file) as npz:
            if str(npz["collection_id"]) != manifest["collection_id"]:
                return None
            if store.has_checksums(manifest) and ("source_stamps" not in npz.files
                                                  or str(npz["source_stamps"]) != store.file_stamps(path, manifest)):
                warnings.warn(f"{file} was built from other files than {path} holds now (a dataset changed, or "
                              "the cache predates this check); rebuilding it after checking every file",
                              BatiWarning)
                return None
            arrays = {key: npz[key] for key in npz.files if key not in ("collection_id", "source_stamps")}
    except Exception as err:  # damaged cache (zip CRCs catch edits): rebuild it from the Minari datasets
        warnings.warn(f"{file} is damaged ({type(err).__name__}: {err}); rebuilding it from the datasets",
                      BatiWarning)
        return None
    for split in store.SPLITS:
        if any(f"{split}__{name}" not in arrays for name in FIELDS):
            return None
        if (arrays[f"{split}__observations"].shape[-1] != obs_dim
                or arrays[f"{split}__actions"].shape[-1] != action_dim):
            return None
    return arrays
