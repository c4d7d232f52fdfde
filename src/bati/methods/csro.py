"""CSRO (Gao et al., 2024): FOCAL's objective plus a CLUB upper bound on I(z; (s, a)).

The encoder's per-transition latents z_i should carry the task, not the behaviour that chose
(s_i, a_i). A variational network q(z | s, a) (Table 3: 200 x 3) is fit by maximum likelihood on
the detached latents; the encoder minimises CLUB (Cheng et al., 2020),
    I(z; x) <= E_p(z,x)[log q(z | x)] - E_p(z)p(x)[log q(z | x)],
estimated with one negative x per latent: the (s, a) of a random other transition of the batch
(any task), on latents centred over the batch. Loss = L_FOCAL + lambda * CLUB with Table 3's
weight lambda per family.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import jax
import jax.numpy as jnp

from bati.envs.base import FamilyRecord, record_default
from bati.methods.base import MethodSpec
from bati.methods.focal import FOCAL, FOCALConfig
from bati.nets import GaussianHead, gaussian_log_prob


@dataclass(frozen=True)
class CSROConfig(FOCALConfig):
    club_weight: float | None = None
    """lambda, the CLUB term's weight (default: the family's, Table 3: FamilyRecord.club_weight)."""
    club_hidden_dims: tuple[int, ...] = (200, 200, 200)
    """Hidden sizes of the variational network q(z | s, a) (Table 3: 200 x 3)."""

    def for_family(self, record: FamilyRecord | None) -> CSROConfig:
        if self.club_weight is not None:
            return self
        return replace(self, club_weight=record.club_weight if record else record_default("club_weight"))


def club_estimate(log_q: Callable, z: jax.Array, x: jax.Array, x_negative: jax.Array) -> jax.Array:
    """CLUB: mean log q(z_i | x_i) minus mean log q(z_i | x'_i), x'_i drawn independently of z_i."""
    return log_q(z, x).mean() - log_q(z, x_negative).mean()


class CSRO(FOCAL):
    Config = CSROConfig
    config_key = "csro"

    def __init__(self, spec: MethodSpec, config: CSROConfig | None = None):
        super().__init__(spec, config)
        self.club_net = GaussianHead(tuple(self.config.club_hidden_dims), spec.latent_dim)
        self.weight = self.config.club_weight

    def init(self, key):
        k_enc, k_club = jax.random.split(key)
        s = self.spec
        return {**super().init(k_enc), "club": self.club_net.init(k_club, jnp.zeros((1, s.obs_dim + s.action_dim)))}

    def log_q(self, club_params, z, state_actions):
        """log q(z | s, a) under the variational network."""
        mean, log_std = self.club_net.apply(club_params, state_actions)
        return gaussian_log_prob(z, mean, log_std)

    def loss(self, params, batch, key):
        context = batch["context"]
        per_transition = self.encoder.apply(params["encoder"], context, pool=False)  # (T, C, d)
        z = per_transition.mean(axis=-2)
        metric = self.pair_loss(params, batch, z)

        latents = per_transition.reshape(-1, per_transition.shape[-1])
        # I(z; x) ignores a common shift of z; centring makes the estimate ignore it too. Without it,
        # CLUB under a lagging q drags all latents away together (|z| ~ 100 after 3k PointGoal steps),
        # which FOCAL's translation-invariant loss does nothing to stop, and IQL's critic diverged.
        latents = latents - latents.mean(axis=0)
        state_actions = jnp.concatenate([context["observations"], context["actions"]], -1)
        state_actions = state_actions.reshape(-1, state_actions.shape[-1])
        negatives = jax.random.permutation(key, state_actions.shape[0])
        # The encoder minimises CLUB under a fixed q ...
        frozen_q = jax.lax.stop_gradient(params["club"])
        club = club_estimate(partial(self.log_q, frozen_q), latents, state_actions, state_actions[negatives])
        # ... while q fits the detached latents by maximum likelihood.
        q_nll = -self.log_q(params["club"], jax.lax.stop_gradient(latents), state_actions).mean()
        loss = metric + self.weight * club + q_nll
        return loss, (z, {"metric_loss": metric, "club": club, "club_q_nll": q_nll})
