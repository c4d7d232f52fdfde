"""DPT (Lee et al., 2023): a causal transformer that reads the context and predicts the expert's action.

Training: for a query state s of task M and the causal transformer's summary h_j of the first
j transitions of a context of M (j uniform over the context), maximise the Gaussian likelihood
of the action the expert for M takes at s (discrete actions: the categorical likelihood of its
one-hot action). Our experts are task-conditioned, so they label any query state. Test time: h of the whole context is the latent, and the action is the predicted
mean at the current state: DPT is its own policy (no IQL).

Deviation: the original DPT puts the query state in the sequence as a token; here the query
meets the context's summary in the action head, so one transformer pass over a context serves
every query and every prefix length.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp

from bati.checks import check_integer
from bati.envs import EPISODE_LENGTH
from bati.methods.base import MethodSpec, TaskInference
from bati.nets import MLP, GaussianHead, gaussian_log_prob

@dataclass(frozen=True)
class DPTConfig:
    """The size of DPT's causal transformer."""

    model_dim: int = 64
    """Width of the transformer (and of DPT's latent: the last position's summary)."""
    num_layers: int = 2
    num_heads: int = 4
    max_length: int = EPISODE_LENGTH
    """Longest context the learned positions cover."""

    def check(self, section: str = "dpt") -> None:
        """ValueError naming `section`.<setting> for a transformer that cannot be built."""
        for name in ("model_dim", "num_layers", "num_heads", "max_length"):
            check_integer(f"{section}.{name}", getattr(self, name))
        if self.model_dim % self.num_heads:
            raise ValueError(f"{section}.model_dim ({self.model_dim}) must be a multiple of {section}.num_heads "
                             f"({self.num_heads}): each head reads model_dim / num_heads features")


class CausalTransformer(nn.Module):
    """Pre-norm transformer over transitions: (..., C, in) -> (..., C, model_dim), position j sees 0..j."""

    model_dim: int = DPTConfig.model_dim
    num_layers: int = DPTConfig.num_layers
    num_heads: int = DPTConfig.num_heads
    max_length: int = DPTConfig.max_length

    @nn.compact
    def __call__(self, tokens: jax.Array) -> jax.Array:
        length = tokens.shape[-2]
        positions = self.param("positions", nn.initializers.normal(0.02), (self.max_length, self.model_dim))
        x = nn.Dense(self.model_dim)(tokens) + positions[:length]
        mask = nn.make_causal_mask(jnp.ones(tokens.shape[:-1]))
        for _ in range(self.num_layers):
            h = nn.LayerNorm()(x)
            x = x + nn.MultiHeadDotProductAttention(num_heads=self.num_heads)(h, h, mask=mask)
            x = x + MLP((4 * self.model_dim,), self.model_dim)(nn.LayerNorm()(x))
        return nn.LayerNorm()(x)


def transition_tokens(context: dict) -> jax.Array:
    """One token per transition: concat(s, a, r, s')."""
    return jnp.concatenate([context["observations"], context["actions"], context["rewards"][..., None],
                            context["next_observations"]], axis=-1)


class DPT(TaskInference):
    needs_context = True
    needs_expert_actions = True
    acts_itself = True

    Config = DPTConfig
    config_key = "dpt"

    def __init__(self, spec: MethodSpec, config: DPTConfig | None = None):
        config = config or DPTConfig()
        super().__init__(dataclasses.replace(spec, latent_dim=config.model_dim), config)
        self.transformer = CausalTransformer(config.model_dim, config.num_layers, config.num_heads, config.max_length)
        # discrete actions (one-hot, KuhnPoker): a categorical head over the action's logits
        head = MLP if spec.discrete_actions else GaussianHead
        self.action_head = head(spec.decoder_dims, spec.action_dim)

    def init(self, key):
        k_transformer, k_head = jax.random.split(key)
        s = self.spec
        tokens = jnp.zeros((1, 1, 2 * s.obs_dim + s.action_dim + 1))
        return {"transformer": self.transformer.init(k_transformer, tokens),
                "action_head": self.action_head.init(k_head, jnp.zeros((1, self.config.model_dim + s.obs_dim)))}

    def action_distribution(self, params, obs, z):
        """Mean (squashed into the action bounds) and log-std of the predicted action at obs."""
        mean, log_std = self.action_head.apply(params["action_head"], jnp.concatenate([z, obs], -1))
        return jnp.tanh(mean), log_std

    def action_log_prob(self, params, obs, z, actions):
        """log-likelihood of `actions` (one-hot for discrete actions) at obs given the summary z."""
        if self.spec.discrete_actions:
            logits = self.action_head.apply(params["action_head"], jnp.concatenate([z, obs], -1))
            return jnp.sum(actions * jax.nn.log_softmax(logits), axis=-1)
        mean, log_std = self.action_distribution(params, obs, z)
        return gaussian_log_prob(actions, mean, log_std)

    def loss(self, params, batch, key):
        summaries = self.transformer.apply(params["transformer"], transition_tokens(batch["context"]))  # (T, C, d)
        queries = batch["observations"]  # (T, B, obs_dim): states of the task's own data
        prefix = jax.random.randint(key, queries.shape[:2], 0, summaries.shape[1])
        z = jnp.take_along_axis(summaries, prefix[..., None], axis=1)  # (T, B, d)
        nll = -self.action_log_prob(params, queries, z, batch["expert_actions"]).mean()
        return nll, (summaries[:, -1], {"action_nll": nll})

    def infer(self, params, context, key):
        return self.transformer.apply(params["transformer"], transition_tokens(context))[..., -1, :]

    def act(self, params, obs, z):
        """The predicted mean action at obs given the context summary z (discrete: the mode, one-hot)."""
        if self.spec.discrete_actions:
            logits = self.action_head.apply(params["action_head"], jnp.concatenate([z, obs], -1))
            return jax.nn.one_hot(jnp.argmax(logits, -1), self.spec.action_dim)
        return self.action_distribution(params, obs, z)[0]
