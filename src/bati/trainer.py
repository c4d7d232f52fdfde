"""The training algorithm (Alg. 1): a task-inference method learned together with IQL.

One jitted step samples a batch of (tasks x transitions) on device, updates the method's representation
loss, and updates IQL on the latent the method produced, detached. Steps run in jitted chunks
(`lax.scan`); k seeds run as one program (`vmap`). No files, no run directories, no lookups by name: the
caller (bati.train) gives the resolved config, the data, the family and, for methods that imitate one
(DPT), the expert.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax.training.train_state import TrainState as ParamsState

from bati.config import TrainConfig
from bati.data import FamilyData, sample_batch, sample_contexts
from bati.data.batch import TRANSITION_FIELDS
from bati.methods import MethodSpec, make_method
from bati.rl.iql import IQL, IQLState

__all__ = ["TrainState", "Trainer"]


class TrainState(NamedTuple):
    """Everything a run learns: the method's parameters with their optimiser state, IQL's, the step."""

    method: ParamsState
    iql: IQLState
    step: jax.Array


class Trainer:
    """The method, IQL and the jitted chunk of training steps for one resolved config."""

    def __init__(self, config: TrainConfig, data: FamilyData, family, expert=None):
        """`family`: the task family the data came from (its record sets the latent and net sizes);
        `expert`: labels actions for methods that imitate one (DPT), required by them."""
        self.config, self.data, self.family = config, data, family
        record = family.record
        family_spec = MethodSpec(
            obs_dim=data.obs_dim, action_dim=data.action_dim, task_dim=data.task_dim,
            n_train_tasks=len(data.train_tasks), latent_dim=record.latent_dim,
            encoder_dims=record.net_dims, decoder_dims=record.net_dims, family=record,
            discrete_actions=config.iql.discrete,
        )
        self.method = make_method(config.method, family_spec, config.method_config())
        self.spec = self.method.spec  # a method may change the latent (Oracle: the task array; DPT: its width)
        self.iql = IQL(data.obs_dim, self.spec.latent_dim, data.action_dim, config.iql)
        self.optimizer = optax.adam(config.learning_rate)
        self.train_task_arrays = jnp.asarray(data.train_task_arrays, jnp.float32)
        if self.method.needs_expert_actions and expert is None:
            raise ValueError(f"method {config.method!r} imitates an expert: give the family's expert")
        self.expert = expert
        self.run_chunk = jax.jit(self._run_chunk, static_argnames="length")
        # k seeds in one program: states and keys stacked on a leading axis, the data shared.
        self.run_chunks = jax.jit(self._run_chunks, static_argnames="length")

    def init(self, key: jax.Array) -> TrainState:
        k_method, k_iql = jax.random.split(key)
        method = ParamsState.create(apply_fn=None, params=self.method.init(k_method), tx=self.optimizer)
        return TrainState(method, self.iql.init(k_iql), jnp.zeros((), jnp.int32))

    def make_batch(self, data, k_batch: jax.Array, k_context: jax.Array) -> dict:
        """A training batch of `data` with what the method's flags ask for (contexts, expert labels)."""
        c = self.config
        batch = sample_batch(data, k_batch, c.task_batch, c.batch_size)
        batch["task_arrays"] = self.train_task_arrays[batch["task_ids"]]
        if self.method.needs_context:
            batch["context"] = sample_contexts(data, k_context, batch["task_ids"], c.context_length)
        if self.method.needs_positive_context:
            batch["positive_context"] = sample_contexts(data, jax.random.fold_in(k_context, 1), batch["task_ids"],
                                                        c.context_length)
        if self.method.needs_expert_actions:
            batch["expert_actions"] = self.expert.task_mean_actions(batch["observations"], batch["task_arrays"])
        return batch

    def step(self, state: TrainState, key: jax.Array, data) -> tuple[TrainState, dict]:
        """One training step: the method's representation loss, then IQL on the detached latent."""
        k_batch, k_context, k_loss = jax.random.split(key, 3)
        batch = self.make_batch(data, k_batch, k_context)

        (rep_loss, (z, rep_metrics)), grads = jax.value_and_grad(self.method.loss, has_aux=True)(
            state.method.params, batch, k_loss)
        method = state.method.apply_gradients(grads=grads)

        if self.method.acts_itself:  # e.g. DPT: no IQL policy to train
            iql, iql_metrics = state.iql, {}
        else:
            flat = {k: batch[k].reshape((-1,) + batch[k].shape[2:]) for k in TRANSITION_FIELDS + ("terminals",)
                    if k in batch}
            z_flat = jnp.repeat(jax.lax.stop_gradient(z), self.config.batch_size, axis=0)
            iql, iql_metrics = self.iql.update(state.iql, flat, z_flat)

        metrics = {"representation_loss": rep_loss, **rep_metrics, **iql_metrics}
        if z.shape[-1]:  # how far apart the batch tasks' latents are: ~0 when task inference collapsed
            metrics["latent_spread"] = jnp.std(jax.lax.stop_gradient(z), axis=0).mean()
        return TrainState(method, iql, state.step + 1), metrics

    def _run_chunk(self, state: TrainState, base_key: jax.Array, data, length: int):
        """`length` steps; step t uses fold_in(base_key, t), so resuming replays the same keys."""

        def body(state, _):
            return self.step(state, jax.random.fold_in(base_key, state.step), data)

        state, metrics = jax.lax.scan(body, state, None, length=length)
        return state, jax.tree_util.tree_map(jnp.mean, metrics)

    def _run_chunks(self, states: TrainState, base_keys: jax.Array, data, length: int):
        """`_run_chunk` for k runs (seeds) at once: states and keys stacked on axis 0, data shared. One run
        (k = 1) is the unvmapped program on its state: exactly the numbers of `run_chunk`."""
        if base_keys.shape[0] == 1:
            state, metrics = self._run_chunk(jax.tree_util.tree_map(lambda x: x[0], states), base_keys[0], data, length)
            return jax.tree_util.tree_map(lambda x: x[None], (state, metrics))
        return jax.vmap(lambda state, key: self._run_chunk(state, key, data, length))(states, base_keys)
