"""Task-conditioned SAC: one expert per family, conditioned on the task's parameters.

The paper trains one SAC per training task; we train one policy pi(a | s, task) on tasks drawn
from the whole task space with eps = 0 (App. C.2), so "the expert for task M" is this policy
conditioned on M. Actor and critics read concat(obs, task_to_array(task)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import flax
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

from bati.checks import check_hidden_dims, check_integer, check_number
from bati.nets import CriticState, DoubleCritic, GaussianHead


@dataclass(frozen=True)
class SACConfig:
    hidden_dims: tuple[int, ...] = (256, 256)
    learning_rate: float = 3e-4
    discount: float = 0.99
    tau: float = 0.005
    batch_size: int = 256
    init_temperature: float = 1.0

    def check(self) -> None:
        """ValueError (one line naming the setting, as `--sac.NAME`) for a value SAC cannot train with."""
        check_hidden_dims("sac.hidden_dims", self.hidden_dims)
        check_integer("sac.batch_size", self.batch_size)
        for name in ("learning_rate", "init_temperature"):
            check_number(f"sac.{name}", getattr(self, name))
        for name in ("discount", "tau"):
            check_number(f"sac.{name}", getattr(self, name), at_most=1.0)


class SACState(NamedTuple):
    actor: TrainState
    critic: CriticState
    alpha: TrainState
    """params: {"log_alpha": the entropy temperature's log} (a dict: TrainState needs a pytree of params)."""


def upgrade_checkpoint(raw: dict) -> dict:
    """A SACState's state dict saved before SAC used flax TrainStates (separate actor_opt, critic_opt,
    alpha_opt, target_critic and log_alpha entries), in today's layout (counters 0: nothing reads them).
    A dict already in today's layout is returned as it is."""
    if "actor_opt" not in raw:
        return raw
    return {"actor": {"step": 0, "params": raw["actor"], "opt_state": raw["actor_opt"]},
            "critic": {"step": 0, "params": raw["critic"], "target_params": raw["target_critic"],
                       "opt_state": raw["critic_opt"]},
            "alpha": {"step": 0, "params": {"log_alpha": raw["log_alpha"]}, "opt_state": _wrap_moments(raw["alpha_opt"])}}


def _wrap_moments(opt_state: dict) -> dict:
    """Adam's state of a bare scalar as the state of {"log_alpha": scalar} (its moments move into the dict)."""
    return {k: {**v, **{m: {"log_alpha": v[m]} for m in ("mu", "nu") if m in v}} if isinstance(v, dict) else v
            for k, v in opt_state.items()}


class SAC:
    """The networks, losses and jitted update of a task-conditioned SAC."""

    def __init__(self, obs_dim: int, task_dim: int, action_dim: int, config: SACConfig = SACConfig()):
        self.config = config
        self.obs_dim, self.task_dim, self.action_dim = obs_dim, task_dim, action_dim
        self.actor_net = GaussianHead(config.hidden_dims, action_dim)
        self.critic_net = DoubleCritic(config.hidden_dims)
        self.optimizer = optax.adam(config.learning_rate)
        self.target_entropy = -float(action_dim)
        self.update_many = jax.jit(self._update_many)
        self.act = jax.jit(self._act, static_argnames="deterministic")

    def init(self, key: jax.Array) -> SACState:
        k_actor, k_critic = jax.random.split(key)
        inputs = jnp.zeros((1, self.obs_dim + self.task_dim))
        actor = self.actor_net.init(k_actor, inputs)
        critic = self.critic_net.init(k_critic, jnp.zeros((1, self.obs_dim + self.task_dim + self.action_dim)))
        log_alpha = jnp.log(jnp.asarray(self.config.init_temperature, jnp.float32))
        return SACState(
            actor=TrainState.create(apply_fn=self.actor_net.apply, params=actor, tx=self.optimizer),
            critic=CriticState.create(apply_fn=self.critic_net.apply, params=critic, tx=self.optimizer,
                                      target_params=critic),
            alpha=TrainState.create(apply_fn=None, params={"log_alpha": log_alpha}, tx=self.optimizer),
        )

    # --- policy ---------------------------------------------------------------------------
    def _sample_action(self, actor, inputs, key):
        mean, log_std = self.actor_net.apply(actor, inputs)
        noise = jax.random.normal(key, mean.shape)
        pre_tanh = mean + jnp.exp(log_std) * noise
        action = jnp.tanh(pre_tanh)
        log_prob = jnp.sum(
            -0.5 * noise**2 - log_std - 0.5 * jnp.log(2 * jnp.pi) - jnp.log(1 - action**2 + 1e-6), axis=-1
        )
        return action, log_prob

    def _act(self, actor, obs, task, key, deterministic: bool):
        inputs = jnp.concatenate([obs, task], axis=-1)
        if deterministic:
            return jnp.tanh(self.actor_net.apply(actor, inputs)[0])
        return self._sample_action(actor, inputs, key)[0]

    # --- losses ---------------------------------------------------------------------------
    def critic_loss(self, critic, state: SACState, batch, key):
        next_inputs = jnp.concatenate([batch["next_observations"], batch["tasks"]], -1)
        next_action, next_log_prob = self._sample_action(state.actor.params, next_inputs, key)
        next_q = self.critic_net.apply(state.critic.target_params, jnp.concatenate([next_inputs, next_action], -1))
        next_v = next_q.min(0) - jnp.exp(state.alpha.params["log_alpha"]) * next_log_prob
        # Episodes only end by the time limit, so every transition bootstraps.
        target = batch["rewards"] + self.config.discount * next_v
        inputs = jnp.concatenate([batch["observations"], batch["tasks"], batch["actions"]], -1)
        q = self.critic_net.apply(critic, inputs)
        return jnp.mean((q - jax.lax.stop_gradient(target)) ** 2), q.mean()

    def actor_loss(self, actor, state: SACState, batch, key):
        inputs = jnp.concatenate([batch["observations"], batch["tasks"]], -1)
        action, log_prob = self._sample_action(actor, inputs, key)
        q = self.critic_net.apply(state.critic.params, jnp.concatenate([inputs, action], -1)).min(0)
        return jnp.mean(jnp.exp(state.alpha.params["log_alpha"]) * log_prob - q), log_prob.mean()

    # --- update ---------------------------------------------------------------------------
    def _update(self, state: SACState, batch, key):
        k_critic, k_actor = jax.random.split(key)
        (c_loss, q_mean), c_grads = jax.value_and_grad(self.critic_loss, has_aux=True)(
            state.critic.params, state, batch, k_critic
        )
        state = state._replace(critic=state.critic.apply_gradients(grads=c_grads))

        (a_loss, log_prob), a_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor.params, state, batch, k_actor
        )
        actor = state.actor.apply_gradients(grads=a_grads)

        # Temperature: raise alpha when the entropy (-log_prob) is below the target.
        alpha_grad = jax.grad(lambda p: -p["log_alpha"] * jax.lax.stop_gradient(log_prob + self.target_entropy))(
            state.alpha.params
        )
        alpha = state.alpha.apply_gradients(grads=alpha_grad)

        critic = state.critic.replace(target_params=optax.incremental_update(
            state.critic.params, state.critic.target_params, self.config.tau))
        metrics = {
            "critic_loss": c_loss,
            "actor_loss": a_loss,
            "q": q_mean,
            "entropy": -log_prob,
            "alpha": jnp.exp(alpha.params["log_alpha"]),
        }
        return SACState(actor, critic, alpha), metrics

    def _update_many(self, state: SACState, batches, key):
        """Apply one update per leading-axis slice of `batches` (a scan: one dispatch)."""
        keys = jax.random.split(key, jax.tree_util.tree_leaves(batches)[0].shape[0])
        state, metrics = jax.lax.scan(lambda s, xs: self._update(s, *xs), state, (batches, keys))
        return state, jax.tree_util.tree_map(jnp.mean, metrics)


def state_to_bytes(state: SACState) -> bytes:
    return flax.serialization.to_bytes(state)


def state_from_bytes(template: SACState, data: bytes) -> SACState:
    """A saved SACState (an older layout is upgraded first)."""
    raw = flax.serialization.msgpack_restore(data)
    return flax.serialization.from_state_dict(template, upgrade_checkpoint(raw))


RESUME_IDENTITY = ("family", "seed", "num_envs", "updates_per_step", "start_steps", "sac")
"""What a resumed expert training run (conditioned or per task) must share with the run in its directory
(total_steps may grow)."""


def generator_from_state(state: dict) -> np.random.Generator:
    """A numpy Generator continuing from a saved `bit_generator.state` (a SAC trainer's checkpoint holds it)."""
    rng = np.random.default_rng()
    rng.bit_generator.state = state
    return rng
