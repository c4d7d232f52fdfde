"""IQL: expectile and AWR losses against hand computations, updates on toy data, discrete actions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.nets import gaussian_log_prob
from bati.rl.iql import IQL, IQLConfig, actor_loss, advantage_weights, critic_loss, expectile_loss


def test_expectile_loss_matches_hand_computation():
    diff = jnp.array([2.0, -1.0, 0.5, -3.0])
    # tau = 0.8: positive residuals weigh 0.8, negative 0.2
    expected = np.array([0.8 * 4.0, 0.2 * 1.0, 0.8 * 0.25, 0.2 * 9.0])
    np.testing.assert_allclose(expectile_loss(diff, 0.8), expected, rtol=1e-6)


def test_advantage_weights_divide_by_beta_and_clip():
    adv = jnp.array([0.0, 0.05, -0.1, 1.0])
    w = advantage_weights(adv, temperature=0.05, max_weight=100.0)
    # exp(A / 0.05): 1, e, e^-2, and exp(20) clipped to 100
    np.testing.assert_allclose(w, [1.0, np.e, np.exp(-2.0), 100.0], rtol=1e-6)


def _toy_batch(n=64, obs_dim=3, action_dim=2, latent_dim=2, seed=0):
    rng = np.random.default_rng(seed)
    batch = {
        "observations": rng.normal(size=(n, obs_dim)).astype(np.float32),
        "actions": rng.uniform(-0.9, 0.9, size=(n, action_dim)).astype(np.float32),
        "rewards": rng.normal(size=n).astype(np.float32),
        "next_observations": rng.normal(size=(n, obs_dim)).astype(np.float32),
    }
    z = rng.normal(size=(n, latent_dim)).astype(np.float32)
    return jax.tree_util.tree_map(jnp.asarray, batch), jnp.asarray(z)


def test_actor_loss_is_weighted_log_likelihood_of_dataset_actions():
    iql = IQL(3, 2, 2, IQLConfig(hidden_dims=(16,)))
    state = iql.init(jax.random.PRNGKey(0))
    batch, z = _toy_batch()
    loss, _ = actor_loss(state.actor.params, state, batch, z, iql.config)
    obs_z = jnp.concatenate([batch["observations"], z], -1)
    sa = jnp.concatenate([obs_z, batch["actions"]], -1)
    q = iql.critic_net.apply(state.critic.target_params, sa).min(0)
    v = iql.value_net.apply(state.value.params, obs_z)[:, 0]
    mean, log_std = iql.actor_net.apply(state.actor.params, obs_z)
    by_hand = -np.mean(
        np.minimum(np.exp((q - v) / 0.05), 100.0) * gaussian_log_prob(batch["actions"], jnp.tanh(mean), log_std)
    )
    np.testing.assert_allclose(loss, by_hand, rtol=1e-5)


def test_critic_target_uses_value_of_next_state():
    iql = IQL(3, 2, 2, IQLConfig(hidden_dims=(16,), discount=0.9))
    state = iql.init(jax.random.PRNGKey(1))
    batch, z = _toy_batch()
    loss, _ = critic_loss(state.critic.params, state, batch, z, iql.config)
    next_v = iql.value_net.apply(state.value.params, jnp.concatenate([batch["next_observations"], z], -1))[:, 0]
    target = batch["rewards"] + 0.9 * next_v
    q = iql.critic_net.apply(state.critic.params, jnp.concatenate([batch["observations"], z, batch["actions"]], -1))
    np.testing.assert_allclose(loss, np.mean((q - target) ** 2), rtol=1e-5)


@pytest.mark.parametrize("discrete", [False, True])
def test_updates_reduce_losses_on_a_fixed_batch(discrete):
    action_dim = 3
    iql = IQL(3, 2, action_dim, IQLConfig(hidden_dims=(32, 32), discrete=discrete, learning_rate=1e-3))
    state = iql.init(jax.random.PRNGKey(2))
    batch, z = _toy_batch(action_dim=action_dim)
    if discrete:
        batch["actions"] = jax.nn.one_hot(jnp.arange(64) % action_dim, action_dim)
    update = jax.jit(iql.update)
    _, first = update(state, batch, z)
    for _ in range(200):
        state, metrics = update(state, batch, z)
    assert metrics["critic_loss"] < first["critic_loss"]
    assert metrics["value_loss"] < first["value_loss"]
    action = iql.act(state.actor.params, batch["observations"][:4], z[:4])
    assert action.shape == (4, action_dim)
    if discrete:
        np.testing.assert_allclose(action.sum(-1), 1.0)
    else:
        assert np.all(np.abs(action) <= 1.0)


def test_latent_gradients_do_not_flow_through_iql():
    iql = IQL(3, 2, 2, IQLConfig(hidden_dims=(16,)))
    state = iql.init(jax.random.PRNGKey(3))
    batch, z = _toy_batch()

    def total_loss(z):
        new_state, metrics = iql.update(state, batch, z)
        return metrics["critic_loss"] + metrics["actor_loss"] + metrics["value_loss"]

    np.testing.assert_array_equal(jax.grad(total_loss)(z), 0.0)


def test_a_checkpoint_saved_before_train_states_loads_into_them():
    import flax

    from bati.checkpoints import upgrade_iql_state

    iql = IQL(3, 2, 2, IQLConfig(hidden_dims=(8,)))
    state, _ = iql.update(iql.init(jax.random.PRNGKey(0)), *_toy_batch())
    new = flax.serialization.to_state_dict(state)
    old = {"actor": new["actor"]["params"], "critic": new["critic"]["params"],
           "target_critic": new["critic"]["target_params"], "value": new["value"]["params"],
           "actor_opt": new["actor"]["opt_state"], "critic_opt": new["critic"]["opt_state"],
           "value_opt": new["value"]["opt_state"]}  # the layout of IQLState before flax TrainStates
    restored = flax.serialization.from_state_dict(iql.init(jax.random.PRNGKey(1)), upgrade_iql_state(old, 1))
    jax.tree_util.tree_map(np.testing.assert_array_equal, restored, state)
    assert upgrade_iql_state(new, 1) is new  # today's layout passes through
