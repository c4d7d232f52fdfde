"""Build a family's offline datasets (Eq. 9) and test-time context data (Eq. 10): run the episodes
of `bati.data.plan`'s plan (who collects which episode) and write the collection.

"The expert for task M" is the family's task-conditioned SAC conditioned on M's parameters
(design deviation: one expert per family), or with `experts="per-task"` the SAC trained for training
task M alone (App. C.2; `bati.experts.per_task`). Experts act stochastically; every episode is run in
the family's env with its default eps (or `noise`). All episodes are stepped in lockstep chunks
of CHUNK envs (one batched expert call per step); a chunk's episodes depend only on the seed, the
plan and the chunk's index, so chunks are spread over worker processes (`workers`, default: all
cores) and the written datasets do not depend on how many there are. The main process writes
each dataset, in plan order, as soon as its episodes are done.
"""

from __future__ import annotations

import os
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bati.checks import check_integer
from bati.data import store
from bati.data.plan import OTHER_FRACTION, PLAN_STREAM, DatasetPlan, Plan, make_plan
from bati.envs import FAMILY_NAMES, TaskFamily, TaskSplit, as_family, get_family
from bati.envs.rollout import ONE_THREAD_ENV, LockstepEnvs
from bati.experts.kinds import ExpertsKind, experts_label, family_experts
from bati.io import atomic_write_json, check_directory, git_commit, hold_lock

# Episodes per training task and per context dataset. `paper`: the family's own size
# (FamilyRecord.paper_episodes: App. C Table 3 "Dataset Size" read as transitions PER TASK).
SCALES: dict[str, dict[str, Any]] = {
    "quick": {"n_episodes": 20, "n_context_episodes": 5},
    "paper": {"n_episodes": "paper_episodes", "n_context_episodes": 20},
}
CHUNK = 256  # envs stepped in lockstep (fixed: the stochastic actions depend on it)


def scale_sizes(family: TaskFamily, scale: str) -> tuple[int, int]:
    """(n_episodes per training task, n_context_episodes per test task) of a scale for `family` (a size given
    as a FamilyRecord field's name is the family's own)."""
    if scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; choose one of: {', '.join(SCALES)}")
    record = family.record
    sizes = {k: getattr(record, v) if isinstance(v, str) else v for k, v in SCALES[scale].items()}
    return int(sizes["n_episodes"]), int(sizes["n_context_episodes"])


def check_fits(family: TaskFamily, n_episodes: int, n_context_episodes: int, tasks: TaskSplit, root) -> None:
    """ValueError (one line: the setting, the estimate and what the machine has) where a collection of these sizes
    cannot be held in memory (a run loads it whole) or written to the data root's disk, before anything is
    allocated or written. Estimate: float32 observations, next observations, actions and rewards and an int32
    collector per transition (the loaded arrays; Minari's files on disk take about as much)."""
    obs_dim, action_dim = _env_dims(family)
    episodes = tasks.n_train * n_episodes + 2 * tasks.n_test * n_context_episodes
    needed = episodes * family.record.episode_length * 4 * (2 * obs_dim + action_dim + 2)
    existing = next(p for p in (Path(root).absolute(), *Path(root).absolute().parents) if p.exists())
    for what, have in (("memory", available_memory()), ("disk space under the data root", shutil.disk_usage(existing).free)):
        if have is not None and needed > have:
            raise ValueError(f"{n_episodes:,} episodes per training task and {n_context_episodes:,} per context dataset "
                             f"make ~{_size(needed)} of {family.name} data; this machine has {_size(have)} of {what}: "
                             "lower --episodes-per-task / --context-episodes (or the scale)")


_DIMS: dict[tuple[str, int], tuple[int, int]] = {}


def _env_dims(family: TaskFamily) -> tuple[int, int]:
    """(obs_dim, action_dim) of the family's env, made once per process (plans check many cells)."""
    key = (family.name, family.record.version)
    if key not in _DIMS:
        probe = family.make_env(family.sample_tasks(1, seed=0)[0], 0.0)
        _DIMS[key] = (probe.observation_space.shape[0], probe.action_space.shape[0])
        probe.close()
    return _DIMS[key]


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable), None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:,.1f} {unit}" if unit != "B" else f"{n:.0f} B"
        n /= 1024
    return f"{n:,.1f} PB"


def check_supported(family: TaskFamily) -> None:
    """ValueError (one line) for a family whose episodes can end early: collection, the datasets and
    IQL's bootstrapping assume every episode runs its full `episode_length` steps."""
    if family.record.terminates:
        raise ValueError(f"{family.name}: families whose episodes end early (FamilyRecord.terminates) are not "
                         "supported yet: datasets store fixed-length episodes and IQL bootstraps every transition")


def _from_plugin(name: str) -> bool:
    """Whether family `name` comes from an installed package's entry point (so a spawned process finds it)."""
    from importlib.metadata import entry_points

    from bati.envs import PLUGIN_GROUP

    return any(entry.name == name for entry in entry_points(group=PLUGIN_GROUP))


# --- collection -------------------------------------------------------------------------------
@dataclass
class CollectResult:
    path: Path
    manifest: dict
    cached: bool  # True when the collection was already on disk
    wall_time_s: float


def collect(
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
    workers: int | None = None,
    tasks: TaskSplit | None = None,
    experts: ExpertsKind | None = None,
    check_only: bool = False,
) -> CollectResult | None:
    """Collect (or find cached) the datasets of `family` under `<root>/<Family>/<scale>-seed<S>-eps<eps>`.

    `n_episodes` / `n_context_episodes` override the scale's sizes (for tests and experiments);
    `zoo_dir` is where the expert is loaded from (default: the package zoo). `workers` processes
    roll out the episodes (default: all cores, at most one per chunk of CHUNK episodes); the
    datasets written are the same whatever their number. `tasks` changes which tasks train and test
    (counts, parameter ranges); a non-default split is its own collection (its label in the name).
    `experts`: "per-task" (one SAC per training task, App. C.2; its collection ends in `-per-task-experts`) or
    "conditioned" (the family's task-conditioned SAC); default: the family's (`family_experts`). `check_only`:
    collect nothing, only raise what collecting would raise before any work (a collection of other sizes in its
    place, a data directory that is a file or not writable); returns None.
    """
    start = time.perf_counter()
    workers = check_workers(workers)
    request = Request.resolve(family, scale, seed, noise, root, n_episodes, n_context_episodes, zoo_dir, tasks,
                              experts)
    target = request.target
    if not (target / store.MANIFEST).is_file():
        check_fits(request.family, request.n_episodes, request.n_context_episodes, request.tasks, request.root)
    cached = request.cached()
    if cached is not None:
        return None if check_only else CollectResult(target, cached, True, time.perf_counter() - start)
    check_directory(target.parent, "the data directory")  # a file, or not writable: say so before any work
    if check_only:
        return None

    fam = request.family
    plan = make_plan(fam, request.seed, request.n_episodes, request.n_context_episodes, request.tasks,
                     ties=collector_ties(request.experts))
    workers = min(default_workers() if workers is None else workers, -(-plan.n_episodes // CHUNK))
    if fam.name not in FAMILY_NAMES and not _from_plugin(fam.name):  # spawned workers would not know it
        workers = 1
    load_start = time.perf_counter()
    expert, dims = _checked_expert(request, plan)
    timings = {"expert_load_s": time.perf_counter() - load_start}
    target.parent.mkdir(parents=True, exist_ok=True)
    # one writer per collection: a second process fails at once naming the first (its pid, host)
    with hold_lock(store.lock_path(target), f"the collection {target}"):
        store.remove_stale_partials(target)
        cached = request.cached()
        if cached is not None:  # another process finished the same collection meanwhile
            return CollectResult(target, cached, True, time.perf_counter() - start)
        if target.exists():  # no manifest: an incomplete or foreign directory; start over
            stale = store.partial_dir(target)
            target.rename(stale)
            shutil.rmtree(stale, ignore_errors=True)
        return _write_collection(request, plan, expert, dims, workers, progress, timings, start)


@dataclass(frozen=True)
class Request:
    """One collection's settings, resolved and checked (`resolve`): where it lies, what decides its content."""

    family: TaskFamily
    scale: str
    seed: int
    noise: float
    root: Path
    tasks: TaskSplit
    experts: ExpertsKind
    n_episodes: int
    n_context_episodes: int
    zoo_dir: str | Path | None = None

    @classmethod
    def resolve(cls, family, scale, seed, noise, root, n_episodes, n_context_episodes, zoo_dir, tasks,
                experts) -> Request:
        """Defaults filled (the scale's sizes, the family's eps and experts), every value checked (one line)."""
        check_integer("seed", seed, low=0)  # a negative seed: one line now, not numpy's after the plan
        fam = as_family(family)  # the caller's resolved family, or one looked up by name here
        check_supported(fam)
        tasks = (tasks or TaskSplit()).checked(fam)
        default_n, default_ctx = scale_sizes(fam, scale)
        n_episodes = default_n if n_episodes is None else int(n_episodes)
        n_context_episodes = default_ctx if n_context_episodes is None else int(n_context_episodes)
        check_integer("n_episodes", n_episodes)
        check_integer("n_context_episodes", n_context_episodes)
        return cls(fam, scale, seed, fam.validate_noise(noise), Path(root), tasks,
                   family_experts(fam, experts, seed, tasks), n_episodes, n_context_episodes, zoo_dir)

    @property
    def target(self) -> Path:
        return store.collection_dir(self.root, self.family, self.scale, self.seed, self.noise, self.tasks,
                                    self.experts)

    def command(self) -> str:
        return store.collect_command(self.family, self.scale, self.seed, self.noise, self.root, self.tasks,
                                     self.experts)

    def settings(self) -> dict:
        """Everything that decides the collection's content, in one place of its manifest: with the same
        settings (and the same expert, by its sha256) a collection is reproduced file for file. (Per-task
        experts add `experts` and `ties`; a collection by the conditioned expert records neither, as before
        they existed.)"""
        from bati.experts.per_task import PER_TASK_DIR
        from bati.experts.zoo import ZOO_DIR

        fam, experts = self.family, self.experts
        entry = Path(self.zoo_dir or ZOO_DIR) / fam.name
        actor = entry / PER_TASK_DIR / "actors.msgpack" if experts == "per-task" else entry / "actor.msgpack"
        kind = {"experts": experts, "ties": collector_ties(experts)} if experts != "conditioned" else {}
        return {**kind, "family": fam.name, "scale": self.scale, "seed": self.seed, "noise": self.noise,
                "n_episodes": self.n_episodes, "n_context_episodes": self.n_context_episodes,
                "episode_length": fam.record.episode_length, "chunk": CHUNK, "other_fraction": OTHER_FRACTION,
                "task_split": self.tasks.record(), "expert_sha256": store.sha256_file(actor) if actor.is_file() else None}

    def cached(self) -> dict | None:
        """The manifest of the complete collection at `target`, None if there is none; ValueError (one line) for
        one made with other sizes, or, by per-task experts, with other experts or another rule for tied
        collectors."""
        target, fam = self.target, self.family
        if not (target / store.MANIFEST).is_file():
            return None
        manifest = store.read_manifest(target, fam, self.scale, self.seed, self.noise, self.root, self.tasks,
                                       self.experts)
        store.require_env_dims(target, manifest, fam, self.noise)  # the env changed since: not "already collected"
        sizes = (manifest.get("n_episodes"), manifest.get("n_context_episodes"))
        if sizes != (self.n_episodes, self.n_context_episodes):
            raise ValueError(
                f"{target} holds {sizes[0]} episodes per training task and {sizes[1]} per context dataset, "
                f"not the requested {self.n_episodes} / {self.n_context_episodes}; delete it or give another data root"
            )
        if self.experts == "per-task":  # per-task experts are retrained: their old data must not pass for the new
            saved, now = manifest.get("settings", {}), self.settings()
            tied = "with the first of tied collectors for every episode"
            for key, what in (("expert_sha256", "by other per-task experts"), ("ties", tied)):
                if now[key] is not None and saved.get(key) != now[key]:
                    raise ValueError(f"{target} was collected {what} than this bati's (its manifest's "
                                     f"settings.{key}: {saved.get(key)!r}); delete it or give another data root")
        return manifest


def _checked_expert(request: Request, plan: Plan):
    """The collection's expert(s) and the env's (obs_dim, action_dim); one line where they do not fit."""
    fam = request.family
    expert = load_expert(fam, request.zoo_dir, request.experts)  # FileNotFoundError naming `bati experts train`
    if request.experts == "per-task":
        expert.check_tasks(plan.train_tasks)  # trained for other tasks: one line, before any episode
    probe = fam.make_env(plan.train_tasks[0], request.noise)
    dims = probe.observation_space.shape[0], probe.action_space.shape[0]
    probe.close()
    # a trained expert records its sizes; a scripted one (register_expert) may not
    if (expert.meta.get("obs_dim", dims[0]), expert.meta.get("action_dim", dims[1])) != dims:
        raise ValueError(
            f"the {fam.name} expert reads obs_dim={expert.meta['obs_dim']} / writes action_dim="
            f"{expert.meta['action_dim']}, but the env has {dims[0]} / {dims[1]}; retrain it with "
            f"`bati experts train --family {fam.name}`"
        )
    return expert, dims


def _write_collection(request: Request, plan: Plan, expert, dims: tuple[int, int], workers: int, progress: bool,
                      timings: dict, start: float) -> CollectResult:
    """Roll out and write the collection into a partial directory, its manifest last, then move it into place
    (the collection's lock held); an error leaves nothing."""
    target, fam = request.target, request.family
    tmp = store.partial_dir(target)
    tmp.mkdir()
    try:
        base_meta = {"family": fam.name, "scale": request.scale, "seed": request.seed, "noise": request.noise,
                     "commit": git_commit(), "collection_id": uuid.uuid4().hex}
        timings.update(run_collection(fam, plan, expert, request.noise, request.seed, tmp, base_meta,
                                      progress=progress, workers=workers, zoo_dir=request.zoo_dir,
                                      experts=request.experts))
        manifest = {
            "format": store.FORMAT_VERSION,
            **base_meta,
            "n_episodes": request.n_episodes,
            "n_context_episodes": request.n_context_episodes,
            "episode_length": fam.record.episode_length,
            "obs_dim": dims[0],
            "action_dim": dims[1],
            "task_dim": fam.task_dim,
            "kind": fam.kind,
            "family_version": fam.record.version,
            "task_split": request.tasks.record(),
            "train_tasks": plan.train_tasks,
            "test_tasks": plan.test_tasks,
            "p_test_most_different": plan.most_different,
            "p_train_most_similar": plan.most_similar,
            "datasets": {s: [d.name for d in plan.datasets if d.split == s] for s in store.SPLITS},
            "transitions": plan.n_episodes * fam.record.episode_length,
            "experts": request.experts,
            "expert": {"train_steps": expert.meta.get("train_steps", expert.meta.get("train_steps_per_task")),
                       "seed": expert.meta.get("seed")},
            "collect_wall_time_s": round(time.perf_counter() - start, 2),
            "workers": workers,  # how it was made, not what it is: not part of the cache identity
            "timings_s": {k: round(v, 2) for k, v in timings.items()},
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": request.command(),
            "settings": request.settings(),
        }
        manifest["files"] = store.file_checksums(tmp, manifest["datasets"])  # what verify and loads check
        manifest[store.MANIFEST_DIGEST] = store.manifest_digest(manifest)  # an edit by hand is found
        atomic_write_json(tmp / store.MANIFEST, manifest)  # written last
        try:
            tmp.rename(target)
        except OSError:  # a concurrent collection finished first: keep its (identical) data
            existing = request.cached()
            if existing is None:
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return CollectResult(target, existing, True, time.perf_counter() - start)
    except OSError as err:  # e.g. a full disk under Minari: nothing stays, the error names the collection
        shutil.rmtree(tmp, ignore_errors=True)
        raise _naming_collection(err, target, tmp) from err
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return CollectResult(target, manifest, False, time.perf_counter() - start)


def _naming_collection(err: OSError, target: Path, tmp: Path) -> OSError:
    """An OS error while writing a collection, naming the collection rather than its temporary directory
    (which is gone by then); bati's own errors (no errno, a whole sentence) pass unchanged."""
    if err.errno is None or (err.filename is not None and tmp.name not in str(err.filename)):
        return err
    named = OSError(err.errno, err.strerror or str(err), str(target))
    named.__cause__ = err
    return named


_EXPERTS: dict[tuple, Any] = {}


def load_expert(family: TaskFamily, zoo_dir: str | Path | None = None, experts: ExpertsKind | None = None):
    """`bati.experts.zoo.load_for`, memoised per process while the expert's files are unchanged."""
    from bati.experts.per_task import PER_TASK_DIR
    from bati.experts.zoo import ZOO_DIR, load_for

    experts = family_experts(family, experts)
    directory = Path(zoo_dir or ZOO_DIR) / family.name
    files = ("expert.json", "actor.msgpack")
    if experts == "per-task":
        directory, files = directory / PER_TASK_DIR, ("expert.json", "actors.msgpack")
    try:
        stamp = tuple((directory / name).stat().st_mtime_ns for name in files)
    except OSError:
        return load_for(family, zoo_dir, experts)  # raises the zoo's own error (e.g. no expert for the family)
    key = (family.name, str(directory.resolve()), stamp)
    if key not in _EXPERTS:
        for stale in [k for k in _EXPERTS if k[:2] == key[:2]]:  # the expert was re-exported
            del _EXPERTS[stale]
        _EXPERTS[key] = load_for(family, zoo_dir, experts)
    return _EXPERTS[key]


def collector_ties(experts: str) -> str:
    """How a collection picks among tied collectors (`bati.data.plan`): per-task experts differ, so "drawn"."""
    return "drawn" if experts == "per-task" else "first"


def default_workers() -> int:
    """All cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def check_workers(workers: int | None) -> int | None:
    """`workers` if it is None or an int >= 1, else a one-line ValueError."""
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers={workers!r}: the number of worker processes must be an integer >= 1")
    return int(workers)


@dataclass
class _Chunk:
    """One lockstep chunk of episodes: all a process needs to roll it out (picklable)."""

    index: int  # its position in the collection: its actions use fold_in(base_key, index)
    tasks: list  # (K,) task of each episode
    reset_seeds: list[int]  # (K,)
    policy_tasks: np.ndarray  # (K, task_dim) task array the collecting expert is conditioned on
    collectors: np.ndarray  # (K,) index of the training task whose expert collects each episode


def _chunks(family: TaskFamily, plan: Plan, chunk_size: int) -> list[_Chunk]:
    jobs = [(d, e) for d in plan.datasets for e in range(len(d.collectors))]
    train_arrays = np.stack([family.task_to_array(t) for t in plan.train_tasks]).astype(np.float32)
    return [
        _Chunk(
            index,
            [d.task for d, _ in jobs[first : first + chunk_size]],
            [int(d.reset_seeds[e]) for d, e in jobs[first : first + chunk_size]],
            train_arrays[[int(d.collectors[e]) for d, e in jobs[first : first + chunk_size]]],
            np.array([int(d.collectors[e]) for d, e in jobs[first : first + chunk_size]], np.int32),
        )
        for index, first in enumerate(range(0, len(jobs), chunk_size))
    ]


def _rollout_chunk(family: TaskFamily, expert, noise: float, seed: int, chunk: _Chunk, chunk_size: int,
                   envs: LockstepEnvs, on_step=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll out one chunk in lockstep: (observations (K, T + 1, obs_dim), actions, rewards).

    The result depends only on (seed, chunk, chunk_size): envs are reset with the episodes' seeds
    and the expert's actions use the chunk's own key, so any process can roll out any chunk.
    `envs` is the caller's pool (reused across chunks).
    """
    import jax

    k_envs, length = len(chunk.tasks), family.record.episode_length
    policy_tasks = np.zeros((chunk_size, family.task_dim), np.float32)  # padded: one jit shape
    policy_tasks[:k_envs] = chunk.policy_tasks
    collectors = np.zeros(chunk_size, np.int32)
    collectors[:k_envs] = chunk.collectors
    first = envs.reset(chunk.tasks, chunk.reset_seeds)
    obs = np.zeros((k_envs, length + 1, first.shape[-1]))
    obs[:, 0] = first
    actions, rewards = None, np.zeros((k_envs, length), np.float32)
    # the expert runs on the CPU in every process (workers never touch an accelerator), so the
    # actions do not depend on where, or in how many processes, the chunk is rolled out
    with jax.default_device(jax.devices("cpu")[0]):
        base_key = jax.random.fold_in(jax.random.PRNGKey(seed), PLAN_STREAM)
        chunk_key = jax.random.fold_in(base_key, chunk.index)
        padded = np.zeros((chunk_size, obs.shape[-1]), np.float32)
        for t in range(length):
            padded[:k_envs] = obs[:, t]
            act = np.asarray(expert.act_for_collectors(padded, collectors, policy_tasks, False,
                                                       jax.random.fold_in(chunk_key, t)))
            if actions is None:
                actions = np.zeros((k_envs, length, act.shape[-1]), np.float32)
            actions[:, t] = act[:k_envs]
            step = envs.step(actions[:, t])
            obs[:, t + 1] = step.observations
            rewards[:, t] = step.rewards
            if on_step is not None:
                on_step(k_envs)
    return obs, actions, rewards


# --- worker processes (spawned: JAX is not fork-safe) -------------------------------------------
_WORKER_THREAD_ENV = {
    **ONE_THREAD_ENV,
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
}
_WORKER: dict[str, Any] = {}


def _worker_init(family_name: str, zoo_dir: str | None, noise: float, seed: int, chunk_size: int,
                 experts: ExpertsKind) -> None:
    """Per worker process, once: one thread (so N workers use N cores), CPU only, the settings."""
    for name, value in _WORKER_THREAD_ENV.items():
        if name == "XLA_FLAGS":
            value = " ".join(filter(None, [os.environ.get(name, ""), value]))
        os.environ[name] = value  # before jax is first imported (this module does not import it)
    os.environ["JAX_PLATFORMS"] = "cpu"  # N processes must not share (or grab) one accelerator
    _WORKER.update(family_name=family_name, zoo_dir=zoo_dir, noise=noise, seed=seed, chunk_size=chunk_size,
                   experts=experts)


def _worker_rollout(chunk: _Chunk) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    w = _WORKER
    if "expert" not in w:  # loaded here, not in the initializer: its errors reach the caller intact
        w["family"] = get_family(w["family_name"])
        w["expert"] = load_expert(w["family"], w["zoo_dir"], w["experts"])
        w["envs"] = LockstepEnvs(w["family"], w["noise"])
    return (chunk.index, *_rollout_chunk(w["family"], w["expert"], w["noise"], w["seed"], chunk,
                                         w["chunk_size"], w["envs"]))


def run_collection(
    family: TaskFamily,
    plan: Plan,
    expert,
    noise: float,
    seed: int,
    out_dir: Path,
    base_meta: dict,
    progress: bool = True,
    *,
    workers: int = 1,
    zoo_dir: str | Path | None = None,
    experts: ExpertsKind,
) -> dict[str, float]:
    """Roll out every planned episode (lockstep chunks of CHUNK envs) and write the datasets.

    With `workers` > 1 the chunks are rolled out by that many spawned processes (each loads the
    family's expert from `zoo_dir` once); the main process writes each dataset, in plan order, as
    soon as all its episodes are in. A chunk's episodes depend only on (seed, plan, chunk index),
    so the written datasets are the same whatever the number of workers.
    Returns wall times: rollout_s (envs + expert, incl. worker start-up), write_s (Minari datasets).
    """
    workers = check_workers(workers) or 1
    start, write_s = time.perf_counter(), 0.0
    chunk_size = CHUNK
    chunks = _chunks(family, plan, chunk_size)
    jobs = [(d, e) for d in plan.datasets for e in range(len(d.collectors))]
    workers = min(workers, len(chunks))
    buffers: dict[str, dict[str, list]] = {}

    def consume(chunk: _Chunk, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray) -> None:
        """Buffer a chunk's episodes (chunks in order) and write the datasets they complete."""
        nonlocal write_s
        chunk_jobs = jobs[chunk.index * chunk_size : chunk.index * chunk_size + len(chunk.tasks)]
        for k, (d, _) in enumerate(chunk_jobs):
            buf = buffers.setdefault(d.name, {"obs": [], "act": [], "rew": []})
            buf["obs"].append(obs[k])
            buf["act"].append(actions[k])
            buf["rew"].append(rewards[k])
        for d in {d.name: d for d, _ in chunk_jobs}.values():
            if len(buffers.get(d.name, {"obs": []})["obs"]) == len(d.collectors):
                write_start = time.perf_counter()
                _write(family, plan, d, buffers.pop(d.name), noise, out_dir, base_meta)
                write_s += time.perf_counter() - write_start

    bar = _progress(progress, f"{family.name} data ({experts_label(experts, family)})")
    with bar:
        task_id = bar.add_task("collect", total=len(jobs) * family.record.episode_length)
        if workers == 1:
            with LockstepEnvs(family, noise) as envs:
                for chunk in chunks:
                    arrays = _rollout_chunk(family, expert, noise, seed, chunk, chunk_size, envs,
                                            on_step=lambda n: bar.advance(task_id, n))
                    consume(chunk, *arrays)
        else:
            _run_parallel(family, chunks, chunk_size, noise, seed, workers, (zoo_dir, experts), consume,
                          lambda n: bar.advance(task_id, n * family.record.episode_length))
    return {"rollout_s": time.perf_counter() - start - write_s, "write_s": write_s}


def _run_parallel(family: TaskFamily, chunks: list[_Chunk], chunk_size: int, noise: float, seed: int,
                  workers: int, expert_source, consume, advance) -> None:
    """Roll out `chunks` in `workers` spawned processes; `consume` them in order as they finish.
    `expert_source`: (zoo_dir, experts), where each worker loads the experts from."""
    from concurrent.futures import FIRST_COMPLETED, wait

    from bati.processes import spawned_pool

    window = 4 * workers  # chunks submitted ahead of the next one to consume (bounds the memory)
    pending: dict = {}  # future -> chunk index
    done: dict[int, tuple] = {}  # finished chunks waiting for an earlier one
    next_submit = next_consume = 0
    zoo_dir, experts = expert_source
    initargs = (family.name, None if zoo_dir is None else str(zoo_dir), noise, seed, chunk_size, experts)
    with spawned_pool(workers, _worker_init, initargs) as executor:
        while next_consume < len(chunks):
            while next_submit < len(chunks) and next_submit < next_consume + window:
                pending[executor.submit(_worker_rollout, chunks[next_submit])] = next_submit
                next_submit += 1
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in finished:
                del pending[future]
                index, *arrays = future.result()  # a worker's exception is re-raised here
                done[index] = arrays
                advance(len(chunks[index].tasks))
            while next_consume in done:
                consume(chunks[next_consume], *done.pop(next_consume))
                next_consume += 1


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
