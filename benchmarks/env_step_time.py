"""Wall time of one 200-step random-action episode per task family, at the family's default eps.

    python benchmarks/env_step_time.py [--repeats 3]

Prints a markdown table (the median over `--repeats` episodes; env construction excluded).
Single process, single thread: cheap enough to run next to other jobs.
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium as gym
import numpy as np

from bati.envs import FAMILY_NAMES, get_family


def episode_seconds(env: gym.Env, seed: int) -> tuple[float, int]:
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    start, steps, done = time.perf_counter(), 0, False
    while not done:
        _, _, terminated, truncated, _ = env.step(rng.uniform(-1.0, 1.0, env.action_space.shape))
        steps, done = steps + 1, terminated or truncated
    return time.perf_counter() - start, steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="episodes per family (median reported)")
    args = parser.parse_args()

    print("| family | eps (default) | obs dim | action dim | steps | episode wall time (ms) | per step (us) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name in FAMILY_NAMES:
        family = get_family(name)
        task = family.sample_tasks(1, seed=0)[0]
        env = family.make_env(task)  # noise=None: the family's default eps
        times, steps = zip(*(episode_seconds(env, seed) for seed in range(args.repeats)))
        seconds = statistics.median(times)
        print(
            f"| {name} | {env.unwrapped.noise:g} | {env.observation_space.shape[0]} | "
            f"{env.action_space.shape[0]} | {steps[0]} | {1e3 * seconds:.1f} | {1e6 * seconds / steps[0]:.0f} |"
        )
        env.close()


if __name__ == "__main__":
    main()
