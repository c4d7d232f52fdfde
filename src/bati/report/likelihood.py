"""Which part of Eq. 8's likelihood picks the task? A diagnostic for runs of likelihood methods.

For every test task's context (p_train and p_test), score each training task's table entry by the
Eq. 7 NLL of the context split in its reward term and its state terms, and report the task-inference
error (App. C.2 distance to the true task) of the arg-min of: the full NLL (BATI's Eq. 8), the reward
term alone (BATI-R) and the state terms alone, plus how often the arg-min is the context collector's task (a
training task with the collector's parameters).

`save_likelihood_split` keeps the result beside the run, `<run>/likelihood.json` (with the commit, the
context length and the wall time), where `bati likelihood` and the `main` and `noise` experiments put it
for every finished run of a likelihood method whose checkpoint is at hand; experiment reports read it back
(checkpoints are not committed, the JSON is).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.checkpoints import CHECKPOINT_NAME
from bati.data import sample_contexts
from bati.envs import get_family
from bati.inference import InferenceError, load_run
from bati.io import atomic_write_json, code_record, read_run_config
from bati.methods.dynamics import context_nll_terms

LIKELIHOOD_FILE = "likelihood.json"
SOURCES, TERMS = ("p_train", "p_test"), ("full", "reward", "state")


def has_task_table(method: str) -> bool:
    """Whether runs of `method` infer by Eq. 8 from a task table (bati, bati-r, bati-auto): what the split needs."""
    from bati.methods import METHODS

    cls = METHODS.get(method)
    return cls is not None and hasattr(cls, "task_latents") and hasattr(cls, "score")


def likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    if read_run_config(Path(run_dir)).get("datasets"):  # before loading anything
        raise InferenceError(f"{run_dir} trained on your own datasets: they have no test tasks with p_train and "
                             "p_test contexts, which this diagnostic compares (`bati infer` scores your contexts)")
    run = load_run(run_dir, calibrate=False)
    config, data, params = run.config, run.data, run.params
    model, table = run.method.model, run.method.task_latents(params)
    family = get_family(config.family)
    distances = family.distance_matrix(data.test_tasks, data.train_tasks)
    # "the collector's task": a training task with the collector's parameters (HalfCheetahDir's 20 training tasks
    # are two directions, so the collector's own index would miss the other tasks of its direction)
    same_task = np.isclose(family.distance_matrix(data.train_tasks, data.train_tasks), 0.0)

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
            report[f"{source}_{name}_picks_collector"] = float(np.mean(same_task[choice, collector]))
    return report


def likelihood_split_markdown(report: dict) -> str:
    lines = [f"Eq. 8 over the table means, {report['method']} on {report['family']} at step {report['step']}:", "",
             "| contexts | NLL used | task-inference error | arg-min = collector's task |", "| --- | --- | --- | --- |"]
    for source in ("p_train", "p_test"):
        for name in ("full", "reward", "state"):
            lines.append(f"| {source} | {name} | {report[f'{source}_{name}_error']:.2f} | "
                         f"{100 * report[f'{source}_{name}_picks_collector']:.0f}% |")
    return "\n".join(lines) + "\n"


def save_likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    """`likelihood_split` of the run's last checkpoint, written to `<run>/likelihood.json` (atomically)."""
    start = time.perf_counter()
    report = likelihood_split(run_dir, context_length, seed)
    report.update(context_length=context_length, seed=seed, **code_record(),
                  wall_time_s=round(time.perf_counter() - start, 2))
    atomic_write_json(Path(run_dir) / LIKELIHOOD_FILE, report)
    return report


def read_likelihood_split(run_dir: Path) -> dict | None:
    """The run's saved split, None when it is missing or unreadable."""
    try:
        saved = json.loads((Path(run_dir) / LIKELIHOOD_FILE).read_text())
    except (OSError, ValueError):
        return None
    keys = [f"{s}_{t}_{k}" for s in SOURCES for t in TERMS for k in ("error", "picks_collector")]
    return saved if isinstance(saved, dict) and all(isinstance(saved.get(k), (int, float)) for k in keys) else None


def likelihood_split_due(run_dir: Path, step: int, context_length: int) -> bool:
    """Whether the run's split should be (re)written: none saved for this step and context length, and the
    checkpoint at hand (a run of a machine since lost keeps its committed results; its split cannot be redone)."""
    saved = read_likelihood_split(run_dir)
    if saved is not None and saved.get("step") == step and saved.get("context_length") == context_length:
        return False
    return (Path(run_dir) / CHECKPOINT_NAME).exists()
