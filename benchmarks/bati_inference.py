"""Time BATI's Eq. 8 inference: N = 40 latents x K contexts of C = 200 transitions (Table 3 dims).

    python benchmarks/bati_inference.py [--family HalfCheetahVel]

Prints a markdown row per K: milliseconds per call (jitted, after warm-up; median of 50 calls).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from bati.methods import MethodSpec
from bati.methods.bati import BATI
from bati.envs import get_family

OBS_ACTION = {"PointGoal": (2, 2), "AntDir": (27, 8), "HalfCheetahVel": (17, 6), "HalfCheetahDir": (17, 6),
              "HopperParam": (11, 3), "WalkerParam": (17, 6)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--family", default="HalfCheetahVel", choices=sorted(OBS_ACTION))
    parser.add_argument("--context-length", type=int, default=200)
    args = parser.parse_args()
    obs_dim, action_dim = OBS_ACTION[args.family]
    record = get_family(args.family).record
    spec = MethodSpec(obs_dim, action_dim, 1, 20, record.latent_dim, record.net_dims, record.net_dims)
    method = BATI(spec)
    params = method.init(jax.random.PRNGKey(0))
    infer = jax.jit(method.infer)
    print("| family | contexts K | C | N | ms per call |\n| --- | --- | --- | --- | --- |")
    for k in (1, 20):
        c = args.context_length
        rng = np.random.default_rng(0)
        context = {"observations": jnp.asarray(rng.normal(size=(k, c, obs_dim)), jnp.float32),
                   "actions": jnp.asarray(rng.uniform(-1, 1, (k, c, action_dim)), jnp.float32),
                   "rewards": jnp.asarray(rng.normal(size=(k, c)), jnp.float32),
                   "next_observations": jnp.asarray(rng.normal(size=(k, c, obs_dim)), jnp.float32)}
        infer(params, context, jax.random.PRNGKey(1)).block_until_ready()
        times = []
        for i in range(50):
            start = time.perf_counter()
            infer(params, context, jax.random.PRNGKey(i)).block_until_ready()
            times.append(time.perf_counter() - start)
        print(f"| {args.family} | {k} | {c} | {method.num_latent_samples} | {1e3 * np.median(times):.2f} |")


if __name__ == "__main__":
    main()
