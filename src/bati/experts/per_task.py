"""One SAC expert per training task (App. C.2), all of a family's training tasks trained as one program.

Task i of `split_tasks(seed=0)`'s training tasks has its own env (fixed to task i, eps = 0), replay
buffer, networks, optimiser states, jax key and numpy generator. Each iteration steps the n envs
once (one lockstep call) and, every `update_every` steps, applies `update_every * updates_per_step`
SAC updates to every task in one jitted call: `SAC.update_many` over the task axis (`lax.map` on the CPU,
`vmap` on an accelerator: `--task-axis`).
A task's random streams depend only on (seed, its index), so training a subset of the tasks (`tasks`)
gives each of them the parameters the full program gives it (tested).

The actors read the observation only (task_dim 0: expert i is "the expert of task i", not a policy
conditioned on a task). Exported as one stacked actor file per family (`<zoo>/<Family>/per-task/`).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import flax
import jax
import jax.numpy as jnp
import numpy as np
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from bati.envs import TaskFamily
from bati.envs.rollout import LockstepEnvs, rollout
from bati.experts.base import Expert
from bati.experts.sac import RESUME_IDENTITY, SAC, SACConfig, generator_from_state
from bati.experts.zoo import read_actors, read_expert_meta
from bati.io import (
    append_jsonl,
    read_jsonl_lines,
    atomic_save_npz,
    atomic_write_bytes,
    atomic_write_json,
    check_directory,
    check_run_config,
)
from bati.processes import stall_watchdog

PER_TASK_DIR = "per-task"
"""Sub-directory of a family's zoo entry that holds its per-task experts."""
SPLIT_SEED = 0
"""The data seed whose training tasks get experts (the collections' default `--seed`)."""
FIELDS = ("observations", "actions", "rewards", "next_observations")


def training_tasks(family: TaskFamily, seed: int = SPLIT_SEED) -> list:
    return family.split_tasks(seed)[0]


class TaskBuffers:
    """One replay buffer per task, as (n_tasks, capacity, ...) arrays filled in lockstep."""

    def __init__(self, n_tasks: int, capacity: int, obs_dim: int, action_dim: int):
        dims = {"observations": obs_dim, "actions": action_dim, "rewards": None, "next_observations": obs_dim}
        self.data = {k: np.zeros((n_tasks, capacity) + (() if d is None else (d,)), np.float32) for k, d in dims.items()}
        self.size = 0

    def add(self, **step: np.ndarray) -> None:
        for k in FIELDS:
            self.data[k][:, self.size] = step[k]
        self.size += 1

    def sample(self, rngs: list[np.random.Generator], num_batches: int, batch_size: int) -> dict[str, np.ndarray]:
        """(n_tasks, num_batches, batch_size, ...): each task's batches from its own buffer and generator."""
        idx = np.stack([rng.integers(0, self.size, size=(num_batches, batch_size)) for rng in rngs])
        rows = np.arange(len(rngs))[:, None, None]
        batch = {k: v[rows, idx] for k, v in self.data.items()}
        # SAC reads a task array beside each observation: per-task experts have none
        batch["tasks"] = np.zeros(idx.shape + (0,), np.float32)
        return batch

    def state(self) -> dict[str, np.ndarray]:
        return {k: v[:, : self.size] for k, v in self.data.items()}

    def restore(self, arrays) -> None:
        self.size = arrays["rewards"].shape[1]
        for k in FIELDS:
            self.data[k][:, : self.size] = arrays[k]


TASK_AXES = ("map", "vmap")
"""How the tasks' SAC updates run in one jitted call: `lax.map` (one task after another, the same program for
every task) or `vmap` (one batched program)."""


def default_task_axis(backend: str | None = None) -> str:
    """The faster axis on `backend` (default: JAX's): `map` on the CPU (benchmarks/per_task_update.py: 1.3-1.9x
    vmap's rate on one core, docs/performance.md), `vmap` on an accelerator (not measured yet: its batched matrix
    products are what a GPU is built for)."""
    return "map" if (backend or jax.default_backend()) == "cpu" else "vmap"


class PerTaskSAC:
    """SAC's networks and update over a leading task axis of states, batches and keys.

    The update applies `SAC.update_many` to every task inside one jitted call: mapped (`lax.map`: the same
    program for every task, so a task's numbers do not depend on which others train beside it) or vmapped
    (one batched program: on an accelerator a task's numbers may differ in the last bits with the number of
    tasks beside it)."""

    def __init__(self, obs_dim: int, action_dim: int, config, task_axis: str = "map"):
        if task_axis not in TASK_AXES:
            raise ValueError(f"task_axis={task_axis!r}: choose one of {', '.join(TASK_AXES)}")
        self.sac = SAC(obs_dim, 0, action_dim, config)
        self.task_axis = task_axis
        self.init = jax.jit(lambda keys: jax.lax.map(self.sac.init, keys))
        if task_axis == "vmap":
            self.update = jax.jit(jax.vmap(self.sac._update_many))
        else:
            self.update = jax.jit(lambda states, batches, keys: jax.lax.map(
                lambda args: self.sac._update_many(*args), (states, batches, keys)))
        self._act = jax.jit(jax.vmap(self._act_one, in_axes=(0, 0, 0, None)), static_argnames="deterministic")

    def _act_one(self, actor, obs, key, deterministic: bool):
        return self.sac._act(actor, obs[None], jnp.zeros((1, 0)), key, deterministic=deterministic)[0]

    def act(self, actors, obs: np.ndarray, keys: jax.Array, deterministic: bool) -> np.ndarray:
        """(n_tasks, action_dim): expert i's action on obs[i]."""
        return np.asarray(self._act(actors, jnp.asarray(obs, jnp.float32), keys, deterministic))


def task_keys(seed: int, indices) -> jax.Array:
    """Each task's own key: fold_in(PRNGKey(seed), task index)."""
    return jnp.stack([jax.random.fold_in(jax.random.PRNGKey(seed), int(i)) for i in indices])


def train_per_task_experts(run, show_progress: bool = True) -> Path:
    """Train (or resume) the per-task experts of a resolved expert run (`ExpertTrainConfig.resolve()`, with
    per_task); returns the run directory."""
    config, family = run.config, run.family
    out: Path = config.out_dir
    check_directory(out, "the experts' run directory")
    check_directory(config.export_dir / config.family / PER_TASK_DIR, "the zoo directory", package=config.into_package)
    all_tasks = training_tasks(family)
    indices = list(range(len(all_tasks))) if config.tasks is None else list(config.tasks)
    tasks = [all_tasks[i] for i in indices]
    probe = family.make_env(tasks[0], noise=0.0)
    obs_dim, action_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    probe.close()
    learner = PerTaskSAC(obs_dim, action_dim, config.sac, config.task_axis)
    updates_per_call = max(1, int(round(config.update_every * config.updates_per_step)))

    keys = task_keys(config.seed, indices)
    split = jax.vmap(jax.random.split)(keys)  # (n, 2, 2): the init key, the running key
    state, keys = learner.init(split[:, 0]), split[:, 1]
    rngs = [np.random.default_rng([config.seed, i]) for i in indices]
    length = family.record.episode_length
    buffers = TaskBuffers(len(tasks), -(-config.total_steps // length) * length, obs_dim, action_dim)  # whole episodes
    episode, wall_time = 0, 0.0
    check_run_config(out / "config.json", json.loads(json.dumps(asdict(config), default=str)),
                     RESUME_IDENTITY + ("per_task", "tasks", "update_every"))
    if (out / "checkpoint.npz").exists():
        state, keys, rngs, episode, wall_time = _load_checkpoint(out, buffers, state)

    progress = Progress(
        TextColumn(f"[bold]{config.family} per-task experts ({len(tasks)})"), BarColumn(),
        TextColumn("{task.completed:,}/{task.total:,} steps per task"), TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress)
    start = time.perf_counter() - wall_time
    envs = LockstepEnvs(family, noise=0.0)
    metrics, returns = {}, None
    with progress, envs, stall_watchdog() as alive:
        bar = progress.add_task("train", total=config.total_steps, completed=buffers.size, status="")
        while buffers.size < config.total_steps:
            obs = envs.reset(tasks, [config.seed * 1_000_003 + i * 100_003 + episode for i in indices])
            for _ in range(length):
                if buffers.size < config.start_steps:
                    actions = np.stack([rng.uniform(-1.0, 1.0, action_dim) for rng in rngs]).astype(np.float32)
                else:
                    split = jax.vmap(jax.random.split)(keys)
                    keys, actions = split[:, 0], learner.act(state.actor.params, obs, split[:, 1], deterministic=False)
                step = envs.step(actions)
                buffers.add(observations=obs, actions=actions, rewards=step.rewards, next_observations=step.observations)
                obs = step.observations
                if buffers.size >= config.start_steps and buffers.size % config.update_every == 0:
                    batches = buffers.sample(rngs, updates_per_call, config.sac.batch_size)
                    split = jax.vmap(jax.random.split)(keys)
                    keys = split[:, 0]
                    state, metrics = learner.update(state, batches, split[:, 1])
            episode += 1
            steps = buffers.size
            progress.update(bar, completed=min(steps, config.total_steps))
            alive()
            crossed = lambda every: steps // every > (steps - length) // every  # noqa: E731
            if crossed(config.eval_every) or steps >= config.total_steps:
                returns = evaluate_per_task(learner, state.actor.params, family, tasks, indices)
                append_jsonl(out / "metrics.jsonl", {
                    "steps": steps, "episode": episode, "wall_time": time.perf_counter() - start,
                    **{k: float(np.mean(v)) for k, v in metrics.items()},
                    "eval_return": float(returns.mean()), "eval_returns": [round(float(r), 2) for r in returns]})
                progress.update(bar, status=f"eval return {returns.mean():.1f} (min {returns.min():.1f})")
            if crossed(config.checkpoint_every) or steps >= config.total_steps:
                _save_checkpoint(out, state, keys, rngs, episode, buffers, time.perf_counter() - start)

    meta = {"kind": "per-task", "obs_dim": obs_dim, "task_dim": family.task_dim, "action_dim": action_dim,
            "family_version": family.record.version, "hidden_dims": list(config.sac.hidden_dims),
            "split_seed": SPLIT_SEED, "task_indices": indices, "tasks": [family.task_to_array(t).tolist() for t in tasks],
            "train_steps_per_task": buffers.size, "seed": config.seed,
            "train_wall_time_s": round(time.perf_counter() - start, 1), **_logged_evaluations(out, buffers.size)}
    save_per_task_experts(config.export_dir / config.family / PER_TASK_DIR, config.family, state.actor.params, meta)
    return out


def _logged_evaluations(out: Path, steps: int) -> dict:
    """From the run's metrics.jsonl, up to `steps` (a run exported at an earlier checkpoint logs no later
    evaluation): `eval_curve` (steps, mean evaluation return over the run's tasks) and `final_eval_returns`
    (each task's return at `steps`, None where no evaluation was logged there)."""
    path = out / "metrics.jsonl"
    records = [r for _, r in read_jsonl_lines(path, require=("steps", "eval_return"))] if path.is_file() else []
    records = [r for r in records if r["steps"] <= steps]
    last = records[-1] if records and records[-1]["steps"] == steps else None
    return {"eval_curve": {"steps": [r["steps"] for r in records], "mean_return": [r["eval_return"] for r in records]},
            "final_eval_returns": None if last is None else last.get("eval_returns")}


def evaluate_per_task(learner: PerTaskSAC, actors, family: TaskFamily, tasks: list, indices: list[int],
                      seed: int = 12345) -> np.ndarray:
    """Each expert's deterministic return (eps = 0) on its own task: (n_tasks,). Training task i's episode is
    reset with seed + i, so a part (`--tasks`) logs the returns the full program logs for its tasks."""
    keys = jnp.zeros((len(tasks), 2), jnp.uint32)
    episodes = rollout(family, tasks, lambda o, _: learner.act(actors, o, keys, deterministic=True), noise=0.0,
                       seed=[seed + i for i in indices])
    return np.asarray(episodes.returns)


def save_per_task_experts(directory: Path, family_name: str, actors, meta: dict) -> None:
    atomic_write_bytes(directory / "actors.msgpack", flax.serialization.to_bytes(actors))
    atomic_write_json(directory / "expert.json", {"family": family_name, **meta})


MERGE_IDENTITY = ("family", "kind", "family_version", "obs_dim", "action_dim", "hidden_dims", "split_seed", "seed",
                  "train_steps_per_task")
"""What the parts of one export must share: the same family, env version, networks, seed and budget."""


def merge_per_task_experts(family: TaskFamily, parts: list[Path], zoo_dir: Path, package: bool = False) -> dict:
    """Join per-task experts trained in parts (`--tasks`, e.g. on different days; each part a zoo directory
    holding `<Family>/per-task/`) into one export in `zoo_dir`, ordered by task index. A task's expert does not
    depend on the tasks trained beside it, so the merge holds what one program training every part's tasks
    gives (tested). Parts must share MERGE_IDENTITY and hold disjoint tasks; ValueError (one line) before
    anything is written otherwise. `package`: `zoo_dir` is the package's own zoo. Returns the merged meta."""
    if not parts:
        raise ValueError("give at least one part to merge")
    target = zoo_dir / family.name / PER_TASK_DIR
    check_directory(target, "the zoo directory", package=package)
    for part in map(Path, parts):
        if part.exists() and not part.is_dir():
            raise ValueError(f"{part} is a file: --parts takes zoo folders, each holding {family.name}/{PER_TASK_DIR}/ "
                             "(a part's run directory's zoo/)")
    loaded = [load_per_task(family, Path(part) / family.name / PER_TASK_DIR) for part in parts]
    first = loaded[0].meta
    for part, experts in zip(parts, loaded):
        for name in MERGE_IDENTITY:
            if experts.meta.get(name) != first.get(name):
                raise ValueError(f"{part} has {name}={experts.meta.get(name)!r}, {parts[0]} has {first.get(name)!r}: "
                                 "the parts of one export must be trained with the same settings")
    indices = [i for experts in loaded for i in experts.meta["task_indices"]]
    repeated = sorted({i for i in indices if indices.count(i) > 1})
    if repeated:
        raise ValueError(f"training task(s) {repeated} are in more than one part: give each task's experts once")
    all_tasks = training_tasks(family, first["split_seed"])
    tasks = [task for experts in loaded for task in experts.meta["tasks"]]
    for i, task in zip(indices, tasks):
        if not np.allclose(task, family.task_to_array(all_tasks[i]), atol=1e-6):
            raise ValueError(f"task {i} of the parts is not training task {i} of data seed {first['split_seed']}")
    order = np.argsort(indices, kind="stable")
    actors = jax.tree_util.tree_map(lambda *xs: np.concatenate([np.asarray(x) for x in xs])[order],
                                    *[experts.actors for experts in loaded])
    finals = [r for experts in loaded
              for r in experts.meta.get("final_eval_returns") or [None] * len(experts.meta["tasks"])]
    meta = {**{k: v for k, v in first.items() if k != "family"},
            "task_indices": [indices[k] for k in order], "tasks": [tasks[k] for k in order],
            "train_wall_time_s": round(sum(experts.meta.get("train_wall_time_s", 0.0) for experts in loaded), 1),
            "final_eval_returns": [finals[k] for k in order], "parts": len(loaded),
            "eval_curve": _merged_curve([experts.meta for experts in loaded])}
    save_per_task_experts(target, family.name, actors, meta)
    return meta


def _merged_curve(metas: list[dict]) -> dict | None:
    """The parts' mean evaluation returns joined into the mean over all their tasks, at the steps every part
    evaluated at (None where a part recorded no curve)."""
    curves = [meta.get("eval_curve") for meta in metas]
    if not all(curves):
        return None
    steps = sorted(set.intersection(*(set(c["steps"]) for c in curves)))
    weights = np.array([len(meta["tasks"]) for meta in metas], float)
    at = [dict(zip(c["steps"], c["mean_return"])) for c in curves]
    return {"steps": steps, "mean_return": [float(np.average([a[s] for a in at], weights=weights)) for s in steps]}


def _save_checkpoint(out: Path, state, keys, rngs, episode: int, buffers: TaskBuffers, wall_time: float) -> None:
    """One file holds the whole training state, so a crash can't leave a mixed checkpoint."""
    meta = {"episode": episode, "keys": np.asarray(keys).tolist(), "rngs": [r.bit_generator.state for r in rngs],
            "wall_time": wall_time}
    atomic_save_npz(out / "checkpoint.npz", **buffers.state(),
                    state=np.frombuffer(flax.serialization.to_bytes(state), np.uint8), meta=np.array(json.dumps(meta)))


def _load_checkpoint(out: Path, buffers: TaskBuffers, template):
    with np.load(out / "checkpoint.npz") as arrays:
        buffers.restore(arrays)
        state = flax.serialization.from_bytes(template, arrays["state"].tobytes())
        meta = json.loads(str(arrays["meta"]))

    rngs = [generator_from_state(saved) for saved in meta["rngs"]]
    keys = jnp.asarray(np.asarray(meta["keys"], dtype=np.uint32))
    return state, keys, rngs, meta["episode"], meta["wall_time"]


class PerTaskExperts(Expert):
    """A family's per-task experts as one `Expert`: "the expert of training task i" is actor i.

    `act_for_collectors` runs the actors the collection plan names (Eq. 9 / 10: a training task's own
    expert, another training task's, the most similar or most different one's). Asked for the expert of
    any task (`policy(obs, task)`, the Oracle reference of a test task), it acts as the expert of the most
    similar training task: the nearest task array (every family's arrays keep its task distance's order),
    the first on ties (HalfCheetahDir's repeated directions), as App. C.2 picks a test task's collector.
    """

    def __init__(self, family: TaskFamily, actors, meta: dict):
        self.family = family
        self.meta = meta
        self.actors = actors  # stacked: a leading axis of n_tasks
        self.train_task_arrays = np.asarray(meta["tasks"], np.float32)  # (n_tasks, task_dim)
        self._sac = SAC(meta["obs_dim"], 0, meta["action_dim"], SACConfig(tuple(meta["hidden_dims"])))
        self._heads = jax.jit(self._all_heads)
        self._act = jax.jit(self._act_rows, static_argnames="deterministic")

    def _all_heads(self, actors, obs):
        """(n_tasks, K, action_dim) means and log-stds of every actor on every row (a map over actors:
        vmapping them hangs XLA's CPU runtime, see PerTaskSAC)."""
        return jax.lax.map(lambda actor: self._sac.actor_net.apply(actor, obs), actors)

    def _act_rows(self, actors, obs, collectors, key, deterministic: bool):
        means, log_stds = self._heads(actors, obs)
        rows = jnp.arange(obs.shape[0])
        mean, log_std = means[collectors, rows], log_stds[collectors, rows]
        if deterministic:
            return jnp.tanh(mean)
        return jnp.tanh(mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape))

    def nearest(self, task_arrays) -> jax.Array:
        """Index of the most similar training task of each row (first on ties)."""
        gaps = jnp.sum((jnp.asarray(task_arrays)[:, None, :] - self.train_task_arrays[None]) ** 2, axis=-1)
        return jnp.argmin(gaps, axis=1)

    def act_for_collectors(self, obs, collectors, task_arrays, deterministic: bool, key) -> np.ndarray:
        obs = jnp.asarray(obs, jnp.float32)
        rows = jnp.atleast_2d(obs)
        actions = self._act(self.actors, rows, jnp.atleast_1d(jnp.asarray(collectors)), key, deterministic)
        return np.asarray(actions if obs.ndim == 2 else actions[0])

    def act_from_arrays(self, obs, task_arrays, deterministic: bool, key) -> np.ndarray:
        return self.act_for_collectors(obs, self.nearest(np.atleast_2d(task_arrays)), task_arrays, deterministic, key)

    def mean_action(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        """Deterministic actions of each row's task's expert, for rows of any leading shape (every actor runs on
        every row, then each row takes its task's)."""
        rows, tasks = obs.reshape(-1, obs.shape[-1]), task_arrays.reshape(-1, task_arrays.shape[-1])
        actions = self._act(self.actors, rows, self.nearest(tasks), jax.random.PRNGKey(0), True)
        return actions.reshape(*obs.shape[:-1], actions.shape[-1])

    def task_mean_actions(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        """DPT's labels, (B, T) rows of B tasks: each task's expert on its own rows only (B actors gathered)."""
        experts = self.nearest(task_arrays)
        actors = jax.tree.map(lambda leaf: jnp.asarray(leaf)[experts], self.actors)
        return jnp.tanh(jax.vmap(lambda actor, rows: self._sac.actor_net.apply(actor, rows)[0])(actors, obs))

    def check_tasks(self, train_tasks: list) -> None:
        """ValueError unless these experts were trained for exactly `train_tasks` (a collection's)."""
        arrays = np.stack([self.family.task_to_array(t) for t in train_tasks])
        if arrays.shape == self.train_task_arrays.shape and np.allclose(arrays, self.train_task_arrays, atol=1e-6):
            return
        seed = self.meta.get("split_seed", SPLIT_SEED)
        indices = self.meta.get("task_indices") or []
        own = training_tasks(self.family, seed)
        covered = len(indices) == len(self.train_task_arrays) and all(0 <= i < len(own) for i in indices) and np.allclose(
            np.stack([self.family.task_to_array(own[i]) for i in indices]), self.train_task_arrays, atol=1e-6)
        missing = [i for i in range(len(own)) if i not in indices]
        same_split = len(own) == len(train_tasks) and np.allclose(
            arrays, np.stack([self.family.task_to_array(t) for t in own]), atol=1e-6)
        if covered and missing and same_split:  # a part of the export this collection needs
            name = self.family.name
            raise ValueError(f"the {name} per-task experts cover {len(indices)} of the {len(own)} training tasks of "
                             f"data seed {seed}; tasks {_ranges(missing)} have none: train them (`bati experts train "
                             f"--family {name} --per-task --tasks {' '.join(map(str, missing))}`) and join the parts "
                             f"with `bati experts merge --family {name} --parts ...`")
        if arrays.shape != self.train_task_arrays.shape or not np.allclose(arrays, self.train_task_arrays, atol=1e-6):
            raise ValueError(f"the {self.family.name} per-task experts were trained for the {len(self.train_task_arrays)} "
                             f"training tasks of data seed {self.meta.get('split_seed', SPLIT_SEED)}; this collection's "
                             "training tasks differ (another --seed or task split): use --experts conditioned")


def load_per_task(family: TaskFamily, directory: Path) -> PerTaskExperts:
    """The per-task experts of `family` in `directory` (`<zoo>/<Family>/per-task`)."""
    family_name = family.name
    meta_path = directory / "expert.json"
    if not meta_path.is_file():
        raise FileNotFoundError(
            f"no per-task experts for {family_name} in {directory}; train them with `bati experts train --family "
            f"{family_name} --per-task` (exported to runs/experts/{family_name}-per-task/zoo: the folder to give as "
            "--zoo-dir to collect, or as a part to `bati experts merge --parts`)")
    retrain = f"bati experts train --family {family_name} --per-task"
    meta = read_expert_meta(meta_path, retrain)
    if meta.get("family") != family_name or meta.get("kind") != "per-task":
        raise ValueError(f"{meta_path} holds {meta.get('kind', 'conditioned')} experts of {meta.get('family')!r}, "
                         f"not per-task experts of {family_name!r}")
    if meta.get("family_version", 1) != family.record.version:
        raise ValueError(f"{meta_path} holds experts for {family_name}'s env version {meta.get('family_version', 1)}, "
                         f"not the current version {family.record.version}; retrain them with `bati experts train "
                         f"--family {family_name} --per-task`")
    sac = SAC(meta["obs_dim"], 0, meta["action_dim"], SACConfig(tuple(meta["hidden_dims"])))
    n = len(meta["tasks"])
    template = jax.eval_shape(lambda: jax.lax.map(sac.init, jnp.zeros((n, 2), jnp.uint32))).actor.params
    actors = read_actors(directory / "actors.msgpack", template, retrain)
    return PerTaskExperts(family, actors, meta)


def _ranges(indices: list[int]) -> str:
    """[10, 11, 12, 15] as "10-12, 15"."""
    runs: list[list[int]] = []
    for i in indices:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)
