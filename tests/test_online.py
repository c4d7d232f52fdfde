"""Self-collected context (`bati.online`): on PointGoal without noise, where the right answers are known."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.envs import get_family
from bati.envs.rollout import rollout
from bati.evaluate import Evaluator
from bati.online import OnlineError, SelfCollector, reinference_steps, window_indices
from bati.report.probes import Probe, ProbeError

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("online")

STEP = 0.1  # PointGoal's position change per step at full action
LENGTH = 40  # episode length of these tests (the env's limit is 200)
RUNS = 2


class ExactTask:
    """Infers the true task exactly (the Oracle's channel): after the first re-inference z is right."""

    acts_itself = calibrates = False

    def infer(self, params, context, key):
        return context["task_arrays"]


class MeanReward:
    """z = the context's mean reward; a table of two entries for the prior (a likelihood method's shape)."""

    acts_itself = calibrates = False

    def infer(self, params, context, key):
        return context["rewards"].mean(-1, keepdims=True)

    def task_latents(self, params):
        return params["table"]


def to_goal(params, obs, z):
    """The policy: straight to the goal z at full speed (reaches it exactly once within one step)."""
    return jnp.clip((z - obs) / STEP, -1.0, 1.0)


def still(params, obs, z):
    return jnp.zeros_like(obs) + params["drift"]


@pytest.fixture(scope="module")
def data():
    from conftest import synthetic_family_data

    return dataclasses.replace(synthetic_family_data("PointGoal", n_train=4, n_test=3, episodes=2, length=LENGTH), noise=0.0)


def states(method_params=None, actor=None):
    method_params = {"table": jnp.stack([jnp.array([[-1.0], [-2.0]])] * RUNS)} if method_params is None else method_params
    actor = {"drift": jnp.stack([jnp.array([0.05, 0.1])] * RUNS)} if actor is None else actor
    return SimpleNamespace(method=SimpleNamespace(params=method_params),
                           iql=SimpleNamespace(actor=SimpleNamespace(params=actor)))


KEYS = jnp.stack([jax.random.PRNGKey(3), jax.random.PRNGKey(4)])
SEEDS = [100, 200]


def collect(data, method, policy, k, episodes=1, context_length=20, keys=KEYS, state=None):
    evaluator = Evaluator(method, SimpleNamespace(act=policy), data, context_length, family=get_family(data.family))
    collector = SelfCollector(evaluator, k, episodes, episode_length=LENGTH)
    return evaluator, collector.run(states() if state is None else state, keys, SEEDS)


def test_window_holds_the_last_transitions_evenly():
    assert window_indices(10, 4).tolist() == [6, 7, 8, 9]  # full: the last C
    assert window_indices(3, 6).tolist() == [0, 0, 1, 1, 2, 2]  # n divides C: each C / n times
    counts = np.bincount(window_indices(7, 20))
    assert counts.sum() == 20 and set(counts) == {2, 3}  # floor or ceil of 20 / 7
    assert reinference_steps(10, 40).tolist() == [10, 20, 30, 40] and reinference_steps(50, 40).size == 0
    with pytest.raises(OnlineError, match="end must be an integer >= 1"):
        window_indices(0, 5)


def test_exact_inference_acts_as_the_oracle_after_the_first_reinference(data):
    evaluator, out = collect(data, ExactTask(), to_goal, k=5)
    truth = np.asarray(data.test_task_arrays, np.float32)
    train = np.asarray(data.train_task_arrays, np.float32)
    assert np.allclose(out.latents, truth[None]) and np.allclose(out.reference, train[None])
    # the prior is a training task's parameters; every later latent is the true task
    assert all(np.any(np.all(np.isclose(z, train), axis=1)) for z in out.prior_latents.reshape(-1, 2))
    right = evaluator.inference_error(truth, train)
    assert np.allclose(out.inference_errors[:, 1:], right) and out.error_steps.tolist() == [0, 5, 10, 15, 20, 25,
                                                                                            30, 35, 40]
    # the oracle (true goal from step 0) and the self-collecting policy both end at the goal
    oracle = rollout(get_family("PointGoal"), list(data.test_tasks), lambda obs, _: np.asarray(to_goal({}, obs, truth)),
                     noise=0.0, seed=SEEDS[0], length=LENGTH)
    assert np.allclose(out.rewards[0, :, -15:], oracle.rewards[:, -15:], atol=1e-5)
    assert np.all(out.returns[0, :, 0] <= oracle.returns + 1e-5)
    # k = the episode: no re-inference before the end, the whole episode is the prior's
    _, late = collect(data, ExactTask(), to_goal, k=LENGTH)
    prior = late.prior_latents[0]
    acting = rollout(get_family("PointGoal"), list(data.test_tasks), lambda obs, _: np.asarray(to_goal({}, obs, prior)),
                     noise=0.0, seed=SEEDS[0], length=LENGTH)
    assert np.array_equal(late.returns[0, :, 0], acting.returns) and np.allclose(late.latents, truth[None])


@pytest.mark.parametrize("context_length", [20, 80])
def test_reinference_reads_the_envs_own_last_transitions(data, context_length):
    _, out = collect(data, MeanReward(), still, k=10, context_length=context_length)
    used = min(LENGTH, context_length)  # 80 > 40: all 40 transitions, each twice
    assert out.context_sizes.tolist() == [min(t, context_length) for t in (10, 20, 30, 40)]
    assert np.allclose(out.latents[..., 0], out.rewards[..., -used:].mean(-1), atol=1e-5)
    # the prior: a table entry per env, before any transition
    assert set(np.unique(out.prior_latents).tolist()) <= {-1.0, -2.0} and out.reference.shape == (RUNS, 2, 1)


def test_episodes_carry_z_and_the_record_over(data):
    _, out = collect(data, MeanReward(), still, k=LENGTH, episodes=3, context_length=2 * LENGTH)
    assert out.returns.shape == (RUNS, 3, 3) and out.rewards.shape == (RUNS, 3, 3 * LENGTH)
    assert out.error_steps.tolist() == [0, 40, 80, 120] and out.context_sizes.tolist() == [40, 80, 80]
    assert np.allclose(out.latents[..., 0], out.rewards[..., -2 * LENGTH:].mean(-1), atol=1e-5)  # spans 2 episodes
    summary = out.summary()
    assert {"self_return", "self_ep2_return", "self_ep3_return", "self_inference_error"} <= set(summary)
    assert len(summary["self_reward_curve"]) == 3 * LENGTH and summary["self_episode_returns"][0] == pytest.approx(
        summary["self_return"], abs=1e-3)


def test_same_key_same_numbers(data):
    _, a = collect(data, ExactTask(), to_goal, k=10)
    _, b = collect(data, ExactTask(), to_goal, k=10)
    assert np.array_equal(a.returns, b.returns) and np.array_equal(a.inference_errors, b.inference_errors)
    other = jnp.stack([jax.random.PRNGKey(5), jax.random.PRNGKey(6)])
    _, c = collect(data, ExactTask(), to_goal, k=10, keys=other)
    assert not np.array_equal(a.prior_latents, c.prior_latents)


def test_bad_settings_are_one_clear_error(data):
    evaluator = Evaluator(ExactTask(), SimpleNamespace(act=to_goal), data, 20, family=get_family(data.family))
    for k, message in ((0, "reinfer_every must be an integer >= 1, got 0"), (True, "reinfer_every"),
                       (2.5, "reinfer_every")):
        with pytest.raises(OnlineError, match=message):
            SelfCollector(evaluator, k)
    with pytest.raises(OnlineError, match="episodes must be an integer >= 1"):
        SelfCollector(evaluator, 10, episodes=0)
    kuhn = SimpleNamespace(family=get_family("KuhnPoker"), context_mix=None)
    with pytest.raises(OnlineError, match="KuhnPoker: its return is computed exactly per hand"):
        SelfCollector(kuhn, 10)
    with pytest.raises(ProbeError, match="self_collect_every must be an integer >= 1"):
        Probe(self_collect_every=0).check()
    with pytest.raises(ProbeError, match="self_collect_episodes needs self_collect_every"):
        Probe(self_collect_episodes=3).check()
    with pytest.raises(ProbeError, match="replaces the given contexts"):
        Probe(self_collect_every=10, context_mix=0.5).check()
    assert Probe(self_collect_every=10).name == "self10"
    assert Probe(self_collect_every=10, self_collect_episodes=3).name == "self10x3"
