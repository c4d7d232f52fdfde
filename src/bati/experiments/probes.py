"""Probes: evaluations of a finished run's final checkpoint under other test-time settings.

Table 1 trains with contexts of C = 50 and evaluates the final checkpoints with C = 50, 200, 400;
Fig. 6 evaluates them on interpolated contexts (a share r of p_test, the rest p_train). Neither
needs retraining: a probe loads the run's config and final checkpoint, evaluates it `repeats` times
(one lockstep rollout of repeats x n_test envs) and writes

    <run>/probes/<name>.json          returns and inference errors per source (mean, std over repeats)
    <run>/probes/<name>-latents.npz   the first repeat's inferred latents (t-SNE of Fig. 6)

(a probe of one of the run's test-time rules, bati-r or bati-auto in a bati run: `<run>/probes/<rule>/...`).

The `novelty` probe measures unknown-task detection instead (`bati.inference.novelty`), and a probe with
`self_collect_every` = k evaluates with self-collected contexts instead of given ones (`bati.online`:
no context; z re-inferred from the policy's own last C transitions every k steps; keys `self_*`).
A probe that is already on disk for the same run step and settings is read back, not redone.

The likelihood split of a likelihood method's run (`bati likelihood`; the `main` and `noise` experiments,
for every finished run whose checkpoint is at hand) asks which part of Eq. 8 picks the task: each training
task's table entry scored on each test task's context (p_train and p_test) by the Eq. 7 NLL split in its
reward and state terms, the task-inference error of the arg-min of the full NLL, the reward term alone
(BATI-R) and the state terms alone, and how often the arg-min is the context collector's task. It is written
to `<run>/likelihood.json`, which reports read (`bati.report.likelihood`).
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.checkpoints import CHECKPOINT_NAME
from bati.io import atomic_save_npz, atomic_write_json, code_record, read_run_config
from bati.report.likelihood import (
    LIKELIHOOD_FILE,
    SOURCES,
    TERMS,
    likelihood_split_markdown,
    read_likelihood_split,
)
from bati.report.probes import Probe, ProbeError, probe_path, read_probe


def run_probe(run_dir: Path, probe: Probe, rule: str | None = None) -> dict:
    """Evaluate the run's final checkpoint under `probe` (or read the saved result); see the module. `rule`: with
    the inference of one of the run's test-time rules (bati-r, bati-auto in a bati run), saved as the rule's."""
    from bati.run_dir import open_run

    probe = probe.check()
    run_dir = Path(run_dir)
    try:  # every config.json names its method and (resolved) steps
        recorded = read_run_config(run_dir)
    except (OSError, ValueError) as err:
        raise ProbeError(f"{run_dir} holds no readable run config ({err})") from err
    rule = None if rule == recorded.get("method") else rule
    saved = read_probe(run_dir, probe, rule)
    if saved is not None and saved.get("step") == recorded.get("steps"):
        return saved
    start = time.perf_counter()
    try:
        run = open_run(run_dir, finished=True, rule=rule)
    except ValueError as err:
        raise ProbeError(str(err)) from err
    config = run.config
    out = {"probe": asdict(probe), "run_dir": str(run_dir), "family": config.family, "method": config.method,
           "seed": config.seed, "step": config.steps}
    path = probe_path(run_dir, probe, rule)
    if probe.novelty:
        from bati.inference import novelty, scorable

        out.update(novelty(scorable(run), repeats=probe.repeats))
    else:
        out.update(_evaluated(run, probe, path.with_name(f"{probe.name}-latents.npz")))
    out.update(**code_record(), wall_time_s=round(time.perf_counter() - start, 2))
    atomic_write_json(path, out)
    return out


def _evaluated(run, probe: Probe, latents_path: Path) -> dict:
    """The probe's returns and inference errors per source (`repeats` evaluations of the run's final state, or
    its self-collected evaluation), its first repeat's latents saved to `latents_path`."""
    from bati.evaluate import Evaluator

    config, data, trainer = run.config, run.data, run.trainer
    for name, attribute in (("refine_steps", "refine_steps"), ("latent_samples", "num_latent_samples")):
        if getattr(probe, name) is not None:
            if not hasattr(trainer.method, attribute):
                raise ProbeError(f"{name}: method {config.method!r} does not infer from a task table")
            setattr(trainer.method, attribute, getattr(probe, name))
    length = probe.eval_context_length or config.eval_context_length
    evaluator = Evaluator(trainer.method, trainer.iql, data, length, probe.context_mix, family=run.inputs.family)
    k = probe.repeats
    states = jax.tree_util.tree_map(lambda x: jnp.stack([jnp.asarray(x)] * k), run.state)
    base = jax.random.fold_in(jax.random.PRNGKey(config.seed), 0x9B0E)
    keys = jnp.stack([jax.random.fold_in(base, i) for i in range(k)])
    seeds = [50_000 + 1000 * i + config.seed for i in range(k)]
    out = {"context_length": length}
    if probe.self_collect_every is not None:
        from bati.online import OnlineError, SelfCollector

        try:
            collector = SelfCollector(evaluator, probe.self_collect_every, probe.self_collect_episodes)
        except OnlineError as err:
            raise ProbeError(str(err)) from err
        collected = collector.run(states, keys, seeds)
        atomic_save_npz(latents_path, final=collected.latents[0], prior=collected.prior_latents[0],
                        reference=collected.reference[0])
        return {**out, **collected.summary(), "train_tasks": data.train_tasks, "test_tasks": data.test_tasks}
    results = evaluator.evaluate_runs(states, keys, seeds)
    for source in evaluator.sources:
        returns = np.array([r.returns[source].mean() for r in results])
        errors = np.array([np.nanmean(r.inference_errors[source]) if np.isfinite(r.inference_errors[source]).any()
                           else np.nan for r in results])
        out[f"{source}_return"] = float(returns.mean())
        out[f"{source}_return_std"] = float(returns.std())
        out[f"{source}_returns"] = returns.round(3).tolist()
        out[f"{source}_inference_error"] = float(errors.mean())
    atomic_save_npz(latents_path, **{name: np.asarray(z) for name, z in results[0].latents.items()})
    return {**out, "train_tasks": data.train_tasks, "test_tasks": data.test_tasks}


def has_task_table(method: str) -> bool:
    """Whether runs of `method` infer by Eq. 8 from a task table (bati, bati-r, bati-auto): what the split needs."""
    from bati.methods import METHODS

    cls = METHODS.get(method)
    return cls is not None and hasattr(cls, "task_latents") and hasattr(cls, "score")


def likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    """The likelihood split (see the module) of the run's last checkpoint."""
    from bati.data import sample_contexts
    from bati.inference import InferenceError, load_run
    from bati.methods.dynamics import context_nll_terms

    if read_run_config(Path(run_dir)).get("datasets"):  # before loading anything
        raise InferenceError(f"{run_dir} trained on your own datasets: they have no test tasks with p_train and "
                             "p_test contexts, which this diagnostic compares (`bati infer` scores your contexts)")
    run = load_run(run_dir, calibrate=False)
    config, data, params = run.config, run.data, run.params
    model, table = run.method.model, run.method.task_latents(params)
    family = run.family
    distances = family.distance_matrix(data.test_tasks, data.train_tasks)
    # "the collector's task": a training task with the collector's parameters (HalfCheetahDir's 20 training tasks
    # are two directions, so the collector's own index would miss the other tasks of its direction)
    same_task = np.isclose(family.distance_matrix(data.train_tasks, data.train_tasks), 0.0)

    def split_nll(context, z):
        return context_nll_terms(model, params["dynamics"], context, z)

    report = {"run_dir": str(run_dir), "family": config.family, "method": config.method, "step": run.step}
    rows = np.arange(len(data.test_tasks))
    for source in SOURCES:
        task_data = getattr(data, source)
        contexts = sample_contexts(task_data, jax.random.PRNGKey(seed), jnp.arange(len(rows)), context_length)
        reward, states = (np.asarray(x) for x in jax.vmap(lambda c: jax.vmap(lambda z: split_nll(c, z))(table))(contexts))
        collector = np.asarray(task_data.collector[:, 0])
        for name, nll in zip(TERMS, (reward + states, reward, states)):
            choice = nll.argmin(1)
            report[f"{source}_{name}_error"] = float(distances[rows, choice].mean())
            report[f"{source}_{name}_picks_collector"] = float(np.mean(same_task[choice, collector]))
    return report


def save_likelihood_split(run_dir: Path, context_length: int = 200, seed: int = 0) -> dict:
    """`likelihood_split` of the run's last checkpoint, written to `<run>/likelihood.json` (atomically). A
    context length under 1 or a run directory that cannot take the file: one line, before the run is loaded."""
    from bati.checks import check_integer
    from bati.io import check_directory

    check_integer("context_length", context_length)
    if not (Path(run_dir) / "config.json").is_file():
        read_run_config(Path(run_dir))  # its own one-line error: not a run directory
    check_directory(run_dir, "the run directory")  # read-only: say so now, not after the numbers are computed
    start = time.perf_counter()
    report = likelihood_split(run_dir, context_length, seed)
    report.update(context_length=context_length, seed=seed, **code_record(),
                  wall_time_s=round(time.perf_counter() - start, 2))
    atomic_write_json(Path(run_dir) / LIKELIHOOD_FILE, report)
    return report


def likelihood_split_due(run_dir: Path, step: int, context_length: int) -> bool:
    """Whether the run's split should be (re)written: none saved for this step and context length, and the
    checkpoint at hand (a run of a machine since lost keeps its committed results; its split cannot be redone)."""
    saved = read_likelihood_split(run_dir)
    if saved is not None and saved.get("step") == step and saved.get("context_length") == context_length:
        return False
    return (Path(run_dir) / CHECKPOINT_NAME).exists()


def show_likelihood_split(run_dir: Path, context_length: int, *, console) -> None:
    """`bati likelihood`: save the run's split and print it as a table, then where it went."""
    from rich.markdown import Markdown

    console.print(Markdown(likelihood_split_markdown(save_likelihood_split(run_dir, context_length))))
    console.print(f"saved in {Path(run_dir) / LIKELIHOOD_FILE}", soft_wrap=True)
