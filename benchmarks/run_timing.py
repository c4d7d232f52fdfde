"""Where a run's wall time went, read from its logs (finished or not): training ms per step and seconds per
evaluation, and its evaluations so far (mean over the seeds of a method).

    python benchmarks/run_timing.py RESULTS_DIR [RESULTS_DIR ...]

Every run directory under RESULTS_DIR (one holding metrics.jsonl) is read. metrics.jsonl has one line per
`log_every` steps with the wall time since the run's start: the median interval gives ms per training step;
an interval that holds an evaluation is the evaluation plus one interval's training; the wall time of the
first line is the start (data loading, compilation). Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

import numpy as np


def timing(metrics: Path) -> dict:
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    steps = np.array([r["step"] for r in rows])
    wall = np.array([r["wall_time"] for r in rows])
    intervals = np.diff(wall) / np.diff(steps)  # seconds per step
    per_step = float(np.median(intervals))
    evaluations = [(int(s), float(w - per_step * d)) for s, w, d in zip(steps[1:], np.diff(wall), np.diff(steps))
                   if w > 5 * per_step * d]
    return {"last_step": int(steps[-1]), "wall_s": float(wall[-1]), "start_s": float(wall[0]),
            "ms_per_step": 1e3 * per_step, "evaluations_s": evaluations}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dirs", nargs="+", type=Path)
    args = parser.parse_args()
    runs = sorted(p.parent for d in args.dirs for p in d.rglob("metrics.jsonl"))
    if not runs:
        raise SystemExit(f"error: no run (metrics.jsonl) under {' '.join(map(str, args.dirs))}")
    print("| run | steps logged | finished | wall s | start s | ms per step | evaluations (s each) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    curves = collections.defaultdict(lambda: collections.defaultdict(list))
    for run in runs:
        t = timing(run / "metrics.jsonl")
        each = ", ".join(f"{s:.0f}" for _, s in t["evaluations_s"])
        print(f"| {run.name} | {t['last_step']:,} | {'yes' if (run / 'eval.json').exists() else 'no'} | "
              f"{t['wall_s']:.0f} | {t['start_s']:.0f} | {t['ms_per_step']:.2f} | {each} |")
        method = run.name.rsplit("-seed", 1)[0]
        for line in (run / "eval.jsonl").read_text().splitlines() if (run / "eval.jsonl").exists() else []:
            e = json.loads(line)
            curves[(run.parent.parent.name, method)][e["step"]].append(e)
    print("\n| family | method | step | seeds | p_train return | p_test return | p_train error | p_test error |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for (family, method), by_step in sorted(curves.items()):
        for step, evals in sorted(by_step.items()):
            mean = lambda key: np.mean([e[key] for e in evals])  # noqa: E731
            print(f"| {family} | {method} | {step:,} | {len(evals)} | {mean('p_train_return'):.1f} | "
                  f"{mean('p_test_return'):.1f} | {mean('p_train_inference_error'):.2f} | "
                  f"{mean('p_test_inference_error'):.2f} |")


if __name__ == "__main__":
    main()
