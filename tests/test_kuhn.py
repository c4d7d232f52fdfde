"""KuhnPoker (App. D.4): exact game values, the env against OpenSpiel, the best-response expert,
exact evaluation, every method on a small collection, and `bati envs` without the `games` extra.

Everything but the last tests needs OpenSpiel (`pip install 'bati[games]'`) and is skipped without it.
"""

from __future__ import annotations

import importlib
import itertools
import json
import sys

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.rl.iql import IQLConfig
from bati.cli import main
from bati.envs import FAMILY_NAMES, EPISODE_LENGTH, FamilyUnavailable, TaskError, get_family
from bati.methods import METHODS

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("kuhn")

try:
    import pyspiel
except ImportError:
    pyspiel = None
needs_openspiel = pytest.mark.skipif(pyspiel is None, reason="needs OpenSpiel: pip install 'bati[games]'")
kuhn = importlib.import_module("bati.envs.kuhn") if pyspiel is not None else None

NEVER_BETS_ALWAYS_CALLS = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
ALWAYS_BETS_NEVER_CALLS = [1.0, 1.0, 1.0, 0.0, 0.0, 0.0]
EQUILIBRIUM = [1 / 3, 0.0, 1.0, 0.0, 1 / 3, 1.0]  # player 2's (unique) Nash equilibrium strategy
J, Q, K = 0, 1, 2


def pure_policies():
    """All 64 deterministic player-1 policies as (first_bet (3,), second_call (3,))."""
    for bits in itertools.product((0.0, 1.0), repeat=6):
        yield np.array(bits[:3]), np.array(bits[3:])


def random_opponents(n, seed=0):
    return get_family("KuhnPoker").sample_tasks(n, seed)


# --- exact values -------------------------------------------------------------------------
@needs_openspiel
def test_best_response_values_computed_by_hand():
    # Opponent A never bets when checked to and always calls a bet.
    #   J: bet -> called, loses 2 (both Q and K win): -2; check -> showdown, loses 1: -1  => check, -1
    #   Q: bet -> called, +2 vs J, -2 vs K: 0;          check -> showdown +1 / -1: 0     => tie: check, 0
    #   K: bet -> called, wins 2: +2;                  check -> showdown, wins 1: +1     => bet, +2
    #   second decisions are never reached (A never bets): ties, fold.   value = (-1 + 0 + 2) / 3 = 1/3
    first_bet, second_call = kuhn.best_response(np.array(NEVER_BETS_ALWAYS_CALLS))
    np.testing.assert_array_equal(first_bet, [0, 0, 1])
    np.testing.assert_array_equal(second_call, [0, 0, 0])
    assert kuhn.best_response_value(np.array(NEVER_BETS_ALWAYS_CALLS)) == pytest.approx(1 / 3, abs=1e-12)
    # Opponent B always bets when checked to and always folds to a bet.
    #   J: bet -> B folds: +1; check -> B bets, fold -1 (call loses 2)                     => bet, +1
    #   Q: bet -> +1;          check -> B bets, call: +2 vs J, -2 vs K = 0 > fold -1: 0      => bet, +1
    #   K: bet -> +1;          check -> B bets, call wins 2: +2                            => check-call, +2
    #   value = (1 + 1 + 2) / 3 = 4/3; second decisions: J folds, Q and K call
    first_bet, second_call = kuhn.best_response(np.array(ALWAYS_BETS_NEVER_CALLS))
    np.testing.assert_array_equal(first_bet, [1, 1, 0])
    np.testing.assert_array_equal(second_call, [0, 1, 1])
    assert kuhn.best_response_value(np.array(ALWAYS_BETS_NEVER_CALLS)) == pytest.approx(4 / 3, abs=1e-12)
    # Against player 2's equilibrium, player 1's best is the game value -1/18.
    assert kuhn.best_response_value(np.array(EQUILIBRIUM)) == pytest.approx(-1 / 18, abs=1e-12)
    # The value of a given policy by hand: always bet against A: J -2, Q 0, K +2 -> 0.
    assert kuhn.policy_value(np.ones(3), np.zeros(3), np.array(NEVER_BETS_ALWAYS_CALLS)) == pytest.approx(0.0)


@needs_openspiel
def test_best_response_beats_every_other_policy():
    rng = np.random.default_rng(0)
    opponents = [NEVER_BETS_ALWAYS_CALLS, ALWAYS_BETS_NEVER_CALLS, EQUILIBRIUM] + random_opponents(30)
    for theta in map(np.array, opponents):
        best = kuhn.best_response_value(theta)
        br_value = kuhn.policy_value(*kuhn.best_response(theta), theta)
        assert br_value == pytest.approx(best, abs=1e-12)
        values = [kuhn.policy_value(x, y, theta) for x, y in pure_policies()]
        assert max(values) == pytest.approx(best, abs=1e-12)
        mixed = kuhn.policy_value(rng.uniform(size=(200, 3)), rng.uniform(size=(200, 3)), theta)
        assert np.all(mixed <= best + 1e-12)
    # tasks differ in what exploits them: the best responses to the 30 opponents are not all one policy
    patterns = {tuple(np.concatenate(kuhn.best_response(np.array(t)))) for t in random_opponents(30)}
    assert len(patterns) >= 4


def _openspiel_opponent(game, theta):
    from open_spiel.python import policy as policy_lib

    tabular = policy_lib.TabularPolicy(game)
    for state in tabular.states:
        if state.current_player() == 1:
            card, facing_bet = state.history()[1], state.history()[-1] == kuhn.BET
            p = theta[(3 if facing_bet else 0) + card]
            tabular.action_probability_array[tabular.state_index(state)] = [1 - p, p]
    return tabular


@needs_openspiel
def test_values_agree_with_openspiel_algorithms():
    from open_spiel.python import policy as policy_lib
    from open_spiel.python.algorithms import best_response, expected_game_score

    game = pyspiel.load_game("kuhn_poker")
    for theta in random_opponents(5, seed=1) + [ALWAYS_BETS_NEVER_CALLS]:
        opponent = _openspiel_opponent(game, theta)
        br = best_response.BestResponsePolicy(game, 0, opponent)
        assert br.value(game.new_initial_state()) == pytest.approx(kuhn.best_response_value(np.array(theta)), abs=1e-9)
        # a fixed stochastic player-1 policy
        x, y = np.array([0.2, 0.5, 0.9]), np.array([0.1, 0.6, 1.0])
        mine = policy_lib.TabularPolicy(game)
        for state in mine.states:
            if state.current_player() == 0:
                card, second = state.history()[0], len(state.history()) > 2
                p = (y if second else x)[card]
                mine.action_probability_array[mine.state_index(state)] = [1 - p, p]
        expected = expected_game_score.policy_value(game.new_initial_state(), [mine, opponent])[0]
        assert expected == pytest.approx(kuhn.policy_value(x, y, np.array(theta)), abs=1e-9)


# --- the env --------------------------------------------------------------------------------
def _payoff(cards, actions):
    """Player 1's return of a finished hand, by the rules (independent of OpenSpiel)."""
    mine, theirs = cards
    win = 1 if mine > theirs else -1
    if actions == [kuhn.PASS, kuhn.PASS]:
        return win
    if actions == [kuhn.BET, kuhn.PASS]:
        return 1
    if actions == [kuhn.PASS, kuhn.BET, kuhn.PASS]:
        return -1
    return 2 * win  # a bet was called


@needs_openspiel
@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_env_rewards_and_terminations_match_openspiel_over_random_play(noise):
    task = random_opponents(1, seed=2)[0]
    env = gym.make("bati/KuhnPoker-v0", task=task, noise=noise)
    game = pyspiel.load_game("kuhn_poker")
    rng = np.random.default_rng(3)
    hands = 0
    for episode in range(3):
        obs, _ = env.reset(seed=episode)
        total, hand_returns, step, done = 0.0, [], 0, False
        while not done:
            assert obs.shape == (kuhn.OBS_DIM,) and obs.dtype == np.float32
            action = rng.integers(2) if step % 3 else rng.uniform(size=2)  # ints and argmax'd vectors
            next_obs, reward, terminated, truncated, info = env.step(action)
            assert info["task_used"] == pytest.approx(list((1 - noise) * np.array(task) + noise / 2))
            if info["hand_over"]:
                history = info["hand_history"]
                state = game.new_initial_state()
                for a in history:
                    state.apply_action(a)
                assert state.is_terminal() and reward == state.returns()[0] == _payoff(history[:2], history[2:])
                hand_returns.append(reward)
                if step % 2 == 0:  # ended at the hand's first step: the flag is set, a padding step follows
                    assert next_obs[kuhn.HAND_OVER] == 1.0
                    np.testing.assert_array_equal(next_obs[:-1], state.information_state_tensor(0))
            else:
                assert reward == 0.0
                assert info.get("padding", False) == (step % 2 == 1 and obs[kuhn.HAND_OVER] == 1.0)
                if step % 2 == 0:  # player 2 bet after a pass: the second decision
                    assert list(next_obs[5:11]) == [1, 0, 0, 1, 0, 0] and next_obs[kuhn.HAND_OVER] == 0.0
            if step % 2 == 1:  # every hand takes exactly 2 steps: a fresh deal follows
                assert next_obs[kuhn.HAND_OVER] == 0 and not next_obs[5:].any() and next_obs[2:5].sum() == 1
            total += reward
            step += 1
            done = terminated or truncated
            obs = next_obs
        assert (step, terminated, truncated) == (EPISODE_LENGTH, False, True)
        assert len(hand_returns) == kuhn.HANDS_PER_EPISODE and total == sum(hand_returns)
        hands += len(hand_returns)
    assert hands == 300


@needs_openspiel
def test_opponent_plays_its_probabilities_and_trembles_with_noise():
    theta = [0.9, 0.2, 0.6, 0.3, 0.7, 0.1]
    for noise in (0.0, 0.5):
        env = get_family("KuhnPoker").make_env(theta, noise).unwrapped  # no time limit
        env.reset(seed=0)
        counts = np.zeros((6, 2))
        choices = np.random.default_rng(1).integers(2, size=12000)
        for t in range(12000):
            phase_first = env._phase == 0
            env.step(choices[t] if phase_first else 0)  # first: pass or bet at random
            if phase_first:
                history = env._state.history()
                row = (3 if history[2] == kuhn.BET else 0) + history[1]
                counts[row] += [1, history[3] == kuhn.BET]
        expected = (1 - noise) * np.array(theta) + noise / 2
        freq = counts[:, 1] / counts[:, 0]
        assert np.all(np.abs(freq - expected) < 5 * np.sqrt(expected * (1 - expected) / counts[:, 0]) + 1e-9)


@needs_openspiel
def test_family_tasks_distance_and_spaces():
    family = get_family("KuhnPoker")
    tasks = family.sample_tasks(50, seed=3)
    assert tasks == family.sample_tasks(50, seed=3) != family.sample_tasks(50, seed=4)
    assert all(len(t) == 6 and all(0 <= p <= 1 for p in t) for t in tasks)
    assert family.task_to_array(tasks[0]).shape == (6,) and family.task_dim == 6
    assert family.distance(NEVER_BETS_ALWAYS_CALLS, ALWAYS_BETS_NEVER_CALLS) == pytest.approx(np.sqrt(6))
    assert family.most_different(NEVER_BETS_ALWAYS_CALLS, [EQUILIBRIUM, ALWAYS_BETS_NEVER_CALLS]) == 1
    for bad in ([0.5] * 5, [0.5] * 5 + [1.5], [0.5] * 5 + [float("nan")]):
        with pytest.raises(TaskError, match="KuhnPoker"):
            family.make_env(bad)
    with pytest.raises(TaskError, match=r"\[0, 1\]"):
        family.validate_noise(1.5)
    env = family.make_env(tasks[0])
    assert env.observation_space.shape == (12,) and env.action_space.shape == (2,)
    assert family.discrete_actions and family.default_context_length == 20 and family.return_unit == "hand"
    env.reset(seed=0)
    with pytest.raises(ValueError, match="0 \\(pass\\) or 1 \\(bet\\)"):
        env.step(3)


@needs_openspiel
def test_exact_returns_match_the_mean_of_rollouts():
    from bati.envs.rollout import rollout

    family = get_family("KuhnPoker")
    tasks = random_opponents(2, seed=5) + [ALWAYS_BETS_NEVER_CALLS]
    # a deterministic policy: the best response to another opponent, looked up per observation
    x, y = kuhn.best_response(np.array(NEVER_BETS_ALWAYS_CALLS))

    def act(obs, _=0):
        card, second, over = kuhn.decision_parts(obs)
        bet = np.where(over, 0, np.where(second, y[card], x[card]))
        return np.stack([1 - bet, bet], -1)

    exact = family.exact_returns(act, tasks, 0.0)
    np.testing.assert_allclose(exact, [kuhn.policy_value(x, y, np.array(t)) for t in tasks])
    episodes = rollout(family, tasks * 20, act, noise=0.0, seed=0)  # 2,000 hands per task
    per_hand = episodes.returns.reshape(20, len(tasks)).mean(0) / kuhn.HANDS_PER_EPISODE
    standard_error = 2.0 / np.sqrt(20 * kuhn.HANDS_PER_EPISODE)  # |return| <= 2
    assert np.all(np.abs(per_hand - exact) < 4 * standard_error)
    random_exact = family.exact_returns(None, tasks, 0.0)
    np.testing.assert_allclose(random_exact, [kuhn.policy_value(np.full(3, .5), np.full(3, .5), np.array(t))
                                              for t in tasks])


# --- the expert -------------------------------------------------------------------------------
@needs_openspiel
def test_expert_is_the_best_response_and_explores_epsilon_greedily():
    from bati.data.collect import load_expert
    from bati.experts.kuhn import EXPLORATION, BestResponseExpert

    expert = load_expert(get_family("KuhnPoker"))
    assert isinstance(expert, BestResponseExpert)
    assert (expert.meta["obs_dim"], expert.meta["action_dim"], expert.meta["task_dim"]) == (12, 2, 6)
    obs = kuhn.decision_observations()
    for theta in random_opponents(10, seed=6) + [ALWAYS_BETS_NEVER_CALLS]:
        x, y = kuhn.best_response(np.array(theta))
        actions = expert(obs, theta)
        np.testing.assert_array_equal(actions[:, 1], np.concatenate([x, y]))
        assert np.all(actions.sum(-1) == 1)
        jitted = jax.jit(expert.mean_action)(jnp.asarray(obs), jnp.broadcast_to(jnp.asarray(theta), (6, 6)))
        np.testing.assert_array_equal(np.asarray(jitted), actions)
    # epsilon-greedy: the best-response action with probability 1 - eps / 2; padding steps always pass
    theta = np.array(ALWAYS_BETS_NEVER_CALLS)
    over = np.zeros(kuhn.OBS_DIM, np.float32)
    over[[0, 2, 5, 7]] = 1.0  # J, bet, fold ...
    over[kuhn.HAND_OVER] = 1.0
    many = np.concatenate([np.repeat(obs[:1], 4000, 0), np.repeat(over[None], 1000, 0)])
    acts = expert.act_from_arrays(many, np.repeat(theta[None], len(many), 0), False, jax.random.PRNGKey(0))
    assert np.all(acts.sum(-1) == 1) and np.all(acts[4000:, 0] == 1)
    off = 1 - acts[:4000, 1].mean()  # J: the best response bets
    assert abs(off - EXPLORATION / 2) < 5 * np.sqrt(EXPLORATION / 2 / 4000)


@needs_openspiel
def test_there_is_no_sac_expert_to_train_or_card(capsys):
    for args in (["experts", "train", "--family", "KuhnPoker"], ["experts", "card", "--family", "KuhnPoker"]):
        assert main(args) == 2
        assert "exact best response" in capsys.readouterr().err


# --- collection, every method, evaluation --------------------------------------------------------
@pytest.fixture(scope="module")
def small_collection(tmp_path_factory):
    """A KuhnPoker collection of 2 episodes per opponent (1 context episode) and its FamilyData."""
    from bati.data import load_family_data
    from bati.data.collect import collect

    root = tmp_path_factory.mktemp("kuhn-data")
    result = collect("KuhnPoker", "quick", 0, root=root, progress=False, n_episodes=2, n_context_episodes=1,
                     workers=1)
    return root, result.manifest, load_family_data("KuhnPoker", root=root)


@needs_openspiel
def test_a_small_collection_holds_one_hot_actions_and_the_most_different_tasks(small_collection):
    _, manifest, data = small_collection
    family = get_family("KuhnPoker")
    assert (manifest["obs_dim"], manifest["action_dim"], manifest["kind"]) == (12, 2, "opponent")
    actions = np.asarray(data.train.actions)
    assert np.all(actions.sum(-1) == 1) and set(np.unique(actions)) == {0.0, 1.0}  # one-hot
    assert manifest["p_test_most_different"] == [family.most_different(t, data.train_tasks) for t in data.test_tasks]


@needs_openspiel
@pytest.mark.slow
@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_trains_and_evaluates_on_a_small_collection(method, small_collection, tmp_path):
    from bati.config import TrainConfig
    from bati.train import train

    root, _, data = small_collection
    expert_value = np.mean([kuhn.best_response_value(np.array(t)) for t in data.test_tasks])
    config = TrainConfig(family="KuhnPoker", method=method, steps=2, log_every=2, eval_every=2,
                         iql=IQLConfig(hidden_dims=(16, 16)), task_batch=4, batch_size=8, data_root=root,
                         episodes_per_task=2, context_episodes=1, out_dir=tmp_path / method)
    summary = train(config, show_progress=False)
    saved = json.loads((tmp_path / method / "config.json").read_text())
    assert saved["context_length"] == 20 and saved["iql"]["discrete"] is True
    for source in ("p_test", "p_train"):  # exact expected returns per hand
        returns = np.array(summary[f"{source}_task_returns"])
        assert returns.shape == (20,) and np.all(np.abs(returns) <= 2)
        assert np.all(returns <= [kuhn.best_response_value(np.array(t)) + 1e-3 for t in data.test_tasks])
    assert summary["reference_returns"]["expert"] == pytest.approx(expert_value, abs=1e-9)


# --- without the `games` extra ------------------------------------------------------------------
def _without_openspiel(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyspiel", None)  # `import pyspiel` raises ImportError
    for name in ("bati.envs.kuhn", "bati.experts.kuhn"):
        monkeypatch.delitem(sys.modules, name, raising=False)


def test_families_list_and_kuhn_install_hint_without_openspiel(monkeypatch, capsys):
    _without_openspiel(monkeypatch)
    with pytest.raises(FamilyUnavailable, match=r"pip install 'bati\[games\]'"):
        get_family("KuhnPoker")
    assert get_family("PointGoal").name == "PointGoal"
    assert main(["envs"]) == 0
    out, err = capsys.readouterr()
    assert all(name in out for name in FAMILY_NAMES) and err == ""
    assert "KuhnPoker needs OpenSpiel, which is not installed; install it with `pip install 'bati[games]'`" in out
    assert main(["envs", "--family", "KuhnPoker"]) == 2
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "Traceback" not in err, err
    assert "KuhnPoker needs OpenSpiel" in lines[0] and "pip install 'bati[games]'" in lines[0]


def test_opponents_are_drawn_near_player_2s_equilibrium():
    # against player 2's Nash policy no player-1 policy earns more than the game's value, -1/18 per hand
    assert kuhn.best_response_value(kuhn.EQUILIBRIUM) == pytest.approx(-1 / 18)
    tasks = np.array(get_family("KuhnPoker").sample_tasks(2000, seed=0))
    low = 0.75 * kuhn.EQUILIBRIUM  # version 2: 3/4 equilibrium + 1/4 uniform in [0, 1]^6
    assert np.all(tasks >= low - 1e-12) and np.all(tasks <= low + 0.25 + 1e-12)
    np.testing.assert_allclose(tasks.mean(0), low + 0.125, atol=0.01)
    assert get_family("KuhnPoker").record.version == 2
