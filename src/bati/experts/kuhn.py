"""KuhnPoker's expert: the exact best response to each opponent, computed by enumeration (not trained).

"The expert for task M" is player 1's best response to opponent M (`bati.envs.kuhn.best_response`,
which enumerates the deals: the game is tiny). It is a `bati.experts.Expert`, like the SAC experts:
`act_from_arrays`, `mean_action`, `__call__`, `meta`.

- Deterministic (`deterministic=True`, `mean_action`: DPT's labels, the "Oracle (Pre-IQL)"
  reference): the best-response action, one-hot.
- Stochastic (data collection, as the SAC experts act stochastically): epsilon-greedy with
  EXPLORATION = 0.1: with probability 0.1 a uniformly random action, so every decision of every
  card appears in each task's data (the best response alone never shows e.g. a pass with K).
- At a padding step (`hand over` flag) it always writes pass: the env ignores that action.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from bati.envs import TaskFamily
from bati.envs.kuhn import BET, OBS_DIM, best_response, decision_parts
from bati.experts.base import Expert

EXPLORATION = 0.1


def best_response_actions(obs, task_arrays, xp=np):
    """One-hot best-response actions (N, 2) at observations (N, OBS_DIM) against opponents (N, 6)."""
    first_bet, second_call = best_response(task_arrays, xp=xp)
    card, second, over = decision_parts(obs, xp)
    pick = lambda table: xp.take_along_axis(table, card[..., None], axis=-1)[..., 0]  # noqa: E731
    bet = xp.where(over, 0.0, xp.where(second, pick(second_call), pick(first_bet)))
    return xp.stack([1.0 - bet, bet], axis=-1).astype(xp.float32)


class BestResponseExpert(Expert):
    """KuhnPoker's expert: the exact best response to the opponent it is conditioned on."""

    def __init__(self, family: TaskFamily, exploration: float = EXPLORATION):
        self.family = family
        self.exploration = float(exploration)
        self.meta = {"family": family.name, "kind": "best response (exact, by enumeration)", "obs_dim": OBS_DIM,
                     "action_dim": 2, "task_dim": self.family.task_dim, "hidden_dims": [], "train_steps": 0,
                     "train_wall_time_s": 0.0, "seed": None, "exploration": self.exploration}

    def mean_action(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        """The best-response actions as a jax function of arrays (usable inside a jitted training step)."""
        return best_response_actions(obs, task_arrays, xp=jnp)

    def act_from_arrays(self, obs: np.ndarray, task_arrays: np.ndarray, deterministic: bool, key) -> np.ndarray:
        """Batched actions: the best response, or epsilon-greedy with `key` when not deterministic."""
        obs, task_arrays = np.asarray(obs, np.float32), np.asarray(task_arrays, np.float64)
        actions = best_response_actions(obs, task_arrays)
        if deterministic:
            return actions
        k_explore, k_action = jax.random.split(key)
        shape = actions.shape[:-1]
        explore = np.asarray(jax.random.bernoulli(k_explore, self.exploration, shape))
        coin = np.asarray(jax.random.bernoulli(k_action, 0.5, shape))
        _, _, over = decision_parts(obs)
        bet = np.where(explore & ~over, coin, actions[..., BET] > 0.5)
        return np.stack([1.0 - bet, bet], axis=-1).astype(np.float32)
