"""Does the task matter? The expert conditioned on each of a grid of tasks, acting in every test task.

If one task-agnostic behaviour (the expert for a single fixed task) earns nearly the experts' own
return on every test task, a family cannot test task inference: a policy that ignores the context
does as well as one that infers the task. Prints and writes, per family and noise level, the
experts' own mean return on the test tasks (the oracle), the best single fixed-task expert's mean
return on all of them, and the most-different expert's (the p_test collector's) return.

    python benchmarks/task_sensitivity.py --family HopperParam --noise 1.0 --out results/diagnostics/
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bati.envs import get_family
from bati.experts import load
from bati.experts.card import expert_episodes
from bati.io import atomic_write_json, git_commit


def sensitivity(family_name: str, noise: float | None, grid: int = 13, seed: int = 0) -> dict:
    family = get_family(family_name)
    noise = family.validate_noise(noise)
    expert = load(family_name)
    train, test = family.split_tasks(seed)
    low, high = family.parameter_range
    candidates = [family.task_from_parameter(x) for x in np.linspace(low, high, grid, endpoint=False) + (high - low) / (2 * grid)]
    own = expert_episodes(expert, test, test, noise, seed=1000 + seed).returns
    fixed = np.stack([expert_episodes(expert, test, [c] * len(test), noise, seed=1000 + seed).returns for c in candidates])
    wrong = [train[family.most_different(t, train)] for t in test]
    against = expert_episodes(expert, test, wrong, noise, seed=1000 + seed).returns
    best = int(np.argmax(fixed.mean(1)))
    return {
        "family": family_name, "noise": noise, "split_seed": seed,
        "oracle_return": float(own.mean()),
        "best_fixed_task": candidates[best], "best_fixed_return": float(fixed[best].mean()),
        "best_fixed_share_of_oracle": float(fixed[best].mean() / own.mean()),
        "most_different_expert_return": float(against.mean()),
        "fixed_task_returns": {str(c): float(r) for c, r in zip(candidates, fixed.mean(1))},
        "per_test_task": [{"task": t, "own": float(o), "best_fixed": float(b)} for t, o, b in zip(test, own, fixed[best])],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", action="append", required=True)
    parser.add_argument("--noise", type=float, action="append")
    parser.add_argument("--out", type=Path, default=Path("results/diagnostics"))
    args = parser.parse_args()
    for family in args.family:
        for noise in args.noise or [None]:
            start = time.perf_counter()
            result = sensitivity(family, noise)
            result.update(commit=git_commit(), wall_time_s=round(time.perf_counter() - start, 1))
            name = f"task_sensitivity-{family}-eps{result['noise']:g}.json"
            atomic_write_json(args.out / name, result)
            print(f"{family} eps={result['noise']:g}: oracle {result['oracle_return']:.1f}, best fixed task "
                  f"{result['best_fixed_task']} {result['best_fixed_return']:.1f} "
                  f"({100 * result['best_fixed_share_of_oracle']:.0f}%), most-different expert "
                  f"{result['most_different_expert_return']:.1f} ({result['wall_time_s']} s)")


if __name__ == "__main__":
    main()
