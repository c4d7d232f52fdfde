"""ER-TRL (Nakhaei, Scannell and Pajarinen, AAAI 2025): FOCAL plus the entropy of the behaviour policy
given the task representation.

A representation z that encodes the policy which collected the context makes that policy predictable
from z: pi_beta(a | s, z) is narrow. ER-TRL keeps FOCAL's distance metric loss and makes the encoder
maximise the entropy of pi_beta(. | s, z), estimated adversarially:
- a conditional generator a = G(s, z, noise) is trained against a discriminator D(s, a, z) to produce
  the data's actions (a GAN on the batch transitions, z detached);
- for each batch task t, the generator's actions at that task's B states under its latent z_t are
  fitted with a Gaussian; its entropy H_t = 1/2 log det(2 pi e Sigma_t) is what the encoder raises,
  through z_t only (the generator frozen).
Loss = w L_FOCAL - lambda * mean_t H_t + L_D + L_G (w = 10, the code's z_loss_weight), each part reaching only
its own networks (stop_gradient keeps the adversarial game apart, as CSRO's CLUB), one optimiser step per
training step.

As the authors' code, the encoder bounds each transition's latent with tanh (`latent_activation`): FOCAL's metric
sees only distances, and unbounded latents let the entropy term drift their common offset.

Our choices (docs/methods.md): IQL instead of BRAC as the offline RL core (as every method here); one
GAN update per step instead of the code's five, on the method's Adam (learning_rate 3e-4) instead of
2e-4; lambda per family from the code's `mir_loss_weight` (FamilyRecord.entropy_weight) and FOCAL's term at the
code's weight 10 (`metric_weight`), with our FOCAL's distance and settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Annotated, Literal

import jax
import jax.numpy as jnp

from bati.checks import check_integer, check_number
from bati.cli_hints import DEFAULT_IN_DOC
from bati.envs.base import FamilyRecord, record_default
from bati.methods.base import MethodSpec
from bati.methods.focal import FOCAL, FOCALConfig
from bati.nets import MLP


@dataclass(frozen=True)
class ERTRLConfig(FOCALConfig):
    entropy_weight: Annotated[float | None, DEFAULT_IN_DOC] = None
    """lambda, the weight of the behaviour-entropy term (default: the family's, FamilyRecord.entropy_weight)."""
    noise_dim: int = 20
    """Dimension of the generator's Gaussian noise (the code's generator_dim)."""
    gan_hidden_dims: tuple[int, ...] = (256, 256)
    """Hidden sizes of the generator and the discriminator."""
    covariance_epsilon: float = 1e-5
    """Added to the diagonal of each task's action covariance before its log-determinant."""
    metric_weight: float = 10.0
    """Weight of FOCAL's metric loss beside lambda H (the code's z_loss_weight): it sets the balance between
    separating tasks and raising the entropy (runs recorded before this field had 1.0)."""
    latent_activation: Literal["none", "tanh"] = "tanh"
    """The encoder bounds each transition's latent with tanh, as the authors' code does (FOCAL's metric sees only
    distances, so unbounded latents let the entropy term drift their common offset: runs recorded before this
    field had "none")."""

    def for_family(self, record: FamilyRecord | None) -> ERTRLConfig:
        if self.entropy_weight is not None:
            return self
        return replace(self, entropy_weight=record.entropy_weight if record else record_default("entropy_weight"))

    def check(self, section: str = "ertrl") -> None:
        super().check(section)
        check_integer(f"{section}.noise_dim", self.noise_dim)
        check_number(f"{section}.metric_weight", self.metric_weight, positive=False)
        check_number(f"{section}.covariance_epsilon", self.covariance_epsilon)


def gaussian_entropy(samples: jax.Array, epsilon: float = 1e-5) -> jax.Array:
    """Entropy of the Gaussian fitted to each row's samples: (T, B, A) -> (T,), unbiased covariance."""
    n, dim = samples.shape[-2], samples.shape[-1]
    centred = samples - samples.mean(axis=-2, keepdims=True)
    covariance = jnp.einsum("...ba,...bc->...ac", centred, centred) / (n - 1) + epsilon * jnp.eye(dim)
    _, log_det = jnp.linalg.slogdet(covariance)
    return 0.5 * (dim * (1.0 + math.log(2.0 * math.pi)) + log_det)


def discriminator_loss(real_logits: jax.Array, fake_logits: jax.Array) -> jax.Array:
    """Binary cross-entropy: the data's actions labelled 1, the generator's 0."""
    return jax.nn.softplus(-real_logits).mean() + jax.nn.softplus(fake_logits).mean()


def generator_loss(fake_logits: jax.Array) -> jax.Array:
    """The generator's non-saturating loss: its actions labelled 1 by the discriminator."""
    return jax.nn.softplus(-fake_logits).mean()


class ERTRL(FOCAL):
    Config = ERTRLConfig
    config_key = "ertrl"
    config_help = "er-trl (FOCAL's settings plus its behaviour-entropy term)."

    def __init__(self, spec: MethodSpec, config: ERTRLConfig | None = None):
        super().__init__(spec, config)
        dims = tuple(self.config.gan_hidden_dims)
        self.generator = MLP(dims, spec.action_dim)
        self.discriminator = MLP(dims, 1)

    def init(self, key):
        k_enc, k_gen, k_disc = jax.random.split(key, 3)
        s = self.spec
        return {**super().init(k_enc),
                "generator": self.generator.init(k_gen, jnp.zeros((1, s.obs_dim + s.latent_dim + self.config.noise_dim))),
                "discriminator": self.discriminator.init(k_disc, jnp.zeros((1, s.obs_dim + s.action_dim + s.latent_dim)))}

    def generate(self, generator_params, observations, z, noise):
        """The behaviour model's actions at observations (T, B, obs) for latents z (T, B, d), in [-1, 1]."""
        return jnp.tanh(self.generator.apply(generator_params, jnp.concatenate([observations, z, noise], -1)))

    def judge(self, discriminator_params, observations, actions, z):
        """The discriminator's logit that (s, a) is the data's, given z: (T, B)."""
        return self.discriminator.apply(discriminator_params, jnp.concatenate([observations, actions, z], -1))[..., 0]

    def loss(self, params, batch, key):
        metric, z = self.contrastive_loss(params, batch)
        observations, actions = batch["observations"], batch["actions"]
        z_per_state = jnp.broadcast_to(z[:, None, :], observations.shape[:2] + z.shape[-1:])
        fixed_z = jax.lax.stop_gradient(z_per_state)
        noise = jax.random.normal(key, observations.shape[:2] + (self.config.noise_dim,))
        # The GAN fits pi_beta(a | s, z) with z detached ...
        fake = self.generate(params["generator"], observations, fixed_z, noise)
        d_loss = discriminator_loss(self.judge(params["discriminator"], observations, actions, fixed_z),
                                    self.judge(params["discriminator"], observations, jax.lax.stop_gradient(fake),
                                               fixed_z))
        g_loss = generator_loss(self.judge(jax.lax.stop_gradient(params["discriminator"]), observations, fake,
                                           fixed_z))
        # ... and the encoder raises its entropy through z alone, the generator frozen.
        behaviour = self.generate(jax.lax.stop_gradient(params["generator"]), observations, z_per_state, noise)
        entropy = gaussian_entropy(behaviour, self.config.covariance_epsilon).mean()
        loss = self.config.metric_weight * metric - self.config.entropy_weight * entropy + d_loss + g_loss
        return loss, (z, {"metric_loss": metric, "behaviour_entropy": entropy, "discriminator_loss": d_loss,
                          "generator_loss": g_loss})
