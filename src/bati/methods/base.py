"""The interface every task-inference method implements.

A method owns its parameters (a pytree) and three pure functions:
- `init(key) -> params`;
- `loss(params, batch, key) -> (loss, (z, metrics))`: the representation loss on a training
  batch, and the latent z (task_batch, latent_dim) that IQL receives (detached) for it;
- `infer(params, context, key) -> z`: test time, from contexts alone (K, C, ...) -> (K, latent_dim).
The training step (bati.trainer) differentiates `loss`, updates the method and IQL together.

A training batch holds, per task of the batch (T tasks x B transitions): task_ids (T,),
task_arrays (T, task_dim), observations, actions, rewards, next_observations (T, B, ...), and on
request (the flags below) context (T, C, ...), positive_context (another context of the same
tasks) and expert_actions (T, B, action_dim). Contexts given to `infer` also hold task_arrays
(the true tasks; only the Oracle may read them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import jax

from bati.envs.base import FamilyRecord


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
    family: FamilyRecord | None = None
    """The task family's record, for per-family settings of Table 3 (None: the record's defaults)."""


class TaskInference:
    """Base class: the flags tell the training step what to put into the batch.

    A method with hyperparameters declares them as a frozen dataclass `Config` (every field with a
    typed default) and, if some values are bad, `check(section)` raising a one-line ValueError that names
    `section.<setting>`; `config_key` names the TrainConfig field that holds it (`bati train --csro.club-weight
    2.5`), shared by variants of one method (bati, bati-r and bati-auto all read `bati`). TrainConfig has one
    such field per section of the methods in `bati.methods.METHODS`.
    """

    Config: ClassVar[type | None] = None
    config_key: ClassVar[str | None] = None
    config_help: ClassVar[str | None] = None
    """The help of the section's options in `bati train --help` (None: the Config's docstring)."""
    trains_as: ClassVar[str | None] = None
    """The method whose training this one's is, step for step (same init, loss and keys: bati-r and
    bati-auto train exactly as bati and differ only at test time). A sweep then trains one run of them and
    evaluates the others in it as test-time rules (`bati.train.train_seeds(..., rules=...)`); None: its own
    training."""

    needs_context: bool = False
    """`loss` reads batch["context"]: a context of each batch task, from its training data."""
    needs_positive_context: bool = False
    """`loss` also reads batch["positive_context"]: a second, independent context of each task."""
    needs_expert_actions: bool = False
    """`loss` reads batch["expert_actions"]: the true task's expert's action at each observation."""
    infers_task: bool = True
    """The latent says which task it is (False for the `no-context` control: its error is undefined)."""
    acts_itself: bool = False
    """The method is its own policy (`act(params, obs, z)`); IQL is not trained for it."""
    calibrates: bool = False
    """Before inference the evaluator calls `calibrate(params, contexts, distances) -> (params, diagnostics)`
    with one off-policy context per training task (another task's expert collected it) and the
    training tasks' distance matrix; `infer` then receives the returned params (BATI-auto)."""

    def __init__(self, spec: MethodSpec, config: Any = None):
        self.spec = spec
        if self.Config is not None:
            config = self.Config() if config is None else config
            config = config.for_family(spec.family) if hasattr(config, "for_family") else config
        self.config = config

    def init(self, key: jax.Array) -> Any:
        raise NotImplementedError

    def loss(self, params: Any, batch: dict, key: jax.Array) -> tuple[jax.Array, tuple[jax.Array, dict]]:
        raise NotImplementedError

    def infer(self, params: Any, context: dict, key: jax.Array) -> jax.Array:
        raise NotImplementedError
