"""Implicit Q-Learning (Kostrikov et al., 2022) conditioned on a task latent z.

Shared by every method: networks read concat(s, z) (and a for Q). The latent arrives detached,
so IQL never shapes the task representation. Continuous actions use a Gaussian actor with a
tanh-bounded mean; discrete actions (one-hot in the data) use a categorical actor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, NamedTuple

import jax
import jax.numpy as jnp
import optax
import tyro
from flax.training.train_state import TrainState

from bati.cli_hints import DEFAULT_IN_DOC
from bati.nets import MLP, CriticState, DoubleCritic, GaussianHead, gaussian_log_prob

TABLE3_HIDDEN_DIMS = (256, 256)


@dataclass(frozen=True)
class IQLConfig:
    hidden_dims: Annotated[tuple[int, ...] | None, DEFAULT_IN_DOC] = None
    """Hidden sizes of the actor, critics and value net (default: Table 3's (256, 256); `bati train`
    fills in its scale's default: quick (128, 128))."""
    learning_rate: float = 3e-4
    discount: float = 0.99
    expectile: float = 0.8
    temperature: float = 0.05
    """Actor weights are exp(A / temperature) (Table 3's 0.05 is this divisor; the IQL paper writes
    exp(beta A) with an inverse temperature beta = 1 / temperature)."""
    max_exp_advantage: float = 100.0
    tau: float = 0.005
    """Polyak rate of the target critic."""
    discrete: tyro.conf.Suppress[bool] = False
    """Categorical actor over one-hot actions (set from the family: KuhnPoker; not a CLI option)."""


class IQLState(NamedTuple):
    actor: TrainState
    critic: CriticState
    value: TrainState


def expectile_loss(diff: jax.Array, expectile: float) -> jax.Array:
    """Asymmetric L2: |expectile - 1(diff < 0)| * diff^2, with diff = Q - V (IQL's expectile, often called tau;
    IQLConfig.tau is the Polyak rate of the target critic)."""
    weight = jnp.where(diff > 0, expectile, 1 - expectile)
    return weight * diff**2


def advantage_weights(advantage: jax.Array, temperature: float, max_weight: float) -> jax.Array:
    """AWR weights exp(A / temperature), clipped at `max_weight`."""
    return jnp.minimum(jnp.exp(advantage / temperature), max_weight)


def log_prob(actor: TrainState, params, obs_z: jax.Array, actions: jax.Array, discrete: bool) -> jax.Array:
    """log pi(a | s, z) of the actor `params`: categorical over one-hot actions, or a Gaussian around tanh(mean)."""
    if discrete:
        return jnp.sum(actions * jax.nn.log_softmax(actor.apply_fn(params, obs_z)), axis=-1)
    mean, log_std = actor.apply_fn(params, obs_z)
    return gaussian_log_prob(actions, jnp.tanh(mean), log_std)


def _target_q(state: IQLState, obs_z: jax.Array, actions: jax.Array) -> jax.Array:
    """min of the twin target critics at (s, z, a)."""
    return state.critic.apply_fn(state.critic.target_params, jnp.concatenate([obs_z, actions], -1)).min(0)


def value_loss(params, state: IQLState, batch: dict, z: jax.Array, config: IQLConfig):
    """Expectile regression of V(s, z) towards the target Q(s, a, z) (IQL's Eq. 5); aux: mean V."""
    obs_z = jnp.concatenate([batch["observations"], z], -1)
    v = state.value.apply_fn(params, obs_z)[..., 0]
    return expectile_loss(_target_q(state, obs_z, batch["actions"]) - v, config.expectile).mean(), v.mean()


def actor_loss(params, state: IQLState, batch: dict, z: jax.Array, config: IQLConfig):
    """Advantage-weighted log-likelihood of the dataset's actions (IQL's Eq. 7); aux: mean weight."""
    obs_z = jnp.concatenate([batch["observations"], z], -1)
    v = state.value.apply_fn(state.value.params, obs_z)[..., 0]
    weights = advantage_weights(_target_q(state, obs_z, batch["actions"]) - v, config.temperature,
                                config.max_exp_advantage)
    # Weighted log-likelihood of the DATASET actions (not of freshly sampled ones).
    log_p = log_prob(state.actor, params, obs_z, batch["actions"], config.discrete)
    return -(jax.lax.stop_gradient(weights) * log_p).mean(), weights.mean()


def critic_loss(params, state: IQLState, batch: dict, z: jax.Array, config: IQLConfig):
    """TD regression of both Q(s, a, z) towards r + discount * V(s', z) (IQL's Eq. 6); aux: mean Q."""
    next_v = state.value.apply_fn(state.value.params, jnp.concatenate([batch["next_observations"], z], -1))[..., 0]
    # Our families' episodes end only by the time limit, so every transition bootstraps; a user's own
    # data may mark terminal transitions (no value after them).
    if "terminals" in batch:
        next_v = (1.0 - batch["terminals"]) * next_v
    target = batch["rewards"] + config.discount * next_v
    q = state.critic.apply_fn(params, jnp.concatenate([batch["observations"], z, batch["actions"]], -1))
    return ((q - jax.lax.stop_gradient(target)) ** 2).mean(), q.mean()


def update(state: IQLState, batch: dict, z: jax.Array, config: IQLConfig) -> tuple[IQLState, dict]:
    """One IQL step on a flat batch: value, then actor and critic, then the target."""
    z = jax.lax.stop_gradient(z)
    (v_loss, v_mean), grads = jax.value_and_grad(value_loss, has_aux=True)(state.value.params, state, batch, z, config)
    state = state._replace(value=state.value.apply_gradients(grads=grads))

    (a_loss, w_mean), grads = jax.value_and_grad(actor_loss, has_aux=True)(state.actor.params, state, batch, z, config)
    actor = state.actor.apply_gradients(grads=grads)

    (c_loss, q_mean), grads = jax.value_and_grad(critic_loss, has_aux=True)(state.critic.params, state, batch, z,
                                                                             config)
    critic = state.critic.apply_gradients(grads=grads)
    critic = critic.replace(target_params=optax.incremental_update(critic.params, critic.target_params, config.tau))

    metrics = {"value_loss": v_loss, "actor_loss": a_loss, "critic_loss": c_loss, "q": q_mean, "v": v_mean,
               "adv_weight": w_mean}
    return IQLState(actor, critic, state.value), metrics


class IQL:
    """Networks and state for one data shape; the losses and `update` above are pure functions of the state.
    Batches are flat: (N, dim) arrays with z (N, d)."""

    def __init__(self, obs_dim: int, latent_dim: int, action_dim: int, config: IQLConfig = IQLConfig()):
        self.config = config
        self.obs_dim, self.latent_dim, self.action_dim = obs_dim, latent_dim, action_dim
        dims = tuple(config.hidden_dims or TABLE3_HIDDEN_DIMS)
        self.actor_net = MLP(dims, action_dim) if config.discrete else GaussianHead(dims, action_dim)
        self.critic_net = DoubleCritic(dims)
        self.value_net = MLP(dims, 1)
        self.optimizer = optax.adam(config.learning_rate)

    def init(self, key: jax.Array) -> IQLState:
        k_actor, k_critic, k_value = jax.random.split(key, 3)
        state_in = jnp.zeros((1, self.obs_dim + self.latent_dim))
        actor = self.actor_net.init(k_actor, state_in)
        critic = self.critic_net.init(k_critic, jnp.zeros((1, self.obs_dim + self.latent_dim + self.action_dim)))
        value = self.value_net.init(k_value, state_in)
        return IQLState(
            actor=TrainState.create(apply_fn=self.actor_net.apply, params=actor, tx=self.optimizer),
            critic=CriticState.create(apply_fn=self.critic_net.apply, params=critic, tx=self.optimizer,
                                      target_params=critic),
            value=TrainState.create(apply_fn=self.value_net.apply, params=value, tx=self.optimizer),
        )

    def act(self, actor, obs: jax.Array, z: jax.Array, key: jax.Array | None = None) -> jax.Array:
        """Greedy action (the Gaussian's mean / the categorical's mode, one-hot) or a sample with `key`;
        `actor`: the actor's params."""
        obs_z = jnp.concatenate([obs, z], axis=-1)
        if self.config.discrete:
            logits = self.actor_net.apply(actor, obs_z)
            index = jnp.argmax(logits, -1) if key is None else jax.random.categorical(key, logits)
            return jax.nn.one_hot(index, self.action_dim)
        mean, log_std = self.actor_net.apply(actor, obs_z)
        if key is None:
            return jnp.tanh(mean)
        return jnp.clip(jnp.tanh(mean) + jnp.exp(log_std) * jax.random.normal(key, mean.shape), -1.0, 1.0)

    def update(self, state: IQLState, batch: dict, z: jax.Array) -> tuple[IQLState, dict]:
        """`update` with this IQL's config."""
        return update(state, batch, z, self.config)
