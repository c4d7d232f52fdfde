"""Evaluations of runs that train together, at their evaluation steps, into their run directories.

`RunEvaluations(at, states)` evaluates k runs' states (stacked, as they train) with the runs' own inference
and with each test-time rule asked for (`Evaluator.inferring_with`), and appends one line per run to its
eval.jsonl (the rules' records under "rules"; the run's own to its sinks). `EvaluatedBeside` wraps it to evaluate in a thread
while the next chunks train. Either way, a callback given with an evaluation (a checkpoint of that step)
runs once the evaluation's records are written, and `wait()` lands the one in flight first: a checkpoint is
never ahead of an evaluation not yet written, and the numbers are the same.

Evaluation at step t uses the key fold_in(run key, 2 + t) and resets the env of test task i with
seed * 7919 + t + i: the same at any resume and in any grouping of runs.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import jax
import jax.numpy as jnp

from bati.io import append_jsonl

__all__ = ["EvaluatedBeside", "RunEvaluations"]


class RunEvaluations:
    """The evaluations of `runs` (all at the same step; each with `base_key`, `config`, `out`, `sinks` and
    `rule_seconds`, as bati.train's SeedRun), done here.

    `rules`: the evaluator of each test-time rule evaluated in these runs beside their own inference (bati-r and
    bati-auto in a bati run: `Evaluator.inferring_with`), on the same states, keys and env seeds; each rule's
    records go into the run's eval.jsonl line under "rules", its evaluation time to `run.rule_seconds`.
    `on_status`: receives the progress bar's line."""

    def __init__(self, evaluator, runs: list, rules: dict[str, object] | None = None,
                 on_status: Callable[[str], None] = lambda line: None):
        self.evaluator, self.runs, self.rules, self.on_status = evaluator, runs, dict(rules or {}), on_status

    def inputs(self, at: int, states):
        """The runs' states, keys and env seeds for an evaluation at step `at`."""
        keys = jnp.stack([jax.random.fold_in(r.base_key, 2 + at) for r in self.runs])
        return states, keys, [r.config.seed * 7919 + at for r in self.runs]

    def warm_up(self, at: int, states) -> None:
        """Begin compiling (and starting envs) for the first evaluation while training goes on."""
        for evaluator in [self.evaluator, *self.rules.values()]:
            evaluator.warm_up(*self.inputs(at, states))

    def run(self, at: int, states) -> dict:
        """Evaluate (here or in a thread): {rule (None: the runs' own inference): (results, seconds)}."""
        done = {}
        for rule, evaluator in [(None, self.evaluator), *self.rules.items()]:
            began = time.perf_counter()
            done[rule] = evaluator.evaluate_runs(*self.inputs(at, states)), time.perf_counter() - began
        return done

    def write(self, at: int, done: dict) -> None:
        """Append each run's line (its own evaluation, then its rules') to its eval.jsonl."""
        own, _ = done[None]
        for j, run in enumerate(self.runs):
            rules = {rule: results[j].summary() for rule, (results, _) in done.items() if rule is not None}
            append_jsonl(run.out / "eval.jsonl", {"step": at, **own[j].summary(), **({"rules": rules} if rules else {})})
            for sink in run.sinks:
                sink.log(at, own[j].summary(), "eval")
            for rule, (_, seconds) in done.items():
                if rule is not None:
                    run.rule_seconds[rule] = run.rule_seconds.get(rule, 0.0) + seconds / len(self.runs)
        self.on_status(self.evaluator.status(own))

    def __call__(self, at: int, states, then: Callable[[], None] | None = None) -> None:
        """Evaluate the runs at step `at`, write the records, then call `then`."""
        self.write(at, self.run(at, states))
        if then is not None:
            then()

    def wait(self) -> None:
        """Nothing in flight here."""

    def close(self) -> None:
        pass


class EvaluatedBeside:
    """`RunEvaluations` in a thread while training goes on (on a GPU the device trains during the CPU-bound
    rollouts instead of idling): an evaluation's records and its `then` land at the next evaluation, `wait()`
    or `close()`, in step order."""

    def __init__(self, evaluations: RunEvaluations):
        self.evaluations = evaluations
        self.thread = ThreadPoolExecutor(1, thread_name_prefix="bati-eval")
        self.pending = None

    def warm_up(self, at: int, states) -> None:
        self.evaluations.warm_up(at, states)

    def __call__(self, at: int, states, then: Callable[[], None] | None = None) -> None:
        self.wait()
        self.pending = (at, self.thread.submit(self.evaluations.run, at, states), then)

    def wait(self) -> None:
        """Land the evaluation in flight: its records, then its `then`."""
        if self.pending is None:
            return
        at, future, then = self.pending
        self.pending = None
        self.evaluations.write(at, future.result())
        if then is not None:
            then()

    def close(self) -> None:
        """Stop the thread (an evaluation not landed is dropped: its step is redone on resume)."""
        self.thread.shutdown(wait=True, cancel_futures=True)
