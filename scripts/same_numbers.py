"""Same numbers before and after a change: train a few PointGoal runs with two checkouts and compare.

    git worktree add ../before <commit-before>
    python scripts/same_numbers.py ../before . --data-root DATA --out /tmp/same-numbers

Each checkout trains `--methods` (default bati, csro, dpt) on PointGoal's quick data for `--steps` steps
(its own code: PYTHONPATH=<checkout>/src), with `bati train` (default) or, `--via run`, with the main job
(`bati run --methods ...`, wherever each checkout puts its run directories); then metrics.jsonl and eval.jsonl (without wall times),
eval.json (without wall time, commit, uncommitted changes and config) and every array of the checkpoints (the earlier one read
in today's layout, bati.checkpoints) are compared. Prints one line per method; exit 1 if any differs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import flax
import jax
import numpy as np

from bati.checkpoints import upgrade_train_state


def train(checkout: Path, method: str, out: Path, steps: int, data_root: str) -> None:
    env = {**os.environ, "PYTHONPATH": str(checkout.resolve() / "src")}
    subprocess.run([sys.executable, "-m", "bati.cli", "train", "--family", "PointGoal", "--method", method,
                    "--steps", str(steps), "--eval-every", str(steps // 2), "--log-every", str(steps // 4),
                    "--data-root", data_root, "--out-dir", str(out)], env=env, check=True, capture_output=True)


def main_job(checkout: Path, methods: list[str], out: Path, steps: int, data_root: str) -> dict[str, Path]:
    """`bati run` of the checkout; {method: its seed-0 run directory}."""
    env = {**os.environ, "PYTHONPATH": str(checkout.resolve() / "src")}
    subprocess.run([sys.executable, "-m", "bati.cli", "run", "--family", "PointGoal", "--methods", *methods,
                    "--steps", str(steps), "--data-root", data_root, "--out-dir", str(out)], env=env, check=True,
                   capture_output=True)
    return {method: next(out.rglob(f"{method}-seed0/eval.json")).parent for method in methods}


def records(run: Path, name: str) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k != "wall_time"}
            for line in (run / name).read_text().splitlines()]


def summary(run: Path) -> dict:
    return {k: v for k, v in json.loads((run / "eval.json").read_text()).items()
            if k not in ("wall_time_s", "commit", "uncommitted_changes", "config")}


def arrays(run: Path) -> dict:
    raw = upgrade_train_state(flax.serialization.msgpack_restore((run / "checkpoint.msgpack").read_bytes()))
    return {jax.tree_util.keystr(k): np.asarray(v) for k, v in jax.tree_util.tree_leaves_with_path(raw)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--methods", nargs="+", default=["bati", "csro", "dpt"])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--data-root", default="data")
    parser.add_argument("--out", type=Path, default=Path("same-numbers"))
    parser.add_argument("--via", choices=("train", "run"), default="train")
    args = parser.parse_args()
    same = True
    if args.via == "run":
        by_checkout = [main_job(checkout, args.methods, args.out / tag, args.steps, args.data_root)
                       for checkout, tag in ((args.before, "before"), (args.after, "after"))]
    for method in args.methods:
        if args.via == "run":
            runs = [found[method] for found in by_checkout]
        else:
            runs = [args.out / tag / method for tag in ("before", "after")]
            for checkout, run in zip((args.before, args.after), runs):
                train(checkout, method, run, args.steps, args.data_root)
        before, after = (arrays(r) for r in runs)
        checks = {"metrics.jsonl": records(runs[0], "metrics.jsonl") == records(runs[1], "metrics.jsonl"),
                  "eval.jsonl": records(runs[0], "eval.jsonl") == records(runs[1], "eval.jsonl"),
                  "eval.json": summary(runs[0]) == summary(runs[1]),
                  "checkpoint": before.keys() == after.keys() and all(np.array_equal(before[k], after[k])
                                                                    for k in before)}
        same &= all(checks.values())
        print(f"{method}: " + ", ".join(f"{name} {'identical' if ok else 'DIFFERS'}" for name, ok in checks.items())
              + f" ({len(before)} checkpoint arrays)")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
