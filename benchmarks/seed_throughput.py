"""Seed-steps per second when k seeds train as one program vmapped over seeds (`Trainer.run_chunks`).

    python benchmarks/seed_throughput.py [--family HalfCheetahVel] [--method bati] [--scale paper] [--seeds 1 3 8]

Random data shaped like the family's (no collection needed). For each k: one chunk of `--length` steps
compiles, then the median over `--chunks` chunks gives seconds per step of the k-seed program;
seed-steps/s = k / that; with XLA's count of one seed-step's flops and bytes, the achieved TFLOP/s and TB/s
(how close the step is to the device's limits). `--precision tensorfloat32|bfloat16` lowers the float32
matmuls' precision (runs use the default). Prints a Markdown table with the device JAX ran on. Target:
>= 3x the single-seed rate at paper scale on one H100 through vmapped seeds.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from train_step import DIMS, make_trainer, random_data

from bati.config import TrainConfig
from bati.device import describe_device
from bati.trainer import Trainer


def seed_steps_per_second(trainer: Trainer, data, k: int, length: int, chunks: int) -> float:
    keys = jax.random.split(jax.random.PRNGKey(0), k)
    states = jax.vmap(trainer.init)(keys)
    states, _ = trainer.run_chunks(states, keys, data.train, length=length)  # compile
    jax.block_until_ready(states)
    times = []
    for _ in range(chunks):
        start = time.perf_counter()
        states, _ = trainer.run_chunks(states, keys, data.train, length=length)
        jax.block_until_ready(states)
        times.append((time.perf_counter() - start) / length)
    return k / float(np.median(times))


def cost_per_seed_step(trainer: Trainer, data) -> tuple[float, float]:
    """XLA's count of (flops, bytes accessed) of one training step of one seed (its cost analysis of the
    compiled step on this device): with seed-steps/s it gives the achieved TFLOP/s and TB/s."""
    state = trainer.init(jax.random.PRNGKey(0))
    step = jax.jit(lambda s, k: trainer.step(s, k, data.train))
    cost = step.lower(state, jax.random.PRNGKey(1)).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return float(cost.get("flops", np.nan)), float(cost.get("bytes accessed", np.nan))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--family", default="HalfCheetahVel", choices=sorted(DIMS))
    parser.add_argument("--method", default="bati")
    parser.add_argument("--scale", default="paper", choices=("quick", "cpu", "paper"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 3, 8])
    parser.add_argument("--length", type=int, default=20)
    parser.add_argument("--chunks", type=int, default=3)
    parser.add_argument("--precision", default="default", choices=("default", "tensorfloat32", "bfloat16", "highest"),
                        help="float32 matmul precision (jax.default_matmul_precision); the runs' is the default")
    args = parser.parse_args()
    with jax.default_matmul_precision(None if args.precision == "default" else args.precision):
        run(args)


def run(args) -> None:
    data = random_data(args.family)
    config = TrainConfig(family=args.family, method=args.method, scale=args.scale).resolved()
    trainer = make_trainer(config, data)
    flops, bytes_accessed = cost_per_seed_step(trainer, data)
    print(f"device: {describe_device()}; jax {jax.__version__}; {args.family} {args.method} {args.scale} "
          f"({config.task_batch} x {config.batch_size}, IQL {config.iql.hidden_dims}); matmul precision "
          f"{args.precision}; XLA's count per seed-step: {flops / 1e9:.2f} GFLOP, {bytes_accessed / 1e9:.2f} GB")
    print("| seeds k | ms per step (all k) | seed-steps / s | vs k = 1 | TFLOP/s | TB/s |\n"
          "| --- | --- | --- | --- | --- | --- |")
    base = None
    for k in args.seeds:
        rate = seed_steps_per_second(trainer, data, k, args.length, args.chunks)
        base = base or rate
        print(f"| {k} | {1e3 * k / rate:.1f} | {rate:.1f} | {rate / base:.2f}x | {rate * flops / 1e12:.2f} | "
              f"{rate * bytes_accessed / 1e12:.2f} |", flush=True)


if __name__ == "__main__":
    main()
