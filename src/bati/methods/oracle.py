"""Oracle: IQL conditioned on the true task parameters instead of an inferred latent.

An upper reference for the learned policies (the experts' own return is a different row, the
paper's "Oracle (Pre-IQL)"). The latent is `task_to_array(task)` of the batch's or the
context's task, so the context itself is ignored and the context shift cannot hurt it.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from bati.methods.base import MethodSpec, TaskInference


class Oracle(TaskInference):
    def __init__(self, spec: MethodSpec, config=None):
        super().__init__(dataclasses.replace(spec, latent_dim=spec.task_dim), config)

    def init(self, key):
        return {}

    def loss(self, params, batch, key):
        return jnp.zeros(()), (batch["task_arrays"], {})

    def infer(self, params, context, key):
        return context["task_arrays"]
