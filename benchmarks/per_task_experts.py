"""Per-task SAC experts: task-steps per second when a family's training tasks train as one program
(`bati experts train --per-task`) against training them one after another (the same program, one task).

    python benchmarks/per_task_experts.py [--family HalfCheetahDir] [--tasks 20] [--steps 1400] [--alone 2]

Each measurement is a real run of the trainer (envs, replay, SAC updates at the family's settings) for
`--steps` transitions per task, the first `--start-steps` with random actions; the rate counts the steps
after the first update call (compilation excluded) from the run's metrics.jsonl wall times. "one after
another" times `--alone` single-task runs and scales them to `--tasks` tasks. Prints a Markdown row with the
device JAX ran on.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from bati.experts.train import ExpertTrainConfig, train_expert
from bati.device import describe_device


def task_steps_per_second(family: str, tasks: tuple[int, ...], steps: int, start_steps: int, out: Path) -> float:
    """Task-steps per second between the run's first and last evaluation (eval_every = start_steps)."""
    config = ExpertTrainConfig(family, per_task=True, tasks=tasks, total_steps=steps, start_steps=start_steps,
                               eval_every=start_steps + 200, checkpoint_every=10**9, out_dir=out,
                               export_dir=out / "zoo")
    train_expert(config, show_progress=False)
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    first, last = records[0], records[-1]
    return len(tasks) * (last["steps"] - first["steps"]) / (last["wall_time"] - first["wall_time"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="HalfCheetahDir")
    parser.add_argument("--tasks", type=int, default=20)
    parser.add_argument("--steps", type=int, default=1400)
    parser.add_argument("--start-steps", type=int, default=400)
    parser.add_argument("--alone", type=int, default=2, help="single-task runs timed for 'one after another'")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        together = task_steps_per_second(args.family, tuple(range(args.tasks)), args.steps, args.start_steps,
                                         Path(tmp) / "together")
        alone = [task_steps_per_second(args.family, (i,), args.steps, args.start_steps, Path(tmp) / f"alone{i}")
                 for i in range(args.alone)]
    one_by_one = sum(alone) / len(alone)
    print("| family | tasks | together: task-steps/s | one after another: task-steps/s | speed-up | device |")
    print("| --- | --- | --- | --- | --- | --- |")
    print(f"| {args.family} | {args.tasks} | {together:.0f} | {one_by_one:.0f} | {together / one_by_one:.1f}x | "
          f"{describe_device()} |")


if __name__ == "__main__":
    main()
