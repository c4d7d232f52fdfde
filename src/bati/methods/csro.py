"""CSRO (Gao et al., 2024): FOCAL's objective plus a CLUB upper bound on I(z; (s, a)).

The encoder's per-transition latents z_i should carry the task, not the behaviour that chose
(s_i, a_i). A variational network q(z | s, a) (Table 3: 200 x 3) is fit by maximum likelihood on
the detached latents; the encoder minimises CLUB (Cheng et al., 2020),
    I(z; x) <= E_p(z,x)[log q(z | x)] - E_p(z)p(x)[log q(z | x)],
under the frozen q, on latents centred over the batch. Loss = L_FOCAL + lambda * CLUB with Table 3's
weight lambda per family.

Where the negative pairs come from decides what CLUB penalises (`club_negatives`):
- "same-task" (default; the official CSRO code, which the paper ported): each latent z_j is paired
  with q(. | x_i) of every transition i of its own task's context. z may then vary between tasks
  freely; only what it says about (s, a) within a task is penalised.
- "any-task" (bati before 2026-11-25): one random other transition of the whole batch. This is
  CLUB of the marginal I(z; x), and x carries the task (each task's data comes from its own expert),
  so it penalises the task information itself: on AntDir and HopperParam every run's latents
  collapsed to one point within 0.7k-6k steps (FOCAL's push has no gradient at coincidence), the
  conflict the paper's Sec. 3.2 describes taken to its end. Kept to reproduce those runs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Annotated, Literal

import jax
import jax.numpy as jnp

from bati.cli_hints import DEFAULT_IN_DOC
from bati.envs.base import FamilyRecord, record_default
from bati.methods.base import MethodSpec
from bati.methods.focal import FOCAL, FOCALConfig
from bati.nets import GaussianHead, gaussian_log_prob


@dataclass(frozen=True)
class CSROConfig(FOCALConfig):
    club_weight: Annotated[float | None, DEFAULT_IN_DOC] = None
    """lambda, the CLUB term's weight (default: the family's, Table 3: FamilyRecord.club_weight)."""
    club_hidden_dims: tuple[int, ...] = (200, 200, 200)
    """Hidden sizes of the variational network q(z | s, a) (Table 3: 200 x 3)."""
    club_negatives: Literal["same-task", "any-task"] = "same-task"
    """CLUB's negative pairs: every transition of the latent's own task (the official code) or one random
    transition of the batch (the marginal CLUB, bati's before 2026-11-25: its latents collapse)."""

    def check(self, section: str = "csro") -> None:
        super().check(section)
        if self.club_negatives not in ("same-task", "any-task"):
            raise ValueError(f"{section}.club_negatives must be 'same-task' or 'any-task', got {self.club_negatives!r}")

    def for_family(self, record: FamilyRecord | None) -> CSROConfig:
        if self.club_weight is not None:
            return self
        return replace(self, club_weight=record.club_weight if record else record_default("club_weight"))


def club_estimate(log_q: Callable, z: jax.Array, x: jax.Array, x_negative: jax.Array) -> jax.Array:
    """CLUB: mean log q(z_i | x_i) minus mean log q(z_i | x'_i), x'_i drawn independently of z_i."""
    return log_q(z, x).mean() - log_q(z, x_negative).mean()


def club_within_tasks(z: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """The official CSRO code's CLUB on each task's context, all C x C pairs of a task as negatives.

    z, mean, log_std: (T, C, d), q(. | x_i) = N(mean_i, exp(log_std_i)^2) at transition i. Returns the mean
    over tasks, transitions i and latent dimensions of
        mean_j (z_j - mean_i)^2 / sigma_i^2  -  (z_i - mean_i)^2 / sigma_i^2     (j over i's task),
    from z's per-task moments (mean_j (z_j - m)^2 = E[z^2] - 2 m E[z] + m^2). This is the Gaussian CLUB
    times 2 / d (q's normaliser cancels within a pair); it is the code's scale, so Table 3's lambda keeps
    its meaning."""
    inverse_variance = jnp.exp(-2.0 * log_std)
    positive = (z - mean) ** 2 * inverse_variance
    first, second = z.mean(axis=-2, keepdims=True), (z**2).mean(axis=-2, keepdims=True)
    negative = (second - 2.0 * mean * first + mean**2) * inverse_variance
    return (negative - positive).mean()


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

        # I(z; x) ignores a common shift of z; centring makes the estimate ignore it too. Without it,
        # CLUB under a lagging q drags all latents away together (|z| ~ 100 after 3k PointGoal steps),
        # which FOCAL's translation-invariant loss does nothing to stop, and IQL's critic diverged.
        latents = per_transition - per_transition.mean(axis=(0, 1))
        state_actions = jnp.concatenate([context["observations"], context["actions"]], -1)  # (T, C, s + a)
        if self.config.club_negatives == "same-task":
            mean, log_std = self.club_net.apply(params["club"], state_actions)  # one pass of q serves both terms
            # The encoder minimises CLUB under a fixed q ...
            club = club_within_tasks(latents, jax.lax.stop_gradient(mean), jax.lax.stop_gradient(log_std))
            # ... while q fits the detached latents by maximum likelihood.
            q_nll = -gaussian_log_prob(jax.lax.stop_gradient(latents), mean, log_std).mean()
        else:
            frozen_q = jax.lax.stop_gradient(params["club"])
            flat_latents, flat_x = latents.reshape(-1, latents.shape[-1]), state_actions.reshape(-1, state_actions.shape[-1])
            negatives = jax.random.permutation(key, flat_x.shape[0])
            club = club_estimate(partial(self.log_q, frozen_q), flat_latents, flat_x, flat_x[negatives])
            q_nll = -self.log_q(params["club"], jax.lax.stop_gradient(latents), state_actions).mean()
        loss = metric + self.weight * club + q_nll
        return loss, (z, {"metric_loss": metric, "club": club, "club_q_nll": q_nll})
