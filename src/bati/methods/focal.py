"""FOCAL (Li et al., 2021): a context encoder trained by distance metric learning.

Latents of two contexts of the same task are pulled together (squared distance); latents of
different tasks are pushed apart by an inverse-square term beta / (||z_i - z_j||^2 + eps). Each
training batch holds two independent contexts of each of its 16 tasks (Table 3's task
contrastive batch size), so every task has one positive pair and 2 x 2 x 15 negatives.

`distance` picks how a pair's distance enters: "squared" (default) as above, with the squared distance
summed over the latent's d dimensions; "root-mean", the form of the FOCAL / CSRO / ER-TRL code lineage,
with m = mean over dimensions of (z_i - z_j)^2: pull sqrt(m + 1e-3), push beta / (m + eps). The second
pulls less hard near coincidence and pushes d times further out (docs/methods.md, "FOCAL").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import jax
import jax.numpy as jnp

from bati.checks import check_number
from bati.methods.base import MethodSpec, TaskInference
from bati.methods.encoder import ContextEncoder, dummy_context

@dataclass(frozen=True)
class FOCALConfig:
    """FOCAL's distance metric loss (also UNICORN's and CSRO's FOCAL term)."""

    push_weight: float = 1.0
    """beta: weight of the inverse-square push between latents of different tasks."""
    push_epsilon: float = 0.1
    """eps: bounds the push at beta / eps when two latents coincide."""
    distance: Literal["squared", "root-mean"] = "squared"
    """How a pair's distance enters: squared and summed over dimensions (ours), or the code lineage's
    root-mean-square pull and mean-square push (module docstring)."""
    latent_activation: Literal["none", "tanh"] = "none"
    """The context encoder's output per transition: "tanh" bounds it in [-1, 1] before the mean (the FOCAL /
    CSRO / ER-TRL code lineage's encoder); "none", unbounded (ours for FOCAL, UNICORN and CSRO: docs/methods.md)."""
    same_task: Literal["index", "value"] = "index"
    """Which contexts the metric loss counts as one task: those of the same training task ("index", FOCAL's), or
    of training tasks with equal parameters ("value": HalfCheetahDir's 20 training tasks are two directions, and
    "index" pushes apart the latents of same-direction tasks, which only their collectors tell apart)."""

    def check(self, section: str = "focal") -> None:
        """ValueError naming `section`.<setting> (the TrainConfig field holding these settings) for a bad value."""
        if self.distance not in DISTANCES:
            raise ValueError(f"{section}.distance must be one of {', '.join(DISTANCES)}, got {self.distance!r}")
        if self.same_task not in SAME_TASK:
            raise ValueError(f"{section}.same_task must be one of {', '.join(SAME_TASK)}, got {self.same_task!r}")
        if self.latent_activation not in LATENT_ACTIVATIONS:
            raise ValueError(f"{section}.latent_activation must be one of {', '.join(LATENT_ACTIVATIONS)}, "
                             f"got {self.latent_activation!r}")
        check_number(f"{section}.push_weight", self.push_weight, positive=False)
        check_number(f"{section}.push_epsilon", self.push_epsilon)  # the push divides by distance + epsilon
        for name in ("focal_weight", "club_weight", "entropy_weight"):  # the subclasses' weights (None: the family's)
            if getattr(self, name, None) is not None:
                check_number(f"{section}.{name}", getattr(self, name), positive=False)


DISTANCES = ("squared", "root-mean")
LATENT_ACTIVATIONS = ("none", "tanh")
SAME_TASK = ("index", "value")
PULL_EPSILON = 1e-3
"""Keeps the root-mean pull's gradient finite at coincidence (the code lineage's value)."""


def metric_loss(z: jax.Array, labels: jax.Array, beta: float = FOCALConfig.push_weight,
                eps: float = FOCALConfig.push_epsilon, distance: str = FOCALConfig.distance) -> jax.Array:
    """FOCAL's distance metric loss over all pairs i < j of latents z (N, d) with task labels (N,).

    Mean pull over same-task pairs plus mean inverse-square push over the other pairs; `distance` as in
    the module docstring.
    """
    sq_diff = (z[:, None, :] - z[None, :, :]) ** 2
    if distance == "squared":
        sq_dist = jnp.sum(sq_diff, axis=-1)
        pull_dist = sq_dist
    else:  # root-mean
        sq_dist = jnp.mean(sq_diff, axis=-1)
        pull_dist = jnp.sqrt(sq_dist + PULL_EPSILON)
    pairs = jnp.triu(jnp.ones_like(sq_dist, dtype=bool), k=1)
    same = (labels[:, None] == labels[None, :]) & pairs
    different = ~(labels[:, None] == labels[None, :]) & pairs
    pull = jnp.sum(jnp.where(same, pull_dist, 0.0)) / jnp.maximum(same.sum(), 1)
    push = jnp.sum(jnp.where(different, beta / (sq_dist + eps), 0.0)) / jnp.maximum(different.sum(), 1)
    return pull + push


def task_labels(batch: dict) -> jax.Array:
    """One label per batch task that tasks with equal parameters share: the batch position of the first of them."""
    tasks = batch["task_arrays"]
    equal = jnp.all(tasks[:, None, :] == tasks[None, :, :], axis=-1)
    return jnp.argmax(equal, axis=1)


class FOCAL(TaskInference):
    Config = FOCALConfig
    config_key = "focal"
    needs_context = True
    needs_positive_context = True

    def __init__(self, spec: MethodSpec, config=None):
        super().__init__(spec, config)
        self.encoder = ContextEncoder(spec.encoder_dims, spec.latent_dim, self.config.latent_activation)

    def init(self, key):
        return {"encoder": self.encoder.init(key, dummy_context(self.spec))}

    def contrastive_loss(self, params, batch):
        """The metric loss on both contexts of every batch task; also returns the first context's z."""
        z = self.encoder.apply(params["encoder"], batch["context"])
        return self.pair_loss(params, batch, z), z

    def pair_loss(self, params, batch, z):
        """The metric loss of the first contexts' latents z and the positive contexts' latents."""
        z_positive = self.encoder.apply(params["encoder"], batch["positive_context"])
        labels = task_labels(batch) if self.config.same_task == "value" else batch["task_ids"]
        labels = jnp.concatenate([labels, labels])
        return metric_loss(jnp.concatenate([z, z_positive]), labels, self.config.push_weight,
                           self.config.push_epsilon, self.config.distance)

    def loss(self, params, batch, key):
        loss, z = self.contrastive_loss(params, batch)
        return loss, (z, {"metric_loss": loss})

    def infer(self, params, context, key):
        return self.encoder.apply(params["encoder"], context)
