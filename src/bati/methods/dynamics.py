"""The probabilistic dynamics model p(r, s' | s, a, z) and its Gaussian NLL (Eq. 6-7).

Shared by BATI, Recon and UNICORN. The model predicts the reward and the state change
s' - s (an equivalent parameterisation of s'); the loss is Eq. 7 summed over output dimensions.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from bati.nets import MLP

MIN_LOG_VAR, MAX_LOG_VAR = -10.0, 5.0


class GaussianRegressor(nn.Module):
    """x -> (mean, soft-bounded log-variance) of an out_dim Gaussian."""

    hidden_dims: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, x):
        h = MLP(self.hidden_dims, activate_final=True)(x)
        mean = nn.Dense(self.out_dim)(h)
        log_var = nn.Dense(self.out_dim)(h)
        # Soft bounds keep the variance sane without killing gradients.
        log_var = MAX_LOG_VAR - nn.softplus(MAX_LOG_VAR - log_var)
        log_var = MIN_LOG_VAR + nn.softplus(log_var - MIN_LOG_VAR)
        return mean, log_var


class DynamicsModel(nn.Module):
    """(s, a, z) -> mean g and log-variance h of (r, s' - s).

    The reward and the state change get separate trunks: near-deterministic state dimensions
    drive their variance down and their NLL gradients up, which would otherwise drown the
    (noisy) reward's dependence on z in a shared trunk.
    """

    hidden_dims: Sequence[int]
    out_dim: int

    @nn.compact
    def __call__(self, obs, actions, z):
        x = jnp.concatenate([obs, actions, z], -1)
        reward_mean, reward_log_var = GaussianRegressor(self.hidden_dims, 1)(x)
        state_mean, state_log_var = GaussianRegressor(self.hidden_dims, self.out_dim - 1)(x)
        return (jnp.concatenate([reward_mean, state_mean], -1), jnp.concatenate([reward_log_var, state_log_var], -1))


def init_dynamics(model: DynamicsModel, key: jax.Array, spec) -> dict:
    """The model's parameters for the spec's observation, action and latent widths."""
    return model.init(key, jnp.zeros((1, spec.obs_dim)), jnp.zeros((1, spec.action_dim)), jnp.zeros((1, spec.latent_dim)))


def transition_targets(transitions: dict) -> jax.Array:
    """X^t as the model predicts it: concat(r, s' - s)."""
    delta = transitions["next_observations"] - transitions["observations"]
    return jnp.concatenate([transitions["rewards"][..., None], delta], axis=-1)


def reconstruction_nll(mean: jax.Array, log_var: jax.Array, target: jax.Array) -> jax.Array:
    """Eq. 7 per transition: sum_d (x - g)^2 / exp(h) + h."""
    return jnp.sum((target - mean) ** 2 * jnp.exp(-log_var) + log_var, axis=-1)


def context_nll(model: DynamicsModel, params, transitions: dict, z: jax.Array, reward_only: bool = False) -> jax.Array:
    """Mean Eq. 7 NLL of transitions (..., C, dim) under latents z (..., latent) broadcast over C.

    With `reward_only`, only the reward's term of Eq. 7 (the first output dimension) counts.
    """
    z = jnp.broadcast_to(z[..., None, :], transitions["observations"].shape[:-1] + z.shape[-1:])
    mean, log_var = model.apply(params, transitions["observations"], transitions["actions"], z)
    target = transition_targets(transitions)
    if reward_only:
        mean, log_var, target = mean[..., :1], log_var[..., :1], target[..., :1]
    return reconstruction_nll(mean, log_var, target).mean(-1)


def context_nll_terms(model: DynamicsModel, params, transitions: dict, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Eq. 7's two parts, each a mean over the C transitions: the reward's NLL and the state change's NLL
    (summed over its dimensions), so that `context_nll` = reward + state (up to rounding)."""
    z = jnp.broadcast_to(z[..., None, :], transitions["observations"].shape[:-1] + z.shape[-1:])
    mean, log_var = model.apply(params, transitions["observations"], transitions["actions"], z)
    target = transition_targets(transitions)
    reward = reconstruction_nll(mean[..., :1], log_var[..., :1], target[..., :1]).mean(-1)
    state = reconstruction_nll(mean[..., 1:], log_var[..., 1:], target[..., 1:]).mean(-1)
    return reward, state
