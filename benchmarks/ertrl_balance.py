"""How strongly does ER-TRL's entropy term pull on the encoder, beside FOCAL's metric loss?

ER-TRL's encoder minimises w L_FOCAL - lambda H (docs/methods.md, "ER-TRL"). Adam makes the encoder's step
depend on the ratio of those two gradients, not on their scale, so this measures, on a run's training
batches, the norms of grad L_FOCAL (our squared distance, and the authors' code's root-mean distance with
its beta 1 and eps 0.1) and of grad H with respect to the encoder's parameters, and prints the entropy's
share |lambda grad H| / |w grad L_FOCAL| for our weighting (w = 1 before 691302f, w = 10 since) and the
code's (root-mean distance, z_loss_weight w = 10), at the run's last checkpoint and at a fresh
initialisation. Writes the numbers as JSON.

    python benchmarks/ertrl_balance.py results/cpu/experiments/AntDir/cpu-eps1-92872b3a/er-trl-seed0 \
        --out results/diagnostics/ertrl-balance-AntDir-cpu.json
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.device import describe_device
from bati.io import atomic_write_json, git_commit
from bati.methods.er_trl import gaussian_entropy
from bati.methods.focal import metric_loss
from bati.run_dir import open_run

CODE_METRIC_WEIGHT = 10.0  # the authors' z_loss_weight
CODE_PUSH = (1.0, 0.1)  # the authors' FOCAL_z_loss: 1 / (mean squared distance + 100 * 1e-3)


def encoder_terms(method, params, encoder, batch, key):
    """(L_FOCAL squared, L_FOCAL root-mean as the code, mean_t H_t) as functions of the encoder's params."""
    config = method.config
    z = method.encoder.apply(encoder, batch["context"])
    latents = jnp.concatenate([z, method.encoder.apply(encoder, batch["positive_context"])])
    labels = jnp.concatenate([batch["task_ids"], batch["task_ids"]])
    squared = metric_loss(latents, labels, config.push_weight, config.push_epsilon, "squared")
    root_mean = metric_loss(latents, labels, *CODE_PUSH, "root-mean")
    observations = batch["observations"]
    z_per_state = jnp.broadcast_to(z[:, None, :], observations.shape[:2] + z.shape[-1:])
    noise = jax.random.normal(key, observations.shape[:2] + (config.noise_dim,))
    behaviour = method.generate(jax.lax.stop_gradient(params["generator"]), observations, z_per_state, noise)
    return squared, root_mean, gaussian_entropy(behaviour, config.covariance_epsilon).mean()


def measure(run, params, batches: int) -> dict:
    trainer, method = run.trainer, run.trainer.method
    flat = lambda tree: jnp.concatenate([leaf.ravel() for leaf in jax.tree_util.tree_leaves(tree)])  # noqa: E731
    rows = []
    for i in range(batches):
        k_batch, k_context, k_noise = jax.random.split(jax.random.PRNGKey(100 + i), 3)
        batch = trainer.make_batch(run.data.train, k_batch, k_context)
        values = encoder_terms(method, params, params["encoder"], batch, k_noise)
        grads = [flat(jax.grad(lambda e, j=j: encoder_terms(method, params, e, batch, k_noise)[j])(params["encoder"]))
                 for j in range(3)]
        norms = [float(jnp.linalg.norm(g)) for g in grads]
        cosine = float(jnp.dot(grads[0], grads[2]) / (norms[0] * norms[2] + 1e-12))
        rows.append([float(v) for v in values] + norms + [cosine])
    m = np.mean(rows, axis=0)
    lam = method.config.entropy_weight
    return {"metric_loss_squared": m[0], "metric_loss_root_mean": m[1], "entropy": m[2],
            "grad_norm_metric_squared": m[3], "grad_norm_metric_root_mean": m[4], "grad_norm_entropy": m[5],
            "cosine_metric_squared_entropy": m[6],
            "entropy_share_weight_1": lam * m[5] / m[3],
            "entropy_share_weight_10": lam * m[5] / (10.0 * m[3]),
            "entropy_share_code": lam * m[5] / (CODE_METRIC_WEIGHT * m[4])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path, help="an er-trl run directory with a checkpoint")
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--out", type=Path, help="JSON file to write")
    args = parser.parse_args()
    start = time.perf_counter()
    run = open_run(args.run_dir)
    if run.config.method != "er-trl":
        parser.error(f"{args.run_dir} is a {run.config.method} run, not er-trl")
    result = {"run_dir": str(args.run_dir), "step": run.step, "entropy_weight": run.trainer.method.config.entropy_weight,
              "run_metric_weight": run.trainer.method.config.metric_weight, "batches": args.batches,
              "checkpoint": measure(run, run.state.method.params, args.batches),
              "init": measure(run, run.trainer.method.init(jax.random.PRNGKey(3)), args.batches)}
    result.update(commit=git_commit(), device=describe_device(), wall_time_s=round(time.perf_counter() - start, 1))
    for where in ("checkpoint", "init"):
        r = result[where]
        print(f"{where}: |grad L_sq| {r['grad_norm_metric_squared']:.3g}, |grad L_root-mean| "
              f"{r['grad_norm_metric_root_mean']:.3g}, |grad H| {r['grad_norm_entropy']:.3g}; entropy's share "
              f"|lambda grad H| / |w grad L|: w = 1 {r['entropy_share_weight_1']:.2f}, w = 10 "
              f"{r['entropy_share_weight_10']:.2f}, the code (root-mean, w = 10) {r['entropy_share_code']:.2f}")
    if args.out:
        atomic_write_json(args.out, result)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
