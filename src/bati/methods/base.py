"""The interface every task-inference method implements.

A method owns its parameters (a pytree) and three pure functions:
- `loss(params, batch, key) -> (loss, (z, metrics))`: the representation loss on a training
  batch, and the latent z (task_batch, latent_dim) that IQL receives (detached) for it;
- `infer(params, context, key) -> z`: test time, from contexts alone (K, C, ...) -> (K, latent_dim).
The training step (bati.train) differentiates `loss`, updates the method and IQL together.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import jax


@dataclass(frozen=True)
class MethodSpec:
    """What a method needs to know about the data it is trained on."""

    obs_dim: int
    action_dim: int
    task_dim: int
    n_train_tasks: int
    latent_dim: int
    encoder_dims: tuple[int, ...]
    decoder_dims: tuple[int, ...]
    discrete_actions: bool = False


class TaskInference(Protocol):
    spec: MethodSpec
    needs_context: bool  # does `loss` read batch["context"] (training contexts)?

    def init(self, key: jax.Array) -> Any: ...

    def loss(self, params: Any, batch: dict, key: jax.Array) -> tuple[jax.Array, tuple[jax.Array, dict]]: ...

    def infer(self, params: Any, context: dict, key: jax.Array) -> jax.Array: ...
