"""Offline training of a task-inference method together with IQL (Alg. 1).

One jitted step samples a batch of (tasks x transitions) on device, updates the method's
representation loss, and updates IQL on the latent the method produced, detached. Steps run in
jitted chunks (`lax.scan`), so the host only wakes up to log, evaluate and checkpoint.
A run directory holds config.json, metrics.jsonl, eval.jsonl, checkpoint.msgpack and eval.json.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
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
from bati.errors import BatiError
from bati.evaluate import Evaluator
from bati.experts import load as load_expert
from bati.io import append_jsonl, atomic_write_bytes, atomic_write_json, atomic_write_text, check_run_config
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
    task_batch: int = 16
    batch_size: int | None = None
    """Transitions per task in a batch (default: paper 256, quick 64)."""
    context_length: int = 200
    """Transitions in a context (training contexts of encoder methods and evaluation contexts)."""
    eval_every: int | None = None
    eval_seeds: int = 1
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

    def resolved(self) -> TrainConfig:
        quick = self.scale == "quick"
        steps = self.steps or (3_000 if quick else 100_000)
        eval_every = self.eval_every or max(steps // 10, self.log_every)
        out = self.out_dir or Path("runs") / self.family / self.scale / f"{self.method}-seed{self.seed}"
        resolved = replace(
            self,
            steps=steps,
            batch_size=self.batch_size or (64 if quick else 256),
            eval_every=eval_every,
            checkpoint_every=self.checkpoint_every or eval_every,
            out_dir=out,
            rl_hidden_dims=self.rl_hidden_dims or ((128, 128) if quick else (256, 256)),
        )
        resolved.iql = replace(self.iql, hidden_dims=resolved.rl_hidden_dims, learning_rate=self.learning_rate)
        if resolved.eval_every % self.log_every or resolved.checkpoint_every % self.log_every:
            raise ValueError(f"eval_every and checkpoint_every must be multiples of log_every={self.log_every}")
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
            encoder_dims=dims, decoder_dims=dims, family=config.family,
        )
        self.method = make_method(config.method, family_spec)
        self.spec = self.method.spec  # a method may change the latent (Oracle: the task array; DPT: its width)
        self.iql = IQL(data.obs_dim, self.spec.latent_dim, data.action_dim, config.iql)
        self.optimizer = optax.adam(config.learning_rate)
        self.train_task_arrays = jnp.asarray(data.train_task_arrays, jnp.float32)
        if self.method.needs_expert_actions:
            self.expert = expert or load_expert(config.family)
        self.run_chunk = jax.jit(self._run_chunk, static_argnames="length")

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


def train(config: TrainConfig, show_progress: bool = True) -> dict:
    """Train (or resume) one run; returns its final evaluation summary (also in eval.json)."""
    config = config.resolved()
    out: Path = config.out_dir
    data = ensure_family_data(config.family, config.scale, config.data_seed, config.noise, config.data_root,
                              progress=show_progress)
    trainer = Trainer(config, data)
    evaluator = Evaluator(trainer.method, trainer.iql, data, config.context_length)
    _check_run_dir(out, config)
    base_key = jax.random.PRNGKey(config.seed)
    state = trainer.init(jax.random.fold_in(base_key, 0))
    if (out / "checkpoint.msgpack").exists():
        state = _load_checkpoint(out / "checkpoint.msgpack", state)
        _drop_records_after(out, int(state.step))
    train_key = jax.random.fold_in(base_key, 1)
    device_data = data.train

    progress = Progress(
        TextColumn(f"[bold]{config.method} on {config.family}"), BarColumn(),
        TextColumn("{task.completed:,}/{task.total:,}"), TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress,
    )
    step = int(state.step)
    start = time.perf_counter()
    with progress:
        bar = progress.add_task("train", total=config.steps, completed=step, status="")
        while step < config.steps:
            length = min(config.log_every, config.steps - step)
            state, metrics = trainer.run_chunk(state, train_key, device_data, length=length)
            step += length
            metrics = {k: float(v) for k, v in metrics.items()}
            bad = [k for k, v in metrics.items() if not math.isfinite(v)]
            if bad:
                raise TrainingError(f"{out}: non-finite {', '.join(bad)} at step {step}; the last good "
                                    f"checkpoint (if any) is untouched in {out / 'checkpoint.msgpack'}")
            append_jsonl(out / "metrics.jsonl", {"step": step, "wall_time": time.perf_counter() - start, **metrics})
            if step % config.eval_every == 0 or step == config.steps:
                result = evaluator.evaluate(state, jax.random.fold_in(base_key, 2 + step), seed=config.seed * 7919 + step)
                append_jsonl(out / "eval.jsonl", {"step": step, **result.summary()})
                progress.update(bar, status=f"p_test {result.returns['p_test'].mean():.1f} "
                                            f"p_train {result.returns['p_train'].mean():.1f}")
            if step % config.checkpoint_every == 0 or step == config.steps:
                atomic_write_bytes(out / "checkpoint.msgpack", flax.serialization.to_bytes(state))
            progress.update(bar, completed=step)
    summary = summarize_run(out)
    atomic_write_json(out / "eval.json", summary)
    return summary


def summarize_run(out: Path, last: int = 5) -> dict:
    """The paper's number: mean of the last `last` evaluations, per context distribution."""
    evals = [json.loads(line) for line in (out / "eval.jsonl").read_text().splitlines()]
    config = json.loads((out / "config.json").read_text())
    tail = evals[-last:]
    summary = {"family": config["family"], "method": config["method"], "seed": config["seed"],
               "scale": config["scale"], "steps": evals[-1]["step"], "evaluations_averaged": len(tail)}
    for source in ("p_test", "p_train"):
        summary[f"{source}_return"] = float(np.mean([e[f"{source}_return"] for e in tail]))
        summary[f"{source}_inference_error"] = float(np.mean([e[f"{source}_inference_error"] for e in tail]))
        summary[f"{source}_task_returns"] = evals[-1][f"{source}_task_returns"]
    summary["curve"] = [{k: e[k] for k in ("step", "p_test_return", "p_train_return")} for e in evals]
    return summary


def _check_run_dir(out: Path, config: TrainConfig) -> None:
    """A run directory belongs to one family/method/seed: refuse to resume someone else's."""
    current = json.loads(json.dumps(asdict(config), default=str))
    check_run_config(out / "config.json", current, ("family", "method", "seed", "scale", "noise", "data_seed"))


def _load_checkpoint(path: Path, template: TrainState) -> TrainState:
    try:
        state = flax.serialization.from_bytes(template, path.read_bytes())
        shapes = jax.tree_util.tree_map(jnp.shape, (template, state))
        if shapes[0] != shapes[1]:
            raise ValueError("parameter shapes differ")
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path} does not match this run's networks (another family or method?): {err}") from err
    return state


def _drop_records_after(out: Path, step: int) -> None:
    """Forget log lines written after the checkpoint we resume from (they will be redone)."""
    for name in ("metrics.jsonl", "eval.jsonl"):
        path = out / name
        if path.exists():
            lines = [line for line in path.read_text().splitlines() if json.loads(line)["step"] <= step]
            atomic_write_text(path, "".join(line + "\n" for line in lines))
