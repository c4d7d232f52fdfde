"""Evaluations of runs that train together, at their evaluation steps, into their run directories.

`RunEvaluations(at, states)` evaluates k runs' states (stacked, as they train) with the runs' own inference
and with each method evaluated alongside some of them (`Evaluator.inferring_with`), and appends the records
to each run directory's eval.jsonl (and the run's sinks). `EvaluatedBeside` wraps it to evaluate in a thread
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
    """The evaluations of `runs` (all at the same step; each with `base_key`, `config`, `out`, `sinks`,
    `companions` and `companion_seconds`, as bati.train's SeedRun), done here.

    `modes`: the evaluator of each method evaluated alongside some of the runs (`run.companions`); its records
    go to the companion's directory and its evaluation time to `run.companion_seconds` (its whole cost: the
    training is the run's). `on_status`: receives the progress bar's line."""

    def __init__(self, evaluator, runs: list, modes: dict[str, object],
                 on_status: Callable[[str], None] = lambda line: None):
        self.evaluator, self.runs, self.on_status = evaluator, runs, on_status
        self.modes = []  # (method, evaluator, {run index: the companion's directory})
        for method, mode in modes.items():
            dirs = {j: c.out_dir for j, run in enumerate(runs) for c in run.companions if c.method == method}
            if dirs:
                self.modes.append((method, mode, dirs))

    def inputs(self, at: int, states, members: list[int]):
        """The states, keys and env seeds of the runs `members` for an evaluation at step `at`."""
        picked = jnp.asarray(members)
        runs = [self.runs[j] for j in members]
        keys = jnp.stack([jax.random.fold_in(r.base_key, 2 + at) for r in runs])
        if len(members) < len(self.runs):
            states = jax.tree_util.tree_map(lambda x: x[picked], states)
        return states, keys, [r.config.seed * 7919 + at for r in runs]

    def plan(self) -> list[tuple]:
        """(method, evaluator, members, their directories): the runs' own inference first (method None)."""
        everyone = list(range(len(self.runs)))
        own = (None, self.evaluator, everyone, [r.out for r in self.runs])
        return [own] + [(m, ev, sorted(dirs), [dirs[j] for j in sorted(dirs)]) for m, ev, dirs in self.modes]

    def warm_up(self, at: int, states) -> None:
        """Begin compiling (and starting envs) for the first evaluation while training goes on."""
        for _, evaluator, members, _ in self.plan():
            evaluator.warm_up(*self.inputs(at, states, members))

    def run(self, at: int, states) -> list[tuple]:
        """Evaluate (here or in a thread): (method, members, directories, results, seconds) each."""
        done = []
        for method, evaluator, members, dirs in self.plan():
            began = time.perf_counter()
            results = evaluator.evaluate_runs(*self.inputs(at, states, members))
            done.append((method, members, dirs, results, time.perf_counter() - began))
        return done

    def write(self, at: int, done: list[tuple]) -> None:
        """Append the evaluations' records to their run directories."""
        for method, members, dirs, results, seconds in done:
            for j, out, result in zip(members, dirs, results):
                append_jsonl(out / "eval.jsonl", {"step": at, **result.summary()})
                if method is None:
                    for sink in self.runs[j].sinks:
                        sink.log(at, result.summary(), "eval")
                else:
                    spent = self.runs[j].companion_seconds
                    spent[method] = spent.get(method, 0.0) + seconds / len(members)
        self.on_status(self.evaluator.status(done[0][3]))

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
