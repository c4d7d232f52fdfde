"""No-context: IQL on the pooled data of all training tasks, with no task latent at all.

A control, not a method of the paper: when it comes close to the Oracle, the family does not
need task inference, and a table of that family cannot tell good inference from bad. Its latent
is empty (width 0), so its task-inference error is undefined (NaN in the results).
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from bati.methods.base import MethodSpec, TaskInference


class NoContext(TaskInference):
    infers_task = False

    def __init__(self, spec: MethodSpec, config=None):
        super().__init__(dataclasses.replace(spec, latent_dim=0), config)

    def init(self, key):
        return {}

    def loss(self, params, batch, key):
        return jnp.zeros(()), (jnp.zeros((batch["task_ids"].shape[0], 0)), {})

    def infer(self, params, context, key):
        return jnp.zeros((context["rewards"].shape[0], 0))
