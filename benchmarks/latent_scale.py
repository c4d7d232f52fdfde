"""How large are an encoder method's latents, and how much of them is the task?

IQL's critic and actor read the latent z beside the state. A metric loss like FOCAL's only sees distances
between latents, so nothing in it keeps their common offset near the origin; a term that moves z for
another reason (ER-TRL's entropy) can drift it far from the scale the IQL networks were initialised for.
For each run (its last checkpoint) this infers z from `--repeats` contexts of every training task
(p_train data, the run's context length) and writes, as JSON: the mean and largest norm of z, the largest
absolute component, the spread of z within a task (over contexts, the encoder's noise) and between tasks
(of the per-task means, what carries the task).

    python benchmarks/latent_scale.py results/cpu/experiments/HalfCheetahVel/cpu-eps1-41518e24/er-trl-seed0 \
        results/cpu/experiments/HalfCheetahVel/cpu-eps1-e867f1c3/csro-seed0 \
        --out results/diagnostics/latent-scale-HalfCheetahVel-cpu.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.data import sample_contexts
from bati.device import describe_device
from bati.io import atomic_write_json, git_commit
from bati.run_dir import open_run


def latent_scale(run_dir: Path, repeats: int) -> dict:
    """The numbers above for one run."""
    run = open_run(run_dir)
    method, params, train = run.trainer.method, run.state.method.params, run.data.train
    length = run.config.eval_context_length
    ids = jnp.arange(train.n_tasks)
    infer = jax.jit(lambda context, key: method.infer(params, context, key))
    keys = jax.random.split(jax.random.PRNGKey(0), repeats)
    z = np.stack([np.asarray(infer(sample_contexts(train, k, ids, length), k)) for k in keys])  # (R, tasks, d)
    norms = np.linalg.norm(z, axis=-1)
    return {"run_dir": str(run_dir), "family": run.config.family, "method": run.config.method,
            "seed": run.config.seed, "step": run.step, "context_length": length, "repeats": repeats,
            "norm_mean": float(norms.mean()), "norm_max": float(norms.max()),
            "abs_component_max": float(np.abs(z).max()),
            "within_task_std": float(z.std(axis=0).mean()), "between_task_std": float(z.mean(axis=0).std(axis=0).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories with a checkpoint")
    parser.add_argument("--repeats", type=int, default=4, help="contexts per training task")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    args = parser.parse_args()
    missing = [str(r) for r in args.runs if not (r / "checkpoint.msgpack").exists()]
    if missing:
        parser.error(f"no checkpoint in {', '.join(missing)}")
    start = time.perf_counter()
    rows = []
    for run_dir in args.runs:
        rows.append(latent_scale(run_dir, args.repeats))
        print(f"{rows[-1]['method']} seed {rows[-1]['seed']}: |z| mean {rows[-1]['norm_mean']:.2f}, "
              f"within-task std {rows[-1]['within_task_std']:.3f}, between-task std {rows[-1]['between_task_std']:.3f}")
    atomic_write_json(args.out, {"runs": rows, "commit": git_commit(), "device": describe_device(),
                                 "wall_time_s": round(time.perf_counter() - start, 1)})


if __name__ == "__main__":
    main()
