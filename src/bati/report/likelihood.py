"""Which part of Eq. 8's likelihood picks the task? A diagnostic for runs of likelihood methods.

For every test task's context (p_train and p_test), score each training task's table entry by the
Eq. 7 NLL of the context split in its reward term and its state terms, and report the task-inference
error (App. C.2 distance to the true task) of the arg-min of: the full NLL (BATI's Eq. 8), the reward
term alone (BATI-R) and the state terms alone, plus how often the arg-min is the context's collector.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.data import load_family_data, sample_contexts
from bati.envs import get_family
from bati.methods.dynamics import reconstruction_nll, transition_targets
from bati.train import TrainConfig, Trainer, load_checkpoint, read_run_config


def likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    saved = read_run_config(run_dir)  # one-line errors: a file, no config.json, not a JSON object
    config = TrainConfig.from_record(saved).resolved()
    data = load_family_data(config.family, config.scale, config.data_seed, config.noise, config.data_root,
                            tasks=config.task_split())
    trainer = Trainer(config, data)
    if not hasattr(trainer.method, "task_latents"):
        raise ValueError(f"{run_dir}: method {config.method!r} has no task table to score")
    checkpoint = run_dir / "checkpoint.msgpack"
    if not checkpoint.is_file():
        raise ValueError(f"{run_dir} has no checkpoint yet: train the run first")
    state = load_checkpoint(checkpoint, trainer.init(jax.random.PRNGKey(0)))
    params, model = state.method, trainer.method.model
    table = trainer.method.task_latents(params)
    family = get_family(config.family)
    distances = family.distance_matrix(data.test_tasks, data.train_tasks)

    def split_nll(context, z):
        zs = jnp.broadcast_to(z, context["observations"].shape[:-1] + z.shape)
        mean, log_var = model.apply(params["dynamics"], context["observations"], context["actions"], zs)
        target = transition_targets(context)
        return (reconstruction_nll(mean[..., :1], log_var[..., :1], target[..., :1]).mean(),
                reconstruction_nll(mean[..., 1:], log_var[..., 1:], target[..., 1:]).mean())

    report = {"run_dir": str(run_dir), "family": config.family, "method": config.method, "step": int(state.step)}
    rows = np.arange(len(data.test_tasks))
    for source in ("p_train", "p_test"):
        task_data = getattr(data, source)
        contexts = sample_contexts(task_data, jax.random.PRNGKey(seed), jnp.arange(len(rows)), context_length)
        reward, states = (np.asarray(x) for x in jax.vmap(lambda c: jax.vmap(lambda z: split_nll(c, z))(table))(contexts))
        collector = np.asarray(task_data.collector[:, 0])
        for name, nll in (("full", reward + states), ("reward", reward), ("state", states)):
            choice = nll.argmin(1)
            report[f"{source}_{name}_error"] = float(distances[rows, choice].mean())
            report[f"{source}_{name}_picks_collector"] = float(np.mean(choice == collector))
    return report


def likelihood_split_markdown(report: dict) -> str:
    lines = [f"Eq. 8 over the table means, {report['method']} on {report['family']} at step {report['step']}:", "",
             "| contexts | NLL used | task-inference error | arg-min = collector's task |", "| --- | --- | --- | --- |"]
    for source in ("p_train", "p_test"):
        for name in ("full", "reward", "state"):
            lines.append(f"| {source} | {name} | {report[f'{source}_{name}_error']:.2f} | "
                         f"{100 * report[f'{source}_{name}_picks_collector']:.0f}% |")
    return "\n".join(lines) + "\n"
