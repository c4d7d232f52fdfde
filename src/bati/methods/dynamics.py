"""The probabilistic dynamics model p(r, s' | s, a, z) and its Gaussian NLL (Eq. 6-7).

Shared by BATI, Recon and UNICORN. The model predicts the reward and the state change
s' - s (an equivalent parameterisation of s'); the loss is Eq. 7 summed over output dimensions.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from bati.nets import MLP

MIN_LOG_VAR, MAX_LOG_VAR = -10.0, 5.0


class DynamicsModel(nn.Module):
    """(s, a, z) -> mean g and log-variance h of (r, s' - s)."""

    hidden_dims: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, obs, actions, z):
        h = MLP(self.hidden_dims, activate_final=True)(jnp.concatenate([obs, actions, z], -1))
        mean = nn.Dense(self.out_dim)(h)
        log_var = nn.Dense(self.out_dim)(h)
        # Soft bounds keep the variance sane without killing gradients.
        log_var = MAX_LOG_VAR - nn.softplus(MAX_LOG_VAR - log_var)
        log_var = MIN_LOG_VAR + nn.softplus(log_var - MIN_LOG_VAR)
        return mean, log_var


def transition_targets(transitions: dict) -> jax.Array:
    """X^t as the model predicts it: concat(r, s' - s)."""
    delta = transitions["next_observations"] - transitions["observations"]
    return jnp.concatenate([transitions["rewards"][..., None], delta], axis=-1)


def reconstruction_nll(mean: jax.Array, log_var: jax.Array, target: jax.Array) -> jax.Array:
    """Eq. 7 per transition: sum_d (x - g)^2 / exp(h) + h."""
    return jnp.sum((target - mean) ** 2 * jnp.exp(-log_var) + log_var, axis=-1)


def context_nll(model: DynamicsModel, params, transitions: dict, z: jax.Array) -> jax.Array:
    """Mean Eq. 7 NLL of transitions (..., C, dim) under latents z (..., latent) broadcast over C."""
    z = jnp.broadcast_to(z[..., None, :], transitions["observations"].shape[:-1] + z.shape[-1:])
    mean, log_var = model.apply(params, transitions["observations"], transitions["actions"], z)
    return reconstruction_nll(mean, log_var, transition_targets(transitions)).mean(-1)
