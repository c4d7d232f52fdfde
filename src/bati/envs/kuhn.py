"""KuhnPoker (App. D.4): the learner is player 1 of OpenSpiel's `kuhn_poker`; a task is player 2's policy.

The game (OpenSpiel's implementation): a deck of three cards J < Q < K, each player antes 1 and
gets one card. Player 1 (OpenSpiel's player 0) passes or bets 1; after a pass player 2 passes
(showdown for 1) or bets 1, and player 1 then folds (-1) or calls (showdown for 2); after a bet
player 2 folds (+1 for player 1) or calls (showdown for 2).

A task is an opponent: six probabilities
    [bet with J, bet with Q, bet with K  (when player 1 passed),
     call with J, call with Q, call with K  (when player 1 bet)],
drawn as theta = 3/4 EQUILIBRIUM + 1/4 u, u uniform in [0, 1]^6 (version 2; version 1 drew theta
uniformly, which leaves every opponent very exploitable: a best response earned 0.56 per hand on
average, and one policy earned 92% of that against all of them). EQUILIBRIUM is player 2's Nash
policy (bet J 1/3, Q 0, K 1; call J 0, Q 1/3, K 1), against which player 1 earns -1/18 per hand.
The best response to the version-2 opponents earns ~0.076 per hand on average (the paper's oracle:
0.073; the paper does not say how it drew opponents). Distance: Euclidean between these vectors.

One env episode is HANDS_PER_EPISODE = 100 hands of exactly 2 steps each (EPISODE_LENGTH = 200):
- step 1 of a hand: player 1's first decision (pass / bet). Its reward is the hand's return for
  player 1 if the hand ended (player 2 passed back, folded or called), else 0; its next
  observation is player 1's second decision (pass, bet) or the finished hand with the `hand over`
  flag set.
- step 2: player 1's second decision (fold = pass / call = bet; reward: the hand's return) or,
  when the hand is already over, a padding step (reward 0, action ignored). Its next observation
  is the first decision of the next hand (a fresh deal).
Observation (12 floats): OpenSpiel's information-state tensor of player 1 (11: player one-hot,
card one-hot, and the pass/bet bits of the three betting rounds) plus the `hand over` flag.
Action: a 2-vector read by argmax (index 0 = pass/check/fold, 1 = bet/call; a one-hot in the
data), or the plain integer 0 / 1.
Noise eps: each of player 2's actions is, with probability eps, a uniformly random one instead of
its policy's (a trembling hand); the opponent then plays (1 - eps) theta + eps / 2. Default 0:
the hidden cards already make every step stochastic.

Pure-numpy game theory of the family (also used by the best-response expert and by the
evaluation): `policy_value` (exact expected return per hand of a player-1 policy, enumerating the
6 deals), `best_response` and `best_response_value`.
"""

from __future__ import annotations

import numpy as np

try:
    import pyspiel
except ImportError as err:  # the `games` extra; bati.envs.get_family turns this into an install hint
    raise ImportError(f"KuhnPoker needs OpenSpiel (`pip install 'bati[games]'`): {err}",
                      name="pyspiel") from err

import gymnasium as gym

from bati.envs.base import EPISODE_LENGTH, FamilyRecord, TaskEnvMixin, TaskError, TaskFamily

HANDS_PER_EPISODE = EPISODE_LENGTH // 2
PASS, BET = 0, 1
INFO_STATE_DIM = 11  # OpenSpiel's kuhn_poker information-state tensor (2 players)
OBS_DIM = INFO_STATE_DIM + 1  # + the `hand over` flag
HAND_OVER = INFO_STATE_DIM  # index of the flag
CARD_SLICE = slice(2, 5)  # card one-hot in the tensor
SECOND_DECISION_BIT = 8  # round 2 "bet" bit: player 2 bet after player 1 passed

# WIN[c, d] = +1 if card c beats card d, -1 if it loses (0 on the diagonal, never dealt)
WIN = np.sign(np.arange(3)[:, None] - np.arange(3)[None, :]).astype(np.float64)
OTHER = 1.0 - np.eye(3)  # OTHER[c, d] = 1 if d can be the opponent's card when player 1 holds c
EQUILIBRIUM = np.array([1 / 3, 0.0, 1.0, 0.0, 1 / 3, 1.0])  # player 2's Nash policy (its only one)
EQUILIBRIUM_SHARE = 0.75  # an opponent is 3/4 of it plus 1/4 of a uniform draw (version 2)


# --- exact game theory (xp: numpy, or jax.numpy inside jitted code) ---------------------------
def effective_opponent(theta, noise: float = 0.0, xp=np):
    """The opponent's action probabilities under the trembling-hand noise eps."""
    return (1.0 - noise) * xp.asarray(theta) + 0.5 * noise


def _terms(theta, xp=np):
    """Per player-1 card c, expected payoffs summed over the two opponent cards d (each 1/2):
    bet (player 2 folds or calls), pass-then-showdown (player 2 passes), and after a pass and a
    bet: call and fold, each weighted by the probability that player 2 bets."""
    theta = xp.asarray(theta)
    bets, calls = theta[..., :3], theta[..., 3:]
    win, other = xp.asarray(WIN), xp.asarray(OTHER)
    over = lambda matrix, v: 0.5 * xp.einsum("cd,...d->...c", matrix, v)  # noqa: E731
    bet = over(other, 1.0 - calls) + 2.0 * over(win, calls)
    showdown = over(win, 1.0 - bets)
    call = 2.0 * over(win, bets)
    fold = -over(other, bets)
    return bet, showdown, call, fold


def policy_value(first_bet, second_call, theta, noise: float = 0.0, xp=np):
    """Exact expected return per hand of player 1 against opponent `theta` (..., 6).

    `first_bet` (..., 3): probability of betting first with J, Q, K; `second_call` (..., 3):
    probability of calling player 2's bet after passing. Enumerates the 6 deals (each 1/6).
    """
    bet, showdown, call, fold = _terms(effective_opponent(theta, noise, xp), xp)
    first_bet, second_call = xp.asarray(first_bet), xp.asarray(second_call)
    check = showdown + second_call * call + (1.0 - second_call) * fold
    return (first_bet * bet + (1.0 - first_bet) * check).mean(-1)


def best_response(theta, noise: float = 0.0, xp=np):
    """Player 1's deterministic best response (first_bet, second_call), each (..., 3) in {0, 1}.

    Ties go to pass / fold (they only occur at unreachable or indifferent decisions)."""
    bet, showdown, call, fold = _terms(effective_opponent(theta, noise, xp), xp)
    second_call = (call > fold).astype(xp.float32)
    check = showdown + xp.maximum(call, fold)
    first_bet = (bet > check).astype(xp.float32)
    return first_bet, second_call


def best_response_value(theta, noise: float = 0.0, xp=np):
    """Exact expected return per hand of the best response (the oracle's value)."""
    bet, showdown, call, fold = _terms(effective_opponent(theta, noise, xp), xp)
    return xp.maximum(bet, showdown + xp.maximum(call, fold)).mean(-1)


def decision_observations() -> np.ndarray:
    """The 6 observations at which player 1 decides: (first decision with J, Q, K; second decision
    with J, Q, K), shape (6, OBS_DIM)."""
    game = pyspiel.load_game("kuhn_poker")
    rows = []
    for history in ([], [PASS, BET]):
        for card in range(3):
            state = game.new_initial_state()
            state.apply_action(card)
            state.apply_action((card + 1) % 3)
            for action in history:
                state.apply_action(action)
            rows.append(observation(state, hand_over=False))
    return np.stack(rows)


def observation(state, hand_over: bool) -> np.ndarray:
    return np.asarray(list(state.information_state_tensor(0)) + [float(hand_over)], dtype=np.float32)


def decision_parts(obs, xp=np):
    """Card index, is-second-decision and is-hand-over of observations (..., OBS_DIM)."""
    obs = xp.asarray(obs)
    card = xp.argmax(obs[..., CARD_SLICE], axis=-1)
    over = obs[..., HAND_OVER] > 0.5
    second = (obs[..., SECOND_DECISION_BIT] > 0.5) & ~over
    return card, second, over


def action_index(action) -> int:
    """A 2-vector (argmax; ties -> pass) or an integer 0 / 1 as the game's action."""
    a = np.asarray(action)
    if a.size == 1:
        value = float(a.reshape(-1)[0])
        if value not in (0.0, 1.0):
            raise ValueError(f"KuhnPoker: action {action!r} must be 0 (pass) or 1 (bet), or a 2-vector")
        return int(value)
    if a.shape[-1:] != (2,) or a.size != 2:
        raise ValueError(f"KuhnPoker: action {action!r} must be a 2-vector (argmax: 0 pass, 1 bet) or 0 / 1")
    return int(np.argmax(a))


class KuhnPokerFamily(TaskFamily):
    record = FamilyRecord(
        name="KuhnPoker",
        task_space=("an opponent (player 2): probabilities [bet with J, Q, K when checked to, "
                    "call a bet with J, Q, K], each in [0, 1]"),
        task_dim=6,
        default_noise=0.0,
        max_noise=1.0,
        noise_meaning="probability that each opponent action is uniformly random instead of its policy's",
        kind="opponent",  # the opponent's policy changes both the transitions and the rewards
        discrete_actions=True,
        context_length=20,  # 10 hands (App. D.4)
        return_unit="hand",
        paper_episodes=500,  # 50,000 hands per task (the paper does not give Kuhn's size)
        expert_steps=None,  # the exact best response (bati.experts.kuhn), computed
        expert_name="exact best responses",
        version=2,  # opponents near equilibrium (version 1: uniform in [0, 1]^6)
    )

    def _sample(self, n, rng):
        theta = EQUILIBRIUM_SHARE * EQUILIBRIUM + (1.0 - EQUILIBRIUM_SHARE) * rng.uniform(0.0, 1.0, size=(n, 6))
        return [[float(x) for x in row] for row in theta]

    def _check(self, task):
        theta = np.asarray(task, dtype=np.float64)
        if theta.shape != (6,):
            raise TaskError(f"{self.name}: task {task!r} must be 6 probabilities, {self.task_space}")
        if not np.all((theta >= 0.0) & (theta <= 1.0)):  # NaN fails too
            raise TaskError(f"{self.name}: task {task!r} is outside the task space: {self.task_space}")
        return [float(x) for x in theta]

    def distance(self, a, b):
        return float(np.linalg.norm(np.asarray(self._check(a)) - np.asarray(self._check(b))))

    def exact_returns(self, act, tasks, noise):
        """Exact expected return PER HAND of a deterministic policy in each task.

        `act(observations (N, OBS_DIM)) -> actions (N, 2)` is called once per decision observation
        (6 calls, N = len(tasks), row i for task i) and read as the env reads an action (argmax);
        `act=None` is the uniformly random policy."""
        tasks = [self.validate_task(t) for t in tasks]
        theta = np.array(tasks, dtype=np.float64).reshape(len(tasks), 6)
        noise = self.validate_noise(noise)
        if act is None:
            return policy_value(np.full((len(tasks), 3), 0.5), np.full((len(tasks), 3), 0.5), theta, noise)
        bets = np.zeros((len(tasks), 6))
        for i, obs in enumerate(decision_observations()):
            actions = np.asarray(act(np.repeat(obs[None], len(tasks), axis=0)))
            bets[:, i] = [action_index(a) for a in actions.reshape(len(tasks), -1)]
        return policy_value(bets[:, :3], bets[:, 3:], theta, noise)


class KuhnPokerEnv(TaskEnvMixin, gym.Env):
    """100 hands of OpenSpiel Kuhn poker against a fixed opponent, 2 steps per hand (see the module)."""

    metadata = {"render_modes": []}
    family = KuhnPokerFamily()

    def __init__(self, task, noise: float | None = None):
        self._set_task(task, noise)
        self.observation_space = gym.spaces.Box(0.0, 1.0, (OBS_DIM,), np.float32)
        self.action_space = gym.spaces.Box(0.0, 1.0, (2,), np.float32)
        self._game = pyspiel.load_game("kuhn_poker")
        self._state = None
        self._phase = 0  # 0: first decision, 1: second decision, 2: hand over (padding step next)

    def _opponent(self) -> np.ndarray:
        return effective_opponent(np.asarray(self.task), self.noise)

    def _deal(self) -> np.ndarray:
        state = self._game.new_initial_state()
        mine = int(self.np_random.integers(3))
        state.apply_action(mine)
        theirs = [c for c in range(3) if c != mine][int(self.np_random.integers(2))]
        state.apply_action(theirs)
        self._state, self._phase = state, 0
        return observation(state, hand_over=False)

    def _opponent_acts(self) -> None:
        state = self._state
        card = int(state.history()[1])
        facing_bet = state.history()[-1] == BET
        p_bet = self._opponent()[(3 if facing_bet else 0) + card]
        state.apply_action(BET if self.np_random.random() < p_bet else PASS)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self._deal(), {}

    def step(self, action):
        state = self._state
        if state is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        info = {"task_used": self._opponent().tolist(), "hand_over": False}
        reward = 0.0
        if self._phase == 2:  # padding step of a hand that ended at its first step: action ignored
            info["padding"] = True
            next_obs = self._deal()
        else:
            state.apply_action(action_index(action))
            if not state.is_terminal():
                self._opponent_acts()
            if state.is_terminal():
                reward = float(state.returns()[0])
                info.update(hand_over=True, hand_history=list(state.history()))
                if self._phase == 0:  # the hand is over after one step: a padding step follows
                    self._phase = 2
                    next_obs = observation(state, hand_over=True)
                else:
                    next_obs = self._deal()
            else:  # player 2 bet after player 1's pass: player 1's second decision
                self._phase = 1
                next_obs = observation(state, hand_over=False)
        info["reward_noise_free"] = reward
        return next_obs, reward, False, False, info
