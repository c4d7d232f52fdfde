"""Networks shared by the experts, IQL and every task-inference method, and the critics' TrainState."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax.training.train_state import TrainState

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


class MLP(nn.Module):
    """ReLU MLP; the last layer is linear unless `activate_final`."""

    hidden_dims: Sequence[int]
    out_dim: int | None = None
    activate_final: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        dims = list(self.hidden_dims) + ([self.out_dim] if self.out_dim is not None else [])
        for i, dim in enumerate(dims):
            x = nn.Dense(dim, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0)))(x)
            if i < len(dims) - 1 or self.activate_final:
                x = nn.relu(x)
        return x


class GaussianHead(nn.Module):
    """MLP -> (mean, log_std) of a diagonal Gaussian, log_std clipped to a sane range."""

    hidden_dims: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = MLP(self.hidden_dims, activate_final=True)(x)
        mean = nn.Dense(self.out_dim)(h)
        log_std = nn.Dense(self.out_dim)(h)
        return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)


class DoubleCritic(nn.Module):
    """Twin Q(s, a, ...) networks, vmapped over their parameters."""

    hidden_dims: Sequence[int]

    @nn.compact
    def __call__(self, inputs: jax.Array) -> jax.Array:
        critics = nn.vmap(
            MLP,
            variable_axes={"params": 0},
            split_rngs={"params": True},
            in_axes=None,
            out_axes=0,
            axis_size=2,
        )(self.hidden_dims, 1)
        return critics(inputs)[..., 0]


def gaussian_log_prob(x: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """log N(x; mean, exp(log_std)^2), summed over the last axis."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


class CriticState(TrainState):
    """A critic's flax TrainState plus its Polyak-averaged target parameters (SAC's and IQL's)."""

    target_params: Any = None
