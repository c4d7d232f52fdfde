"""Per-task SAC updates: the tasks' update mapped (`lax.map`, one task after another inside one jitted call)
against vectorised (`vmap`, one batched program), on the device JAX runs on.

    python benchmarks/per_task_update.py [--tasks 10] [--obs-dim 17] [--action-dim 6] [--calls 4]

Times `PerTaskSAC.update` on random replay data of HalfCheetah's sizes: one call applies `--updates` (25, the
default `update_every * updates_per_step`) SAC updates to every task; compilation is excluded. Prints a Markdown
row per axis with task-updates per second and the device. `bati experts train --per-task` picks the faster
axis per backend (`--task-axis auto`): what this script measured decides that default.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from bati.device import describe_device
from bati.experts.per_task import TASK_AXES, PerTaskSAC, TaskBuffers, task_keys
from bati.experts.sac import SACConfig


def updates_per_second(task_axis: str, n_tasks: int, obs_dim: int, action_dim: int, updates: int,
                       calls: int) -> float:
    learner = PerTaskSAC(obs_dim, action_dim, SACConfig(), task_axis=task_axis)
    keys = jax.vmap(jax.random.split)(task_keys(0, range(n_tasks)))
    state = learner.init(keys[:, 0])
    buffers = TaskBuffers(n_tasks, 2_000, obs_dim, action_dim)
    rng = np.random.default_rng(0)
    for _ in range(2_000):
        buffers.add(observations=rng.normal(size=(n_tasks, obs_dim)), actions=rng.uniform(-1, 1, (n_tasks, action_dim)),
                    rewards=rng.normal(size=n_tasks), next_observations=rng.normal(size=(n_tasks, obs_dim)))
    rngs = [np.random.default_rng(i) for i in range(n_tasks)]
    state, _ = learner.update(state, buffers.sample(rngs, updates, 256), keys[:, 1])  # compile
    jax.block_until_ready(state)
    start = time.perf_counter()
    for _ in range(calls):
        state, _ = learner.update(state, buffers.sample(rngs, updates, 256), keys[:, 1])
    jax.block_until_ready(state)
    return n_tasks * updates * calls / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--obs-dim", type=int, default=17)
    parser.add_argument("--action-dim", type=int, default=6)
    parser.add_argument("--updates", type=int, default=25)
    parser.add_argument("--calls", type=int, default=4)
    args = parser.parse_args()
    print("| task axis | tasks | task-updates/s | device |")
    print("| --- | --- | --- | --- |")
    for axis in TASK_AXES:
        rate = updates_per_second(axis, args.tasks, args.obs_dim, args.action_dim, args.updates, args.calls)
        print(f"| {axis} | {args.tasks} | {rate:.0f} | {describe_device()} |", flush=True)


if __name__ == "__main__":
    main()
