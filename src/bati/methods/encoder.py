"""The context encoder shared by the encoder baselines (Recon, FOCAL, UNICORN, CSRO)."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax.numpy as jnp

from bati.nets import MLP


class ContextEncoder(nn.Module):
    """Per-transition MLP on (s, a, r, s'), mean-pooled over the context: (..., C, .) -> (..., latent).

    With `pool=False` it returns the per-transition latents (..., C, latent). `activation="tanh"` bounds each
    transition's latent in [-1, 1]^latent before the mean (the FOCAL / CSRO / ER-TRL code lineage's encoder);
    "none" leaves it unbounded.
    """

    hidden_dims: Sequence[int]
    latent_dim: int
    activation: str = "none"

    @nn.compact
    def __call__(self, context: dict, pool: bool = True):
        x = jnp.concatenate(
            [context["observations"], context["actions"], context["rewards"][..., None], context["next_observations"]],
            axis=-1,
        )
        per_transition = MLP(self.hidden_dims, self.latent_dim)(x)
        if self.activation == "tanh":
            per_transition = jnp.tanh(per_transition)
        return per_transition.mean(axis=-2) if pool else per_transition


def dummy_context(spec) -> dict:
    """A one-transition context with the spec's shapes (for initialising networks)."""
    return {"observations": jnp.zeros((1, 1, spec.obs_dim)), "actions": jnp.zeros((1, 1, spec.action_dim)),
            "rewards": jnp.zeros((1, 1)), "next_observations": jnp.zeros((1, 1, spec.obs_dim))}
