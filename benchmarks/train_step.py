"""Time one jitted training step (method loss + IQL) per method and scale, on random data.

    python benchmarks/train_step.py [--family HalfCheetahVel] [--methods bati recon] [--scales quick paper]

Prints a markdown table: milliseconds per gradient step of one seed (median over chunks of 20 steps,
after compilation) at each scale's batch and nets: quick and cpu (16 x 64, IQL 128x128), paper (16 x 256,
IQL 256x256).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from bati.data import FamilyData, TaskData
from bati.config import TrainConfig, family_of
from bati.experts import load as load_expert
from bati.methods import METHODS
from bati.trainer import Trainer

DIMS = {"PointGoal": (2, 2, 2), "AntDir": (27, 8, 2), "HalfCheetahVel": (17, 6, 1), "HalfCheetahDir": (17, 6, 1),
        "HopperParam": (11, 3, 1), "WalkerParam": (17, 6, 1)}


def random_data(family: str, n_tasks: int = 20, n: int = 2000) -> FamilyData:
    obs_dim, action_dim, task_dim = DIMS[family]
    rng = np.random.default_rng(0)
    arr = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
    data = TaskData(arr(n_tasks, n, obs_dim), jnp.clip(arr(n_tasks, n, action_dim), -1, 1), arr(n_tasks, n),
                    arr(n_tasks, n, obs_dim), jnp.zeros((n_tasks, n), jnp.int32))
    tasks = list(range(n_tasks))
    return FamilyData(family, "quick", 0, 0.0, tasks, tasks, np.zeros((n_tasks, task_dim)),
                      np.zeros((n_tasks, task_dim)), data, data, data, obs_dim, action_dim, task_dim)


def make_trainer(config: TrainConfig, data: FamilyData) -> Trainer:
    """The config's trainer, with the family's shipped expert for a method that imitates one (DPT)."""
    expert = load_expert(config.family, config.zoo_dir) if METHODS[config.method].needs_expert_actions else None
    return Trainer(config, data, family_of(config.family), expert)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--family", default="HalfCheetahVel", choices=sorted(DIMS))
    parser.add_argument("--methods", nargs="+", default=["bati", "recon"])
    parser.add_argument("--scales", nargs="+", default=["quick", "paper"], choices=["quick", "cpu", "paper"])
    parser.add_argument("--chunks", type=int, default=5)
    args = parser.parse_args()
    data = random_data(args.family)
    print("| family | method | scale | batch | IQL dims | ms / step |\n| --- | --- | --- | --- | --- | --- |")
    for method in args.methods:
        for scale in args.scales:
            config = TrainConfig(family=args.family, method=method, scale=scale).resolved()
            trainer = make_trainer(config, data)
            state = trainer.init(jax.random.PRNGKey(0))
            state, _ = trainer.run_chunk(state, jax.random.PRNGKey(1), data.train, length=20)
            jax.block_until_ready(state)
            times = []
            for i in range(args.chunks):
                start = time.perf_counter()
                state, _ = trainer.run_chunk(state, jax.random.PRNGKey(2 + i), data.train, length=20)
                jax.block_until_ready(state)
                times.append((time.perf_counter() - start) / 20)
            print(f"| {args.family} | {method} | {scale} | {config.task_batch} x {config.batch_size} | "
                  f"{config.iql.hidden_dims} | {1e3 * np.median(times):.1f} |", flush=True)


if __name__ == "__main__":
    main()
