"""BATI and Recon: Eq. 7 against hand computation, Eq. 8 inference, learning on a toy family."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bati.methods import MethodSpec, make_method
from bati.methods.bati import BATI
from bati.methods.dynamics import reconstruction_nll, transition_targets

SPEC = MethodSpec(obs_dim=2, action_dim=1, task_dim=1, n_train_tasks=4, latent_dim=3,
                  encoder_dims=(32, 32), decoder_dims=(32, 32))
THETAS = np.array([-2.0, -0.7, 0.7, 2.0])  # reward slope of each toy task


def toy_transitions(task_ids, n, seed, noise=0.3):
    """Toy family: r = theta_task + 0.5 a + N(0, noise^2), s' = s + 0.1 a + N(0, 0.05^2). Shapes (T, n, .)."""
    rng = np.random.default_rng(seed)
    task_ids = np.asarray(task_ids)
    obs = rng.normal(size=(len(task_ids), n, 2)).astype(np.float32)
    actions = rng.uniform(-1, 1, size=(len(task_ids), n, 1)).astype(np.float32)
    rewards = THETAS[task_ids][:, None] + 0.5 * actions[..., 0] + noise * rng.normal(size=(len(task_ids), n))
    return {"observations": jnp.asarray(obs), "actions": jnp.asarray(actions),
            "rewards": jnp.asarray(rewards, jnp.float32), "next_observations": jnp.asarray(obs + 0.1 * actions + 0.05 * rng.normal(size=obs.shape), jnp.float32)}


def test_reconstruction_nll_matches_hand_computation():
    mean = jnp.array([[1.0, 0.0]])
    log_var = jnp.array([[0.0, np.log(4.0)]])
    target = jnp.array([[3.0, 1.0]])
    # (3-1)^2/1 + 0 + (1-0)^2/4 + log 4
    np.testing.assert_allclose(reconstruction_nll(mean, log_var, target), [4.0 + 0.25 + np.log(4.0)], rtol=1e-6)


def test_transition_targets_are_reward_and_state_change():
    t = {"observations": jnp.array([[1.0, 2.0]]), "next_observations": jnp.array([[1.5, 1.0]]),
         "rewards": jnp.array([0.3])}
    np.testing.assert_allclose(transition_targets(t), [[0.3, 0.5, -1.0]], rtol=1e-6)


class KnownDynamics:
    """The toy family's true model: mean reward z[0] + 0.5 a, mean state change 0.1 a."""

    def apply(self, params, obs, actions, z):
        mean = jnp.concatenate([z[..., :1] + 0.5 * actions, 0.1 * jnp.broadcast_to(actions, obs.shape)], -1)
        return mean, jnp.log(jnp.full(mean.shape, 0.09))


def test_bati_infer_picks_the_table_entry_of_the_true_task():
    method = BATI(SPEC)
    method.model = KnownDynamics()
    table = jnp.zeros((4, 3)).at[:, 0].set(jnp.asarray(THETAS, jnp.float32))
    params = {"table": table, "dynamics": None}
    context = toy_transitions([3, 0, 2, 1], n=50, seed=1)
    z = method.infer(params, context, jax.random.PRNGKey(0))
    nearest = np.argmin(np.abs(np.asarray(z)[:, :1] - THETAS[None, :]), axis=1)
    np.testing.assert_array_equal(nearest, [3, 0, 2, 1])
    # Eq. 8 returns one of the sampled latents: within a few std of its table entry.
    assert np.all(np.abs(np.asarray(z)[:, 0] - THETAS[[3, 0, 2, 1]]) < 4 * float(method.std))


def _fit(method, steps=300, seed=0):
    params = method.init(jax.random.PRNGKey(seed))
    optimizer = optax.adam(3e-3)
    opt_state = optimizer.init(params)

    @jax.jit
    def step(params, opt_state, batch, key):
        (loss, _), grads = jax.value_and_grad(method.loss, has_aux=True)(params, batch, key)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(params, updates), opt_state, loss

    losses = []
    for i in range(steps):
        batch = toy_transitions(np.arange(4), n=64, seed=100 + i)
        batch["task_ids"] = jnp.arange(4)
        batch["context"] = toy_transitions(np.arange(4), n=32, seed=10_000 + i)
        params, opt_state, loss = step(params, opt_state, batch, jax.random.PRNGKey(i))
        losses.append(float(loss))
    return params, losses


@pytest.mark.parametrize("name", ["bati", "recon"])
def test_reconstruction_loss_goes_down_and_inference_finds_the_task(name):
    method = make_method(name, SPEC)
    params, losses = _fit(method)
    assert np.mean(losses[-20:]) < np.mean(losses[:20]) - 1.0
    # Reference latents from each task's own contexts; inferred latents of fresh contexts must be nearest
    # to their own task's reference.
    reference = method.infer(params, toy_transitions(np.arange(4), n=100, seed=5), jax.random.PRNGKey(1))
    z = method.infer(params, toy_transitions(np.arange(4), n=100, seed=6), jax.random.PRNGKey(2))
    nearest = np.argmin(((np.asarray(z)[:, None] - np.asarray(reference)[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_array_equal(nearest, np.arange(4))


def test_bati_train_latent_is_a_sample_of_the_batch_task_entry():
    method = BATI(SPEC)
    params = method.init(jax.random.PRNGKey(0))
    ids = jnp.array([2, 2, 0])
    z = method.sample_task_latents(params, ids, jax.random.PRNGKey(3))
    assert z.shape == (3, SPEC.latent_dim)
    np.testing.assert_array_less(np.abs(z - params["table"][ids]), 5 * float(method.std))
    assert not np.allclose(z[0], z[1])  # two samples of the same entry differ


def test_unknown_method_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        make_method("nope", SPEC)


def test_reward_only_inference_ignores_the_state_terms():
    from bati.methods.dynamics import context_nll

    class Model:
        def apply(self, params, obs, actions, z):
            mean = jnp.concatenate([z[..., :1], jnp.zeros_like(obs)], -1)
            return mean, jnp.zeros_like(mean)

    context = {"observations": jnp.zeros((2, 2)), "next_observations": jnp.full((2, 2), 3.0),
               "rewards": jnp.array([1.0, 2.0]), "actions": jnp.zeros((2, 1))}
    z = jnp.array([0.5, 0.0, 0.0])
    # reward term: ((1 - 0.5)^2 + (2 - 0.5)^2) / 2; each state dim adds 3^2
    np.testing.assert_allclose(context_nll(Model(), None, context, z, reward_only=True), (0.25 + 2.25) / 2)
    np.testing.assert_allclose(context_nll(Model(), None, context, z), (0.25 + 2.25) / 2 + 18.0)
    assert make_method("bati-r", SPEC).reward_only_inference and not make_method("bati", SPEC).reward_only_inference
