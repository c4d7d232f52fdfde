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

from bati.data import sample_contexts
from bati.envs import get_family
from bati.inference import InferenceError, load_run
from bati.io import read_run_config
from bati.methods.dynamics import context_nll_terms


def likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    if read_run_config(Path(run_dir)).get("datasets"):  # before loading anything
        raise InferenceError(f"{run_dir} trained on your own datasets: they have no test tasks with p_train and "
                             "p_test contexts, which this diagnostic compares (`bati infer` scores your contexts)")
    run = load_run(run_dir, calibrate=False)
    config, data, params = run.config, run.data, run.params
    model, table = run.method.model, run.method.task_latents(params)
    family = get_family(config.family)
    distances = family.distance_matrix(data.test_tasks, data.train_tasks)

    def split_nll(context, z):
        return context_nll_terms(model, params["dynamics"], context, z)

    report = {"run_dir": str(run_dir), "family": config.family, "method": config.method, "step": run.step}
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
