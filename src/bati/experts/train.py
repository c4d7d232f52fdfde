"""Train a family's task-conditioned SAC expert, with periodic checkpoints and resume.

Each iteration steps `num_envs` envs in lockstep (each on its own task, resampled from the
task space every episode, eps = 0) and then applies `num_envs * updates_per_step` SAC updates
in one jitted call. Checkpoints are taken at episode boundaries, so a resumed run replays
exactly what the uninterrupted run would have done.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import jax
import numpy as np
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from bati.checks import check_integer, check_number
from bati.cli_hints import DEFAULT_IN_DOC
from bati.envs import TaskFamily, get_family
from bati.envs.rollout import LockstepEnvs, rollout
from bati.experts.per_task import TASK_AXES, default_task_axis
from bati.experts.sac import (
    RESUME_IDENTITY,
    SAC,
    SACConfig,
    generator_from_state,
    state_from_bytes,
    state_to_bytes,
)
from bati.experts.zoo import save_expert
from bati.io import append_jsonl, atomic_save_npz, check_directory, check_run_config
from bati.processes import stall_watchdog

MAX_UPDATES_PER_STEP = 1_000.0
"""More SAC updates per transition than this is a typo, not a plan (the default is 0.5)."""


@dataclass
class ExpertTrainConfig:
    family: str
    total_steps: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Environment transitions (default: the family's FamilyRecord.expert_steps; App. C.2 gives none:
    chosen by measured learning curves)."""
    num_envs: int = 4
    updates_per_step: float = 0.5
    """SAC updates per environment transition (env steps are cheap next to updates on CPU)."""
    start_steps: int = 5_000
    """Transitions collected with uniform random actions before the policy acts."""
    seed: int = 0
    checkpoint_every: int = 20_000
    eval_every: int = 20_000
    eval_tasks: int = 8
    out_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Run directory (default: runs/experts/<family>)."""
    export_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Zoo directory the finished actor is exported into, as <export_dir>/<family>/ (default: the run
    directory's zoo/, for `--zoo-dir RUN_DIR/zoo`); collect with `--zoo-dir` pointing there."""
    into_package: bool = False
    """Export into the package's own zoo instead (src/bati/experts/zoo: the expert every later collection
    of this family uses, replacing the shipped one)."""
    per_task: bool = False
    """Train one SAC per training task (App. C.2: the 20 training tasks of data seed 0), all as one
    program (bati.experts.per_task); `total_steps` is then per task (default: FamilyRecord.per_task_expert_steps)."""
    tasks: tuple[int, ...] | None = None
    """With --per-task: train only these training tasks' experts (indices; default all). Each gets the
    parameters the full program gives it."""
    update_every: int = 50
    """With --per-task: environment steps per task between update calls (each applies
    update_every * updates_per_step updates to every task)."""
    task_axis: Literal["auto", "map", "vmap"] = "auto"
    """With --per-task: how one call updates every task, `map` (one after another) or `vmap` (batched); `auto`:
    the faster on this backend (map on the CPU, vmap on an accelerator; benchmarks/per_task_update.py)."""
    sac: SACConfig = field(default_factory=SACConfig)

    def resolved(self) -> ExpertTrainConfig:
        """Every default filled in and every value checked, before any work (one line naming the setting)."""
        return self.resolve().config

    def resolve(self) -> ResolvedExperts:
        """The run resolved once: its config with every default filled in, and its family object."""
        family = get_family(self.family)  # the one lookup by name; an unknown family is one line
        record = family.record
        if record.discrete_actions:
            raise ValueError(f"{self.family}'s expert is not a SAC (KuhnPoker: the exact best response, "
                             "bati.experts.kuhn, computed when needed): there is no SAC expert to train")
        budget = record.per_task_expert_steps if self.per_task else record.expert_steps
        for name in ("total_steps", "num_envs", "checkpoint_every", "eval_every", "eval_tasks", "update_every"):
            hint = f" (leave it out for the family's {budget:,})" if name == "total_steps" and budget else ""
            if getattr(self, name) is not None:  # None: the default; 0 is refused, never the default
                check_integer(name, getattr(self, name), hint=hint)
        for name in ("start_steps", "seed"):
            check_integer(name, getattr(self, name), low=0)
        check_number("updates_per_step", self.updates_per_step, positive=False, at_most=MAX_UPDATES_PER_STEP)
        self.sac.check()
        if self.into_package and self.export_dir is not None:
            raise ValueError("give either --export-dir or --into-package, not both")
        out = self.out_dir or Path("runs/experts") / (f"{self.family}-per-task" if self.per_task else self.family)
        export = _default_zoo() if self.into_package else self.export_dir or out / "zoo"
        if self.tasks is not None and not self.per_task:
            raise ValueError("--tasks picks per-task experts: give it with --per-task")
        if self.tasks is not None:
            n = len(family.split_tasks(0)[0])
            if not self.tasks or len(set(self.tasks)) != len(self.tasks) or not all(
                    isinstance(i, int) and 0 <= i < n for i in self.tasks):
                raise ValueError(f"tasks={list(self.tasks)}: give distinct training-task indices in 0..{n - 1}")
        if budget is None and self.total_steps is None:
            field_name = "per_task_expert_steps" if self.per_task else "expert_steps"
            raise ValueError(f"{self.family} has no {'per-task ' if self.per_task else ''}expert budget (its "
                             f"FamilyRecord.{field_name} is None): give --total-steps, or set it in the record")
        total = budget if self.total_steps is None else self.total_steps
        if total <= self.start_steps:
            raise ValueError(f"total_steps ({total:,}) must exceed start_steps ({self.start_steps:,}): SAC would never "
                             "update and the exported expert would be untrained")
        _check_some_update(self, total, record.episode_length)
        if self.task_axis not in ("auto",) + TASK_AXES:
            raise ValueError(f"task_axis={self.task_axis!r}: choose auto, {' or '.join(TASK_AXES)}")
        axis = default_task_axis() if self.task_axis == "auto" else self.task_axis
        config = ExpertTrainConfig(**{**asdict(self), "total_steps": total, "out_dir": out, "export_dir": export,
                                      "task_axis": axis, "sac": self.sac})
        return ResolvedExperts(config, family)


def _check_some_update(config: ExpertTrainConfig, total: int, episode_length: int) -> None:
    """ValueError (one line) where the budget leaves no SAC update: an expert is never exported untrained."""
    if config.updates_per_step == 0:
        raise ValueError("updates_per_step=0: SAC would never update and the exported expert would be untrained")
    if not config.per_task:
        if round(config.num_envs * config.updates_per_step) == 0:
            raise ValueError(f"updates_per_step={config.updates_per_step:g} x num_envs={config.num_envs} rounds to 0 SAC "
                             "updates per lockstep step: the exported expert would be untrained")
        return
    collected = -(-total // episode_length) * episode_length  # whole episodes
    first = max(config.update_every, -(-config.start_steps // config.update_every) * config.update_every)
    if first > collected:
        raise ValueError(f"no SAC update would run: updates come every update_every={config.update_every:,} steps "
                         f"from start_steps={config.start_steps:,} on (the first at {first:,}), but each task collects "
                         f"{collected:,} (total_steps {total:,} in whole episodes of {episode_length}): the exported "
                         "experts would be untrained")


@dataclass(frozen=True)
class ResolvedExperts:
    """An expert training run resolved at its entry point (`ExpertTrainConfig.resolve`)."""

    config: ExpertTrainConfig
    family: TaskFamily

    @property
    def collected_steps(self) -> int:
        """The transitions (per task, with per_task) a run collects: its budget in whole episodes of every
        lockstep env."""
        per_round = self.family.record.episode_length * (1 if self.config.per_task else self.config.num_envs)
        return -(-self.config.total_steps // per_round) * per_round


class ReplayBuffer:
    """Flat numpy arrays, filled in order, sampled uniformly."""

    FIELDS = ("observations", "tasks", "actions", "rewards", "next_observations")

    def __init__(self, capacity: int, obs_dim: int, task_dim: int, action_dim: int):
        dims = {"observations": obs_dim, "tasks": task_dim, "actions": action_dim, "rewards": None,
                "next_observations": obs_dim}
        self.data = {k: np.zeros((capacity,) if d is None else (capacity, d), np.float32) for k, d in dims.items()}
        self.size = 0

    def add(self, **batch: np.ndarray) -> None:
        n = len(batch["rewards"])
        for k in self.FIELDS:
            self.data[k][self.size : self.size + n] = batch[k]
        self.size += n

    def sample(self, rng: np.random.Generator, num_batches: int, batch_size: int) -> dict[str, np.ndarray]:
        idx = rng.integers(0, self.size, size=(num_batches, batch_size))
        return {k: v[idx] for k, v in self.data.items()}

    def state(self) -> dict[str, np.ndarray]:
        return {k: v[: self.size] for k, v in self.data.items()}

    def restore(self, arrays) -> None:
        self.size = len(arrays["rewards"])
        for k in self.FIELDS:
            self.data[k][: self.size] = arrays[k]


def train_expert(config: ExpertTrainConfig, show_progress: bool = True) -> Path:
    """Train (or resume) the expert of `config.family` (or, with `per_task`, its per-task experts);
    returns the run directory."""
    return train_resolved(config.resolve(), show_progress)


def train_resolved(run: ResolvedExperts, show_progress: bool = True) -> Path:
    """`train_expert` of a resolved run."""
    if run.config.per_task:
        from bati.experts.per_task import train_per_task_experts

        return train_per_task_experts(run, show_progress)
    config, family = run.config, run.family
    out: Path = config.out_dir
    check_directory(out, "the expert's run directory")  # a file, or not writable: now, not after training
    check_directory(config.export_dir / config.family, "the zoo directory", package=config.into_package)
    probe = family.make_env(family.sample_tasks(1, seed=0)[0], noise=0.0)
    obs_dim, action_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    sac = SAC(obs_dim, family.task_dim, action_dim, config.sac)
    updates_per_iter = int(round(config.num_envs * config.updates_per_step))

    key = jax.random.PRNGKey(config.seed)
    key, init_key = jax.random.split(key)
    state = sac.init(init_key)
    rng = np.random.default_rng(config.seed)
    buffer = ReplayBuffer(config.total_steps + config.num_envs * family.record.episode_length, obs_dim, family.task_dim, action_dim)
    episode, wall_time = 0, 0.0
    _check_config(out, config)
    if (out / "checkpoint.npz").exists():
        state, key, rng, episode, wall_time = _load_checkpoint(out, buffer, state)
    steps = buffer.size

    envs = LockstepEnvs(family, noise=0.0)
    progress = Progress(
        TextColumn(f"[bold]{config.family} expert"), BarColumn(), TextColumn("{task.completed:,}/{task.total:,}"),
        TextColumn("{task.fields[status]}"), TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress,
    )
    start = time.perf_counter() - wall_time
    last_eval = None
    with progress, envs, stall_watchdog() as alive:
        bar = progress.add_task("train", total=config.total_steps, completed=steps, status="")
        while steps < config.total_steps:
            tasks = family.sample_tasks(config.num_envs, rng)
            task_arrays = np.stack([family.task_to_array(t) for t in tasks])
            first_seed = config.seed * 1_000_003 + episode * config.num_envs
            obs = envs.reset(tasks, range(first_seed, first_seed + config.num_envs)).astype(np.float32)
            metrics = {}
            for _ in range(family.record.episode_length):
                if steps < config.start_steps:
                    actions = rng.uniform(-1.0, 1.0, size=(config.num_envs, action_dim)).astype(np.float32)
                else:
                    key, act_key = jax.random.split(key)
                    actions = np.asarray(sac.act(state.actor.params, obs, task_arrays, act_key, deterministic=False))
                step = envs.step(actions)
                next_obs = step.observations.astype(np.float32)
                buffer.add(observations=obs, tasks=task_arrays, actions=actions, rewards=step.rewards.astype(np.float32),
                           next_observations=next_obs)
                obs = next_obs
                steps += config.num_envs
                if steps >= config.start_steps and updates_per_iter > 0:
                    batches = buffer.sample(rng, updates_per_iter, config.sac.batch_size)
                    key, update_key = jax.random.split(key)
                    state, metrics = sac.update_many(state, batches, update_key)
            episode += 1
            progress.update(bar, completed=min(steps, config.total_steps))
            alive()
            crossed = lambda every: steps // every > (steps - config.num_envs * family.record.episode_length) // every
            if crossed(config.eval_every) or steps >= config.total_steps:
                last_eval = evaluate_expert(sac, state.actor.params, family, config.eval_tasks, seed=12345)
                record = {"steps": steps, "episode": episode, "wall_time": time.perf_counter() - start,
                          **{k: float(v) for k, v in metrics.items()}, **last_eval}
                append_jsonl(out / "metrics.jsonl", record)
                progress.update(bar, status=f"eval return {last_eval['eval_return']:.1f}")
            if crossed(config.checkpoint_every) or steps >= config.total_steps:
                _save_checkpoint(out, state, key, rng, episode, buffer, time.perf_counter() - start)

    meta = {"obs_dim": obs_dim, "task_dim": family.task_dim, "action_dim": action_dim,
            "family_version": family.record.version,
            "hidden_dims": list(config.sac.hidden_dims), "train_steps": steps, "seed": config.seed,
            "train_wall_time_s": round(time.perf_counter() - start, 1), "final_eval": last_eval}
    save_expert(config.export_dir / config.family, config.family, state.actor.params, meta)
    return out


def train_and_export(config: ExpertTrainConfig, *, console) -> None:
    """`bati experts train`: every setting checked before any work (one line), the expert trained, and where
    it was exported printed on the rich `console`."""
    run = config.resolve()
    if run.collected_steps != run.config.total_steps:
        console.print(f"total_steps {run.config.total_steps:,} is collected in whole episodes: "
                      f"{run.collected_steps:,} transitions{' per task' if run.config.per_task else ''}", soft_wrap=True)
    config, out = run.config, train_resolved(run)
    where = "the package zoo (every later collection of it uses this expert)" if config.into_package else \
        f"{config.export_dir} (collect with --zoo-dir {config.export_dir})"
    if config.per_task:
        where += " as per-task experts (collect with --experts per-task)"
    console.print(f"expert run in {out}; exported to {where}", soft_wrap=True)

def evaluate_expert(sac: SAC, actor, family, n_tasks: int, seed: int) -> dict[str, float]:
    """Deterministic return (eps = 0) on n fixed tasks; velocity error where it applies."""
    tasks = family.sample_tasks(n_tasks, seed)
    task_arrays = np.stack([family.task_to_array(t) for t in tasks])
    key = jax.random.PRNGKey(0)
    episodes = rollout(family, tasks, lambda o, _: sac.act(actor, o, task_arrays, key, deterministic=True),
                       noise=0.0, seed=seed)
    return {"eval_return": float(episodes.returns.mean())}


def _default_zoo() -> Path:
    from bati.experts.zoo import ZOO_DIR

    return ZOO_DIR


def _check_config(out: Path, config: ExpertTrainConfig) -> None:
    """Refuse to resume a run directory written with another family, seed, env count or SAC setting."""
    current = json.loads(json.dumps(asdict(config), default=str))
    check_run_config(out / "config.json", current, RESUME_IDENTITY)


def _save_checkpoint(out: Path, state, key, rng, episode, buffer, wall_time: float) -> None:
    """One file holds the whole training state, so a crash can't leave a mixed checkpoint."""
    meta = {"episode": episode, "key": np.asarray(key).tolist(), "rng": rng.bit_generator.state,
            "wall_time": wall_time}
    atomic_save_npz(out / "checkpoint.npz", **buffer.state(),
                    state=np.frombuffer(state_to_bytes(state), np.uint8), meta=np.array(json.dumps(meta)))


def _load_checkpoint(out: Path, buffer: ReplayBuffer, template):
    with np.load(out / "checkpoint.npz") as arrays:
        buffer.restore(arrays)
        state = state_from_bytes(template, arrays["state"].tobytes())
        meta = json.loads(str(arrays["meta"]))
    rng = generator_from_state(meta["rng"])
    key = jax.numpy.asarray(np.asarray(meta["key"], dtype=np.uint32))
    return state, key, rng, meta["episode"], meta["wall_time"]
