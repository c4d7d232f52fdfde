"""Training runs: k seeds of one config trained as one program, with their logs, evaluations and checkpoints.

The algorithm itself is bati.trainer (pure JAX, no files); run directories (claiming, resuming, summaries,
opening a finished run) are bati.run_dir; evaluations into them are bati.evaluations. This module is the
loop: `train_seeds` opens each seed's run (fresh or from its checkpoint), brings resumed seeds level (the
ones behind advance alone), then trains them together chunk by chunk (`_train_together`), and writes each
run's eval.json. A lone run is the k = 1 case of the same loop, with the numbers of the unvmapped program.

Methods that train exactly as another and differ only at test time (bati-r and bati-auto train as bati,
`TaskInference.trains_as`) are test-time rules of its run (`rules`): at every evaluation the same states, with the
same keys and env seeds, are evaluated with each rule's inference too, into the run's own eval.jsonl line and
eval.json (under "rules"; `bati.report.runs` reads each rule as a result of its own). One training, one run
directory: a rule's numbers are those of a run of the rule trained alone with the same seed.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import jax
import jax.numpy as jnp
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from bati.checkpoints import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from bati.config import ResolvedRun, TrainConfig
from bati.data import FamilyData
from bati.device import machine_record
from bati.envs import TaskFamily
from bati.evaluate import Evaluator, OfflineEvaluator, reference_returns
from bati.evaluations import EvaluatedBeside, RunEvaluations
from bati.io import append_jsonl, atomic_write_json, code_record
from bati.methods import check_rules
from bati.processes import stall_watchdog
from bati.run_dir import (
    RunInputs,
    TrainingError,
    check_datasets_unchanged,
    check_rules_evaluated,
    check_seeds,
    claim_run_dirs,
    drop_records_after,
    own_env,
    summarize_evaluations,
    summarize_run,
)
from bati.sinks import open_sinks
from bati.trainer import Trainer, TrainState

__all__ = ["TrainingError", "train", "train_seeds"]

CHECKPOINT_SECONDS = 600.0
"""Besides every checkpoint_every steps, a run checkpoints at the first log boundary this long (wall time)
after its last checkpoint, so a kill loses at most about this much work. A run resumed from any log
boundary gives the same numbers (step t's key is fold_in(key, t)), so this changes no result."""


def train(config: TrainConfig, show_progress: bool = True) -> dict:
    """Train (or resume) one run; returns its final evaluation summary (also in eval.json)."""
    return train_seeds(config, (config.seed,), show_progress=show_progress)[0]


def train_seeds(config: TrainConfig, seeds: tuple[int, ...], show_progress: bool = True,
                runs_dir: Path | None = None, references: dict | None = None, rules: tuple[str, ...] = (),
                family: TaskFamily | None = None) -> list[dict]:
    """Train (or resume) one run per seed of one config as one compiled program vmapped over seeds.

    Each seed has its own run directory (`runs_dir/<method>-seed<s>`, default: the config's default
    directory), metrics, evaluations and checkpoints, exactly as a run trained alone; seed s gives the
    numbers of the single-seed run s to float tolerance. Returns the runs' summaries (also in each eval.json),
    in the order of `seeds`. `references`: the collection's random and expert returns when the caller has them
    (`bati run` computes them once for all its methods); by default they are computed here. `rules`: methods that
    train exactly as this one, evaluated in each run as test-time rules (see the module docstring; ValueError for
    a run that has evaluations without one of them). `family`: the config's family object, when the caller has
    looked it up already.
    """
    seeds = check_seeds(seeds)
    if len(seeds) > 1 and config.out_dir is not None and runs_dir is None:
        raise ValueError("several seeds need one directory each: give runs_dir (the parent), not out_dir")
    out_dir = lambda seed: runs_dir / f"{config.method}-seed{seed}" if runs_dir else config.out_dir  # noqa: E731
    first = replace(config, seed=seeds[0], out_dir=out_dir(seeds[0])).resolve(family)  # a lookup by name, if any
    runs = [first.for_seed(s, out_dir(s)) for s in seeds]
    rules = check_rules(first.config.method, rules, bool(first.config.datasets))
    with claim_run_dirs(runs):
        return _train_claimed(runs, rules, show_progress, references)


@dataclass
class SeedRun:
    """One seed's run directory and its state on the host side of the training loop."""

    config: TrainConfig
    state: TrainState
    base_key: jax.Array
    sinks: list = field(default_factory=list)
    """Optional mirrors of the JSONL logs (TensorBoard, W&B: `--log-to`)."""
    rule_seconds: dict[str, float] = field(default_factory=dict)
    """Wall time of each test-time rule's evaluations in this session (`train_seeds(..., rules=...)`)."""

    @property
    def out(self) -> Path:
        return self.config.out_dir

    @property
    def step(self) -> int:
        return int(self.state.step)

    @classmethod
    def open(cls, run: ResolvedRun, trainer: Trainer, rules: tuple[str, ...]) -> SeedRun:
        """Start fresh or resume from the run directory's checkpoint (the directory is already claimed); ValueError
        when its evaluations so far lack one of the test-time `rules` (they cannot be redone at past steps)."""
        config = run.config
        base_key = jax.random.PRNGKey(config.seed)
        state = trainer.init(jax.random.fold_in(base_key, 0))
        if (config.out_dir / CHECKPOINT_NAME).exists():
            state = load_checkpoint(config.out_dir / CHECKPOINT_NAME, state)
        drop_records_after(config.out_dir, int(state.step))
        check_rules_evaluated(config.out_dir, rules)
        sinks = open_sinks(config.log_to, config.out_dir, run.record()) if config.log_to else []
        return cls(config, state, base_key, sinks)


def _train_claimed(resolved: list[ResolvedRun], rules: tuple[str, ...], show_progress: bool,
                   references: dict | None) -> list[dict]:
    """train_seeds once its run directories are checked, claimed and locked."""
    config = resolved[0].config
    inputs = RunInputs.read(resolved[0], show_progress)
    data, trainer = inputs.data, inputs.trainer()
    if config.datasets:
        evaluator = OfflineEvaluator(trainer, data, config.eval_context_length, *own_env(config, data))
        for run in resolved:  # the data a run started on is the data it resumes on
            check_datasets_unchanged(Path(run.config.out_dir), data.manifest["fingerprint"])
    else:
        evaluator = Evaluator(trainer.method, trainer.iql, data, config.eval_context_length, family=inputs.family,
                              workers=config.eval_workers)
    runs = [SeedRun.open(run, trainer, rules) for run in resolved]
    if all(r.step >= config.steps for r in runs) and all((r.out / "eval.json").is_file() for r in runs):
        evaluator.close()  # finished before this call: a rerun that trains nothing rewrites nothing
        for sink in (sink for run in runs for sink in run.sinks):
            sink.close()
        return [json.loads((r.out / "eval.json").read_text()) for r in runs]
    of_rules = {rule: evaluator.inferring_with(inputs.with_method(rule).trainer().method) for rule in rules}
    start = time.perf_counter()
    progress = Progress(
        TextColumn(f"[bold]{config.method} on {config.family}" + (f" x{len(runs)} seeds" if len(runs) > 1 else "")),
        BarColumn(), TextColumn("{task.completed:,}/{task.total:,}"), TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress,
    )
    with progress, stall_watchdog() as alive:
        bar = progress.add_task("train", total=config.steps, completed=min(r.step for r in runs), status="")

        def report(**fields) -> None:
            progress.update(bar, **fields)
            alive()

        try:
            while (behind := min(r.step for r in runs)) < config.steps:  # the runs behind first, alone
                group = [r for r in runs if r.step == behind]
                until = min([r.step for r in runs if r.step > behind] + [config.steps])
                evaluations = RunEvaluations(evaluator, group, of_rules, lambda line: report(status=line))
                _train_together(trainer, evaluations, data, group, until, start,
                                on_step=lambda step: report(completed=step))
        finally:
            for evaluator_of_rule in [*of_rules.values(), evaluator]:  # the rules share the evaluator's envs
                evaluator_of_rule.close()
            for run in runs:
                for sink in run.sinks:
                    sink.close()
    if references is None and not config.datasets:
        references = reference_returns(data, family=inputs.family, expert=inputs.expert)
    return _write_summaries(runs, rules, data, references, round(time.perf_counter() - start, 2))


def _train_together(trainer: Trainer, evaluations: RunEvaluations, data: FamilyData, runs: list[SeedRun],
                    until: int, start: float, on_step) -> None:
    """Train `runs` (all at the same step) together up to step `until`, a chunk of log_every steps at a time:
    log each chunk, evaluate when due (beside training with `eval_beside_training`), checkpoint when due
    (after the evaluation of its step is written)."""
    c, step = runs[0].config, runs[0].step
    states = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[r.state for r in runs])  # stay stacked on device
    keys = jnp.stack([jax.random.fold_in(r.base_key, 1) for r in runs])
    evaluate = EvaluatedBeside(evaluations) if c.eval_beside_training else evaluations
    last_checkpoint = time.monotonic()

    def checkpoint(states) -> None:
        nonlocal last_checkpoint
        for j, run in enumerate(runs):
            save_checkpoint(run.out / CHECKPOINT_NAME, jax.tree_util.tree_map(lambda x, j=j: x[j], states))
        last_checkpoint = time.monotonic()

    if (step // c.eval_every + 1) * c.eval_every <= until or until == c.steps:  # an evaluation comes: prepare it
        evaluate.warm_up(step, states)
    try:
        while step < until:
            length = min(c.log_every, until - step)
            states, metrics = trainer.run_chunks(states, keys, data.train, length=length)
            step += length
            _log_metrics(runs, step, jax.device_get(metrics), time.perf_counter() - start)
            checkpoint_due = (step % c.checkpoint_every == 0 or step == c.steps
                              or time.monotonic() - last_checkpoint >= CHECKPOINT_SECONDS)
            if step % c.eval_every == 0 or step == c.steps:
                evaluate(step, states, then=(lambda states=states: checkpoint(states)) if checkpoint_due else None)
            elif checkpoint_due:
                evaluate.wait()  # never a checkpoint ahead of an evaluation not yet written
                checkpoint(states)
            on_step(step)
        evaluate.wait()
    finally:
        evaluate.close()
    for j, run in enumerate(runs):
        run.state = jax.tree_util.tree_map(lambda x, j=j: x[j], states)


def _log_metrics(runs: list[SeedRun], step: int, metrics: dict, wall_time: float) -> None:
    """Append each run's chunk means to its metrics.jsonl (and sinks); TrainingError on a non-finite one."""
    for j, run in enumerate(runs):
        record = {k: float(v[j]) for k, v in metrics.items()}
        bad = [k for k, v in record.items() if not math.isfinite(v)]
        if bad:
            raise TrainingError(f"{run.out}: non-finite {', '.join(bad)} at step {step}; the last good "
                                f"checkpoint (if any) is untouched in {run.out / CHECKPOINT_NAME}")
        append_jsonl(run.out / "metrics.jsonl", {"step": step, "wall_time": wall_time, **record})
        for sink in run.sinks:
            sink.log(step, record, "train")


def _write_summaries(runs: list[SeedRun], rules: tuple[str, ...], data: FamilyData, references: dict | None,
                     wall_time: float) -> list[dict]:
    """Each run's eval.json: its own evaluations' summary and, under "rules", each test-time rule's."""
    session = {**machine_record(), **code_record(), "wall_time_s": wall_time}
    recorded = {k: data.manifest[k] for k in ("n_episodes", "n_context_episodes", "transitions", "transitions_read",
                                              "tasks") if k in data.manifest}
    if not runs[0].config.datasets:  # own data is fingerprinted by its files (data.manifest["fingerprint"])
        recorded["fingerprint"] = data.fingerprint()
    summaries = []
    for run in runs:
        summary = {**summarize_run(run.out), "reference_returns": references, **session, "data": recorded}
        of_rules = {rule: {**summarize_evaluations(run.out, rule), "wall_time_s": round(run.rule_seconds.get(rule, 0.0), 2)}
                    for rule in rules}
        atomic_write_json(run.out / "eval.json", {**summary, **({"rules": of_rules} if of_rules else {})})
        summaries.append(summary)
    return summaries
