"""Offline training of a task-inference method together with IQL (Alg. 1).

One jitted step samples a batch of (tasks x transitions) on device, updates the method's
representation loss, and updates IQL on the latent the method produced, detached. Steps run in
jitted chunks (`lax.scan`), so the host only wakes up to log, evaluate and checkpoint.
A run directory holds config.json, metrics.jsonl, eval.jsonl, checkpoint.msgpack and eval.json.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from bati.data import FamilyData, ensure_family_data, sample_batch, sample_contexts
from bati.data.batch import TRANSITION_FIELDS
from bati.envs import TaskSplit
from bati.errors import BatiError
from bati.evaluate import Evaluator, reference_returns
from bati.experts import load as load_expert
from bati.io import (
    LOCK_NAME,
    append_jsonl,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    check_directory,
    check_run_config,
    git_commit,
    hold_lock,
    read_jsonl,
    read_jsonl_lines,
)
from bati.methods import MethodSpec, make_method
from bati.rl.iql import IQL, IQLConfig, IQLState

# Table 3, per family (PointGoal follows the reward families).
LATENT_DIMS = {"HopperParam": 40, "WalkerParam": 40}
NET_DIMS = {"HopperParam": (128, 128), "WalkerParam": (128, 128)}


class TrainingError(BatiError, RuntimeError):
    """Training cannot go on (e.g. a NaN loss); earlier checkpoints are left untouched."""


@dataclass
class TrainConfig:
    family: str = "PointGoal"
    method: str = "bati"
    seed: int = 0
    scale: Literal["quick", "paper"] = "quick"
    steps: int | None = None
    """Gradient steps (default: paper 100k, quick 3k)."""
    task_batch: int | None = None
    """Tasks in a batch (default: Table 3's 16, or all training tasks when there are fewer)."""
    batch_size: int | None = None
    """Transitions per task in a batch (default: paper 256, quick 64)."""
    context_length: int | None = None
    """Transitions in a training context (encoder methods) and, by default, in an evaluation context
    (default: the family's, one episode = 200; KuhnPoker 20 = 10 hands)."""
    eval_context_length: int | None = None
    """Transitions in an evaluation context (default: context_length; Table 1 evaluates other lengths)."""
    eval_every: int | None = None
    checkpoint_every: int | None = None
    log_every: int = 100
    noise: float | None = None
    """The family's eps for data and evaluation (default: the family's)."""
    data_seed: int = 0
    data_root: Path = Path("data")
    out_dir: Path | None = None
    """Run directory (default: runs/<family>/<scale>/<method>-seed<seed>)."""
    rl_hidden_dims: tuple[int, ...] | None = None
    """IQL's hidden dims (default: paper (256, 256) as Table 3, quick (128, 128))."""
    learning_rate: float = 3e-4
    iql: IQLConfig = field(default_factory=IQLConfig)

    episodes_per_task: int | None = None
    """Episodes per training task in the data (default: the scale's; a collection of other sizes needs
    its own --data-root)."""
    context_episodes: int | None = None
    """Episodes per test task in the context data (default: the scale's)."""
    n_train_tasks: int = 20
    """Training tasks (App. D.3 splits AntDir's 40 tasks 10/30 and 30/10)."""
    n_test_tasks: int = 20
    train_task_range: tuple[float, float] | None = None
    """Draw the training tasks' parameter uniformly from [LOW, HIGH) (Sec. 5.7: AntDir 0 3.14159)."""
    test_task_range: tuple[float, float] | None = None
    """Draw the test tasks' parameter uniformly from [LOW, HIGH) (Sec. 5.7: AntDir 3.14159 6.28319)."""

    @classmethod
    def from_record(cls, record: dict) -> TrainConfig:
        """The config a run directory's config.json records (lists back to tuples; `runtime` and keys
        this version does not know are ignored)."""
        names = {f.name for f in fields(cls)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in record.items() if k in names}
        if isinstance(values.get("iql"), dict):
            iql_names = {f.name for f in fields(IQLConfig)}
            values["iql"] = IQLConfig(**{k: tuple(v) if isinstance(v, list) else v
                                         for k, v in values["iql"].items() if k in iql_names})
        for name in ("data_root", "out_dir"):
            if values.get(name) is not None:
                values[name] = Path(values[name])
        return cls(**values)

    def task_split(self) -> TaskSplit:
        """The training / test task split of the run's data."""
        return TaskSplit(self.n_train_tasks, self.n_test_tasks,
                         None if self.train_task_range is None else tuple(self.train_task_range),
                         None if self.test_task_range is None else tuple(self.test_task_range))

    def resolved(self) -> TrainConfig:
        """Every default filled in (an explicit default and None give the same config) and every value
        checked, before any work: ValueError / TaskError with one line naming the setting."""
        from bati.envs import get_family
        from bati.methods import METHODS

        family = get_family(self.family)  # TaskError for an unknown family
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of: {', '.join(METHODS)}")
        if self.scale not in ("quick", "paper"):
            raise ValueError(f"unknown scale {self.scale!r}; choose quick or paper")
        for name in ("steps", "task_batch", "batch_size", "context_length", "eval_context_length", "eval_every",
                     "checkpoint_every", "log_every", "episodes_per_task", "context_episodes"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        for name in ("seed", "data_seed"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {getattr(self, name)!r}")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise ValueError(f"learning_rate must be a finite number > 0, got {self.learning_rate!r}")
        quick = self.scale == "quick"
        pick = lambda value, default: default if value is None else value  # noqa: E731
        steps = pick(self.steps, 3_000 if quick else 100_000)
        tenth = max(self.log_every, (steps // 10) // self.log_every * self.log_every)
        eval_every = pick(self.eval_every, tenth)
        out = pick(self.out_dir, Path("runs") / self.family / self.scale / f"{self.method}-seed{self.seed}")
        split = self.task_split().checked(family)  # TaskError for a bad count or range
        context_length = pick(self.context_length, family.default_context_length)
        resolved = replace(
            self,
            noise=family.validate_noise(self.noise),
            train_task_range=split.train_range,
            test_task_range=split.test_range,
            steps=steps,
            batch_size=pick(self.batch_size, 64 if quick else 256),
            task_batch=pick(self.task_batch, min(16, split.n_train)),
            eval_every=eval_every,
            context_length=context_length,
            eval_context_length=pick(self.eval_context_length, context_length),
            checkpoint_every=pick(self.checkpoint_every, eval_every),
            out_dir=Path(out),
            data_root=Path(self.data_root),
            rl_hidden_dims=tuple(pick(self.rl_hidden_dims, (128, 128) if quick else (256, 256))),
        )
        resolved.iql = replace(self.iql, hidden_dims=resolved.rl_hidden_dims, learning_rate=self.learning_rate,
                               discrete=family.discrete_actions)
        if resolved.task_batch > split.n_train:
            raise ValueError(f"task_batch ({resolved.task_batch}) must be at most n_train_tasks ({split.n_train}): "
                             "a batch draws distinct training tasks")
        if resolved.eval_every % self.log_every or resolved.checkpoint_every % self.log_every:
            raise ValueError(f"eval_every ({resolved.eval_every}) and checkpoint_every ({resolved.checkpoint_every}) "
                             f"must be multiples of log_every ({self.log_every})")
        return resolved


class TrainState(NamedTuple):
    method: Any
    method_opt: Any
    iql: IQLState
    step: jax.Array


class Trainer:
    """Builds the method, IQL and the jitted chunk of training steps for one config."""

    def __init__(self, config: TrainConfig, data: FamilyData, expert=None):
        """`expert` labels actions for methods that imitate one (DPT); default: the family's shipped expert."""
        self.config = config
        self.data = data
        dims = NET_DIMS.get(config.family, (64, 64))
        family_spec = MethodSpec(
            obs_dim=data.obs_dim, action_dim=data.action_dim, task_dim=data.task_dim,
            n_train_tasks=len(data.train_tasks), latent_dim=LATENT_DIMS.get(config.family, 5),
            encoder_dims=dims, decoder_dims=dims, family=config.family, discrete_actions=config.iql.discrete,
        )
        self.method = make_method(config.method, family_spec)
        self.spec = self.method.spec  # a method may change the latent (Oracle: the task array; DPT: its width)
        self.iql = IQL(data.obs_dim, self.spec.latent_dim, data.action_dim, config.iql)
        self.optimizer = optax.adam(config.learning_rate)
        self.train_task_arrays = jnp.asarray(data.train_task_arrays, jnp.float32)
        if self.method.needs_expert_actions:
            self.expert = expert or load_expert(config.family)
        self.run_chunk = jax.jit(self._run_chunk, static_argnames="length")
        # k seeds in one program: states and keys stacked on a leading axis, the data shared.
        self.run_chunks = jax.jit(self._run_chunks, static_argnames="length")

    def init(self, key: jax.Array) -> TrainState:
        k_method, k_iql = jax.random.split(key)
        params = self.method.init(k_method)
        return TrainState(params, self.optimizer.init(params), self.iql.init(k_iql), jnp.zeros((), jnp.int32))

    def step(self, state: TrainState, key: jax.Array, data) -> tuple[TrainState, dict]:
        """One training step: representation loss + IQL on the detached latent."""
        c = self.config
        k_batch, k_context, k_loss = jax.random.split(key, 3)
        batch = sample_batch(data, k_batch, c.task_batch, c.batch_size)
        batch["task_arrays"] = self.train_task_arrays[batch["task_ids"]]
        if self.method.needs_context:
            batch["context"] = sample_contexts(data, k_context, batch["task_ids"], c.context_length)
        if self.method.needs_positive_context:
            batch["positive_context"] = sample_contexts(data, jax.random.fold_in(k_context, 1), batch["task_ids"],
                                                        c.context_length)
        if self.method.needs_expert_actions:
            task_arrays = jnp.broadcast_to(batch["task_arrays"][:, None], batch["observations"].shape[:2] +
                                           batch["task_arrays"].shape[-1:])
            batch["expert_actions"] = self.expert.mean_action(batch["observations"], task_arrays)
        (rep_loss, (z, rep_metrics)), grads = jax.value_and_grad(self.method.loss, has_aux=True)(
            state.method, batch, k_loss
        )
        updates, method_opt = self.optimizer.update(grads, state.method_opt, state.method)
        method_params = optax.apply_updates(state.method, updates)

        if self.method.acts_itself:  # e.g. DPT: no IQL policy to train
            iql_state, iql_metrics = state.iql, {}
        else:
            flat = {k: batch[k].reshape((-1,) + batch[k].shape[2:]) for k in TRANSITION_FIELDS}
            z_flat = jnp.repeat(jax.lax.stop_gradient(z), c.batch_size, axis=0)
            iql_state, iql_metrics = self.iql.update(state.iql, flat, z_flat)
        metrics = {"representation_loss": rep_loss, **rep_metrics, **iql_metrics}
        return TrainState(method_params, method_opt, iql_state, state.step + 1), metrics

    def _run_chunk(self, state: TrainState, base_key: jax.Array, data, length: int):
        """`length` steps; step t uses fold_in(base_key, t), so resuming replays the same keys."""

        def body(state, _):
            return self.step(state, jax.random.fold_in(base_key, state.step), data)

        state, metrics = jax.lax.scan(body, state, None, length=length)
        return state, jax.tree_util.tree_map(jnp.mean, metrics)

    def _run_chunks(self, states: TrainState, base_keys: jax.Array, data, length: int):
        """`_run_chunk` for k runs (seeds) at once: states and keys stacked on axis 0, data shared."""
        return jax.vmap(lambda state, key: self._run_chunk(state, key, data, length))(states, base_keys)


def train(config: TrainConfig, show_progress: bool = True) -> dict:
    """Train (or resume) one run; returns its final evaluation summary (also in eval.json)."""
    return train_seeds(config, (config.seed,), show_progress=show_progress)[0]


def train_seeds(config: TrainConfig, seeds: tuple[int, ...], show_progress: bool = True,
                runs_dir: Path | None = None) -> list[dict]:
    """Train (or resume) one run per seed of one config as one compiled program vmapped over seeds.

    Each seed has its own run directory (`runs_dir/<method>-seed<s>`, default: the config's default
    directory), metrics, evaluations and checkpoints, exactly as a run trained alone; seed s gives the
    numbers of the single-seed run s to float tolerance. Runs resumed from checkpoints of different
    steps are first brought level (the ones behind advance alone), then go on together.
    Returns the runs' summaries (also in each eval.json), in the order of `seeds`.
    """
    seeds = check_seeds(seeds)
    if len(seeds) > 1 and config.out_dir is not None and runs_dir is None:
        raise ValueError("several seeds need one directory each: give runs_dir (the parent), not out_dir")
    configs = [replace(config, seed=s, out_dir=(runs_dir / f"{config.method}-seed{s}") if runs_dir else
                       config.out_dir).resolved() for s in seeds]
    _check_paths(configs)
    with contextlib.ExitStack() as claimed:
        for c in configs:  # claim the run directories (or refuse them) before any work
            claimed.enter_context(hold_lock(c.out_dir / LOCK_NAME, f"the run directory {c.out_dir}"))
            claimed.enter_context(_forgotten_unless_started(c.out_dir))
            _check_run_dir(c.out_dir, c)
        return _train_claimed(configs, show_progress)


def _check_paths(configs: list[TrainConfig]) -> None:
    """Refuse run directories and a data root that are files (or unwritable where we must write) with
    one line, before anything is written anywhere."""
    from bati.data import store

    for c in configs:
        check_directory(c.out_dir, "the run directory")
    c = configs[0]
    collection = store.collection_dir(c.data_root, c.family, c.scale, c.data_seed, c.noise, c.task_split())
    check_directory(c.data_root, "the data root", writable=not (collection / store.MANIFEST).is_file())


@contextlib.contextmanager
def _forgotten_unless_started(out: Path):
    """A run directory this call creates is removed again if it fails before its first record (e.g. no
    data, Ctrl-C while collecting): the next attempt may then use other settings without being refused."""
    fresh = not (out / "config.json").exists()
    try:
        yield
    except BaseException:
        left = {p.name for p in out.iterdir()} if out.is_dir() else set()
        if fresh and left <= {"config.json", LOCK_NAME}:
            (out / "config.json").unlink(missing_ok=True)
        raise


def _train_claimed(configs: list[TrainConfig], show_progress: bool) -> list[dict]:
    """train_seeds once its run directories are checked, claimed and locked."""
    config, seeds = configs[0], [c.seed for c in configs]
    data = ensure_family_data(config.family, config.scale, config.data_seed, config.noise, config.data_root,
                              n_episodes=config.episodes_per_task, n_context_episodes=config.context_episodes,
                              progress=show_progress, tasks=config.task_split())
    trainer = Trainer(config, data)
    evaluator = Evaluator(trainer.method, trainer.iql, data, config.eval_context_length)
    runs = [_SeedRun.open(c, trainer) for c in configs]
    start = time.perf_counter()
    progress = Progress(
        TextColumn(f"[bold]{config.method} on {config.family}" + (f" x{len(seeds)} seeds" if len(seeds) > 1 else "")),
        BarColumn(), TextColumn("{task.completed:,}/{task.total:,}"), TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress,
    )
    with progress:
        bar = progress.add_task("train", total=config.steps, completed=min(r.step for r in runs), status="")
        while (behind := min(r.step for r in runs)) < config.steps:
            group = [r for r in runs if r.step == behind]
            until = min([r.step for r in runs if r.step > behind] + [config.steps])
            _advance(trainer, evaluator, data, group, until, start, progress, bar)
    references = reference_returns(data)
    session = {"device": describe_device(), "jax_version": jax.__version__, "commit": git_commit(),
               "wall_time_s": round(time.perf_counter() - start, 2)}
    summaries = []
    for run in runs:
        summary = {**summarize_run(run.out), "reference_returns": references, **session,
                   "data": {k: data.manifest.get(k) for k in ("n_episodes", "n_context_episodes", "transitions")}}
        atomic_write_json(run.out / "eval.json", summary)
        summaries.append(summary)
    return summaries


def check_seeds(seeds) -> tuple[int, ...]:
    """The seeds as a tuple, or ValueError unless they are distinct integers >= 0, at least one."""
    seeds = tuple(seeds)
    if not seeds or len(set(seeds)) != len(seeds) or any(not isinstance(s, int) or s < 0 for s in seeds):
        raise ValueError(f"seeds must be distinct integers >= 0 (at least one), got {list(seeds)}")
    return seeds


@dataclass
class _SeedRun:
    """One seed's run directory and its state on the host side of the training loop."""

    config: TrainConfig
    state: TrainState
    base_key: jax.Array

    @property
    def out(self) -> Path:
        return self.config.out_dir

    @property
    def step(self) -> int:
        return int(self.state.step)

    @classmethod
    def open(cls, config: TrainConfig, trainer: Trainer) -> _SeedRun:
        """Start fresh or resume from the run directory's checkpoint (the directory is already claimed)."""
        base_key = jax.random.PRNGKey(config.seed)
        state = trainer.init(jax.random.fold_in(base_key, 0))
        if (config.out_dir / "checkpoint.msgpack").exists():
            state = _load_checkpoint(config.out_dir / "checkpoint.msgpack", state)
        _drop_records_after(config.out_dir, int(state.step))
        return cls(config, state, base_key)


def _advance(trainer: Trainer, evaluator: Evaluator, data, runs: list[_SeedRun], until: int, start: float,
             progress, bar) -> None:
    """Train `runs` (all at the same step) together up to step `until`: chunks of log_every steps,
    vmapped over the runs when there are several, with their logs, evaluations and checkpoints."""
    c = runs[0].config
    step = runs[0].step
    train_keys = jnp.stack([jax.random.fold_in(r.base_key, 1) for r in runs])
    states = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[r.state for r in runs])
    while step < until:
        length = min(c.log_every, until - step)
        if len(runs) == 1:  # the plain program: a run trained alone gives exactly its own numbers
            state, metrics = trainer.run_chunk(runs[0].state, train_keys[0], data.train, length=length)
            states = jax.tree_util.tree_map(lambda x: x[None], state)
            metrics = jax.tree_util.tree_map(lambda x: x[None], metrics)
        else:
            states, metrics = trainer.run_chunks(states, train_keys, data.train, length=length)
        step += length
        metrics = jax.device_get(metrics)
        for j, run in enumerate(runs):
            run.state = jax.tree_util.tree_map(lambda x, j=j: x[j], states)
            record = {k: float(v[j]) for k, v in metrics.items()}
            bad = [k for k, v in record.items() if not math.isfinite(v)]
            if bad:
                raise TrainingError(f"{run.out}: non-finite {', '.join(bad)} at step {step}; the last good "
                                    f"checkpoint (if any) is untouched in {run.out / 'checkpoint.msgpack'}")
            append_jsonl(run.out / "metrics.jsonl", {"step": step, "wall_time": time.perf_counter() - start, **record})
        if step % c.eval_every == 0 or step == c.steps:
            keys = jnp.stack([jax.random.fold_in(r.base_key, 2 + step) for r in runs])
            results = evaluator.evaluate_runs(states, keys, [r.config.seed * 7919 + step for r in runs])
            for run, result in zip(runs, results):
                append_jsonl(run.out / "eval.jsonl", {"step": step, **result.summary()})
            progress.update(bar, status=f"p_test {np.mean([r.returns['p_test'].mean() for r in results]):.1f} "
                                        f"p_train {np.mean([r.returns['p_train'].mean() for r in results]):.1f}")
        if step % c.checkpoint_every == 0 or step == c.steps:
            for run in runs:
                atomic_write_bytes(run.out / "checkpoint.msgpack", flax.serialization.to_bytes(run.state))
        progress.update(bar, completed=step)  # the runs behind set the pace


def describe_device() -> str:
    """The accelerator JAX runs on, as JAX reports it (e.g. "gpu: NVIDIA H100 80GB HBM3 x1")."""
    devices = jax.devices()
    first = devices[0]
    kind = first.device_kind if first.platform != "cpu" else f"{os.cpu_count()}-core CPU ({platform.machine()})"
    return f"{first.platform}: {kind} x{len(devices)}"


def summarize_run(out: Path, last: int = 5) -> dict:
    """The paper's number: mean of the last `last` evaluations, per context distribution."""
    evals = read_jsonl(out / "eval.jsonl", require=("step",))
    if not evals:
        raise ValueError(f"{out / 'eval.jsonl'} holds no evaluation; resume the run to redo them")
    config = read_run_config(out)
    tail = evals[-last:]
    summary = {"family": config["family"], "method": config["method"], "seed": config["seed"],
               "scale": config["scale"], "steps": evals[-1]["step"], "evaluations_averaged": len(tail)}
    for source in ("p_test", "p_train"):
        summary[f"{source}_return"] = float(np.mean([e[f"{source}_return"] for e in tail]))
        summary[f"{source}_inference_error"] = float(np.mean([e[f"{source}_inference_error"] for e in tail]))
        summary[f"{source}_task_returns"] = evals[-1][f"{source}_task_returns"]
    curve_keys = ("step", "p_test_return", "p_train_return", "p_test_inference_error", "p_train_inference_error")
    summary["curve"] = [{k: e[k] for k in curve_keys if k in e} for e in evals]
    # a method's own numbers (e.g. BATI-auto's calibrated state weight), averaged like the returns
    extra = [k for k, v in evals[-1].items() if k not in curve_keys and isinstance(v, (int, float))
             and all(isinstance(e.get(k), (int, float)) for e in tail)]
    if extra:
        summary["diagnostics"] = {k: float(np.mean([e[k] for e in tail])) for k in extra}
    summary["config"] = {k: v for k, v in config.items() if k != "runtime"}
    return summary


# Where a run lives is not what it is: these fields may differ when a run directory is moved or resumed.
NOT_IDENTITY = ("out_dir", "data_root")
# Fields added to TrainConfig after runs were recorded: a saved config without one had this value.
LATER_FIELDS = {"n_train_tasks": 20, "n_test_tasks": 20, "train_task_range": None, "test_task_range": None}


def differing_settings(saved: dict, current: dict, keys) -> list[str]:
    """The keys whose saved and current values differ (a key added later and absent from the saved
    config counts as its old value, LATER_FIELDS)."""
    def old(k):
        return saved[k] if k in saved else LATER_FIELDS.get(k, saved.get(k))

    return [k for k in keys if old(k) != current.get(k)]


def _check_run_dir(out: Path, config: TrainConfig) -> None:
    """A run directory belongs to one resolved config: refuse to resume a run that differs in any setting."""
    current = json.loads(json.dumps(asdict(config), default=str))
    identity = tuple(k for k in current if k not in NOT_IDENTITY)
    runtime = {"device": describe_device(), "jax_version": jax.__version__, "commit": git_commit()}
    check_run_config(out / "config.json", {**current, "runtime": runtime}, identity, differing_settings)


def _load_checkpoint(path: Path, template: TrainState) -> TrainState:
    """The checkpoint at `path`: ValueError naming the file when it is not a checkpoint at all (damaged:
    checkpoints are replaced atomically, so a kill never leaves half of one) or holds other networks."""
    try:
        raw = flax.serialization.msgpack_restore(path.read_bytes())
        if not isinstance(raw, dict):
            raise ValueError(f"it holds a {type(raw).__name__}")
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path} is damaged: not a readable checkpoint ({type(err).__name__}: {err}); delete it to "
                         "restart the run from step 0") from err
    try:
        state = flax.serialization.from_state_dict(template, raw)
        shapes = jax.tree_util.tree_map(jnp.shape, (template, state))
        if shapes[0] != shapes[1]:
            raise ValueError("parameter shapes differ")
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path} does not match this run's networks (another family or method?): {err}") from err
    return state


def load_checkpoint(path: Path, template: TrainState) -> TrainState:
    """A run's saved TrainState (shaped like `template`); ValueError naming the file if it does not fit."""
    return _load_checkpoint(path, template)


def _drop_records_after(out: Path, step: int) -> None:
    """Forget log lines written after the checkpoint we resume from (they will be redone)."""
    for name in ("metrics.jsonl", "eval.jsonl"):
        path = out / name
        if path.exists():  # a torn last line (a kill mid-append) is dropped with a warning
            text = "".join(line + "\n" for line, record in read_jsonl_lines(path, require=("step",))
                           if record["step"] <= step)
            if text.encode() != path.read_bytes():
                atomic_write_text(path, text)


def read_run_config(out: Path) -> dict:
    """A run directory's config.json as a dict; one-line errors naming what is wrong (not a directory,
    no config, not JSON, not an object)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a run directory")
    path = out / "config.json"
    if not path.is_file():
        raise ValueError(f"{out} is not a run directory: it has no config.json")
    try:
        config = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON ({err})") from err
    if not isinstance(config, dict):
        raise ValueError(f"{path} holds a JSON {type(config).__name__}, not a run's config")
    return config
