"""Unit tests of the task families (App. C.1-C.2): rewards, noise, friction, distances, errors.

No training: every test runs at most a few thousand simulator steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import pytest

from bati.envs import EPISODE_LENGTH, FAMILY_NAMES, TaskError, get_family, make_env
from bati.envs.friction_param import action_map, inverse_action_map

# the continuous-control families; KuhnPoker (discrete, an optional extra) is tested in tests/test_kuhn.py
FAMILY_NAMES = tuple(name for name in FAMILY_NAMES if name != "KuhnPoker")

MUJOCO = ("AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam")
DYNAMICS = ("HopperParam", "WalkerParam")
GAUSSIAN = ("AntDir", "HalfCheetahVel", "HopperParam", "WalkerParam", "PointGoal")


@dataclass
class Spec:
    task: object  # a valid task away from the boundaries
    obs_dim: int
    act_dim: int
    bad_tasks: list = field(default_factory=list)  # outside the task space
    range_text: str = ""  # how the allowed range appears in error messages


SPECS = {
    "AntDir": Spec(1.0, 27, 8, [2 * math.pi, -0.1, 7.0, math.nan], "[0, 2*pi)"),
    "HalfCheetahVel": Spec(1.5, 17, 6, [-0.5, 2.5, math.inf], "[0, 2]"),
    "HalfCheetahDir": Spec(-1.0, 17, 6, [0.0, 0.5, 2.0, -3.0], "{-1.0 (left), +1.0 (right)}"),
    "HopperParam": Spec(1.0, 11, 3, [3.5, -3.01], "[-3, 3]"),
    "WalkerParam": Spec(-1.0, 17, 6, [-4.0, 10.0], "[-3, 3]"),
    "PointGoal": Spec([0.6, 0.8], 2, 2, [[0.0, -1.0], [2.0, 0.0], [0.6, 0.8, 0.0]], "angle in [0, pi]"),
}


def make(name: str, task=None, noise: float | None = 0.0, seed: int = 0) -> gym.Env:
    env = gym.make(f"bati/{name}-v0", task=SPECS[name].task if task is None else task, noise=noise)
    env.reset(seed=seed)
    return env


def warm_up(env: gym.Env, steps: int = 15, seed: int = 1) -> None:
    """Random actions so that the robot is moving (non-trivial velocities)."""
    rng = np.random.default_rng(seed)
    for _ in range(steps):
        env.step(rng.uniform(-1, 1, env.action_space.shape))


def get_state(env: gym.Env):
    u = env.unwrapped
    if hasattr(u, "data"):
        # qacc_warmstart seeds MuJoCo's constraint solver: restoring it too makes replays bitwise equal
        return u.data.qpos.copy(), u.data.qvel.copy(), u.data.qacc_warmstart.copy()
    return u._position.copy()


def set_state(env: gym.Env, state) -> None:
    u = env.unwrapped
    if hasattr(u, "data"):
        qpos, qvel, warmstart = state
        u.set_state(qpos, qvel)
        u.data.qacc_warmstart[:] = warmstart
    else:
        u._position = state.copy()


def measure(env: gym.Env) -> dict:
    """The simulator quantities the rewards are computed from."""
    u = env.unwrapped
    if hasattr(u, "data"):
        return {"x": float(u.data.qpos[0]), "xy": u.data.body(1).xpos[:2].copy()}
    return {"pos": u._position.copy()}


def hand_reward(name: str, before: dict, after: dict, action, task, dt: float | None) -> float:
    """Reward of App. C.1 computed by hand, with the task `task` used in the reward."""
    a = np.clip(np.asarray(action, dtype=np.float64), -1, 1)
    sq = float(np.sum(a**2))
    if name == "PointGoal":
        return -float(np.linalg.norm(after["pos"] - np.asarray(task)))
    if name == "AntDir":
        velocity = (after["xy"] - before["xy"]) / dt
        return velocity[0] * math.cos(task) + velocity[1] * math.sin(task) - 0.05 * sq
    velocity = (after["x"] - before["x"]) / dt
    if name == "HalfCheetahVel":
        return -abs(velocity - task) - 0.05 * sq
    if name == "HalfCheetahDir":
        return task * velocity - 0.05 * sq
    return velocity - 1e-3 * sq  # HopperParam, WalkerParam


def step_measured(env: gym.Env, action):
    before = measure(env)
    obs, reward, _, _, info = env.step(action)
    return before, measure(env), obs, reward, info


# --- rewards ---------------------------------------------------------------------------


@pytest.mark.parametrize("action_kind", ["zero", "random"])
@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_reward_matches_hand_computation_without_noise(name, action_kind):
    env = make(name, noise=0.0)
    warm_up(env)
    u = env.unwrapped
    action = np.zeros(env.action_space.shape)
    if action_kind == "random":
        action = np.random.default_rng(2).uniform(-1, 1, env.action_space.shape)
    before, after, obs, reward, info = step_measured(env, action)
    expected = hand_reward(name, before, after, action, u.task, getattr(u, "dt", None))
    assert reward == pytest.approx(expected, abs=1e-9)
    assert info["reward_noise_free"] == pytest.approx(reward, abs=1e-12)
    if name in MUJOCO:  # the robot moves, so a wrong velocity term cannot cancel out
        assert abs(after["x"] - before["x"]) / u.dt > 1e-3
    else:
        assert np.array_equal(after["pos"], np.clip(before["pos"] + 0.1 * np.clip(action, -1, 1), -2, 2))


def test_reward_constants_are_those_of_the_docs():
    from bati.envs import ant_dir, friction_param, half_cheetah

    assert ant_dir.CONTROL_COST == 0.05
    assert half_cheetah.CONTROL_COST == 0.05
    assert friction_param.CONTROL_COST == 1e-3


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_noisy_reward_uses_task_used_and_noise_free_uses_true_task(name):
    env = make(name, noise=0.7 if name == "HalfCheetahDir" else 0.5)
    warm_up(env)
    u = env.unwrapped
    rng = np.random.default_rng(3)
    used = []
    for _ in range(10):
        action = rng.uniform(-1, 1, env.action_space.shape)
        before, after, obs, reward, info = step_measured(env, action)
        used.append(info["task_used"])
        if name in DYNAMICS:  # noise acts on the physics; the reward formula has none
            assert reward == pytest.approx(hand_reward(name, before, after, action, None, u.dt), abs=1e-9)
            assert info["reward_noise_free"] == reward
        else:
            dt = getattr(u, "dt", None)
            assert reward == pytest.approx(hand_reward(name, before, after, action, info["task_used"], dt), abs=1e-9)
            noise_free = hand_reward(name, before, after, action, u.task, dt)
            assert info["reward_noise_free"] == pytest.approx(noise_free, abs=1e-9)
    assert any(not np.array_equal(t, u.task) for t in used), "eps > 0 never perturbed the task"


# --- noise -----------------------------------------------------------------------------


def repeated_steps(env: gym.Env, trials: int = 20):
    """`trials` steps with the same action, each from the same simulator state."""
    warm_up(env)
    state = get_state(env)
    action = np.random.default_rng(4).uniform(-1, 1, env.action_space.shape)
    rewards, observations = [], []
    for _ in range(trials):
        set_state(env, state)
        obs, reward, *_ = env.step(action)
        rewards.append(reward)
        observations.append(obs)
    return np.array(rewards), np.array(observations)


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_without_noise_identical_steps_are_identical(name):
    rewards, observations = repeated_steps(make(name, noise=0.0))
    assert np.all(rewards == rewards[0])
    assert np.all(observations == observations[0])


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_with_noise_identical_steps_differ(name):
    noise = 1.0 if name == "HalfCheetahDir" else 0.5
    rewards, observations = repeated_steps(make(name, noise=noise))
    if name in DYNAMICS:
        # the friction and the action map change: the next state is stochastic
        assert np.ptp(observations, axis=0).max() > 1e-6
    else:
        # only the reward is stochastic: the next state stays deterministic
        assert np.all(observations == observations[0])
        assert np.ptp(rewards) > 1e-6


@pytest.mark.parametrize("noise", [0.3, 0.8, 1.0])
@pytest.mark.parametrize("direction", [-1.0, 1.0])
def test_half_cheetah_dir_flips_direction_with_probability_eps_over_2(noise, direction):
    env = make("HalfCheetahDir", task=direction, noise=noise).unwrapped  # no time limit
    n = 2000
    used = np.array([env.step(np.zeros(6))[4]["task_used"] for _ in range(n)])
    assert set(np.unique(used)) <= {-1.0, 1.0}
    p = noise / 2
    flipped = np.mean(used != direction)
    assert abs(flipped - p) <= 5 * math.sqrt(p * (1 - p) / n)


@pytest.mark.parametrize("noise", [0.0, 0.5])
@pytest.mark.parametrize("name", GAUSSIAN)
def test_gaussian_task_noise_has_std_eps(name, noise):
    env = make(name, noise=noise).unwrapped  # no time limit
    n = 1000
    zero = np.zeros(env.action_space.shape)
    used = np.array([env.step(zero)[4]["task_used"] for _ in range(n)])
    deviations = (used - np.asarray(env.task)).reshape(-1)  # PointGoal: both coordinates
    m = deviations.size
    assert abs(deviations.std() - noise) <= 5 * noise / math.sqrt(2 * m)
    assert abs(deviations.mean()) <= 5 * noise / math.sqrt(m)


# --- HopperParam / WalkerParam: friction and action map --------------------------------


@pytest.mark.parametrize("m", [-3.0, -1.2, 0.0, 2.5])
@pytest.mark.parametrize("name", DYNAMICS)
def test_geom_friction_is_default_times_1_5_pow_m(name, m):
    default = make(name, task=0.0).unwrapped.model.geom_friction.copy()  # fresh, never stepped
    env = make(name, task=m, noise=0.0)
    warm_up(env, steps=2)
    np.testing.assert_allclose(env.unwrapped.model.geom_friction, default * 1.5**m, rtol=1e-12)


@pytest.mark.parametrize("name", DYNAMICS)
def test_simulator_receives_the_mapped_clipped_action(name):
    env = make(name, task=2.0, noise=0.0)
    action = np.random.default_rng(5).uniform(-1, 1, env.action_space.shape)
    env.step(action)
    expected = np.clip(action_map(action, 2.0), -1, 1)
    np.testing.assert_allclose(env.unwrapped.data.ctrl, expected, rtol=1e-12)
    assert not np.allclose(expected, action)


def _same_state_pair(name, tasks):
    """Two envs with tasks `tasks` (eps = 0), moved to the same mid-episode state."""
    envs = [make(name, task=t, noise=0.0) for t in tasks]
    warm_up(envs[0])
    for _ in range(200):  # continue (zero action) until a foot touches the floor
        if envs[0].unwrapped.data.ncon > 0:
            break
        envs[0].step(np.zeros(envs[0].action_space.shape))
    state = get_state(envs[0])
    for env in envs:
        set_state(env, state)
    return envs


@pytest.mark.parametrize("name", DYNAMICS)
def test_tasks_change_the_dynamics(name):
    envs = _same_state_pair(name, (-2.0, 2.0))
    action = np.random.default_rng(6).uniform(-1, 1, envs[0].action_space.shape)
    obs = [env.step(action)[0] for env in envs]
    assert np.abs(obs[0] - obs[1]).max() > 1e-4


@pytest.mark.parametrize("name", DYNAMICS)
def test_friction_alone_changes_the_dynamics(name):
    """Same simulator action (the action maps undone), so only the friction differs."""
    tasks = (-2.0, 2.0)
    envs = _same_state_pair(name, tasks)
    assert envs[0].unwrapped.data.ncon > 0 and envs[1].unwrapped.data.ncon > 0  # touching the floor
    sim_action = np.random.default_rng(7).uniform(-0.3, 0.3, envs[0].action_space.shape)
    obs = []
    for env, m in zip(envs, tasks):
        agent_action = inverse_action_map(sim_action, m)
        assert np.all(np.abs(agent_action) <= 1)  # not clipped: the simulator gets sim_action
        obs.append(env.step(agent_action)[0])
        np.testing.assert_allclose(env.unwrapped.data.ctrl, sim_action, atol=1e-12)
    assert np.abs(obs[0] - obs[1]).max() > 1e-4
    # control: same friction and same simulator action -> same next state
    same = _same_state_pair(name, (1.0, 1.0))
    same_obs = [env.step(inverse_action_map(sim_action, 1.0))[0] for env in same]
    np.testing.assert_allclose(same_obs[0], same_obs[1], atol=1e-12)


@pytest.mark.parametrize("dim", [3, 6])
@pytest.mark.parametrize("m", [-3.0, -1.0, 0.5, 3.0])
def test_action_map_and_inverse_are_inverses(m, dim):
    actions = np.random.default_rng(8).uniform(-1, 1, (50, dim))
    mapped = action_map(actions, m)
    np.testing.assert_allclose(inverse_action_map(mapped, m), actions, atol=1e-12)
    np.testing.assert_allclose(action_map(inverse_action_map(actions, m), m), actions, atol=1e-12)
    assert np.abs(mapped - actions).max() > 0.05  # not the identity for m != 0
    # rotation part preserves norms; bias is 0.1 * m / 3 on every dimension
    bias = 0.1 * m / 3
    np.testing.assert_allclose(np.linalg.norm(mapped - bias, axis=1), np.linalg.norm(actions, axis=1))
    np.testing.assert_allclose(action_map(np.zeros(dim), m), np.full(dim, bias), atol=1e-15)


def test_action_map_rotation_angle_is_pi_m_over_6():
    m = 1.7
    theta = math.pi * m / 6  # version 2: up to pi/2 at m = +-3
    mapped = action_map(np.array([1.0, 0.0]), m) - 0.1 * m / 3  # one Givens rotation for 2-D
    np.testing.assert_allclose(mapped, [math.cos(theta), math.sin(theta)], atol=1e-15)
    np.testing.assert_allclose(action_map(np.array([0.3, -0.2, 0.9]), 0.0), [0.3, -0.2, 0.9])


# --- distances and sampling (App. C.2) -------------------------------------------------

DISTANCES = [
    ("AntDir", 0.1, 2 * math.pi - 0.1, 0.2),
    ("AntDir", 0.0, math.pi, math.pi),
    ("AntDir", 1.0, 2.5, 1.5),
    ("AntDir", 0.5, 0.5 + 1.5 * math.pi, 0.5 * math.pi),
    ("HalfCheetahDir", 1.0, 1.0, 0.0),
    ("HalfCheetahDir", -1.0, 1.0, 1.0),
    ("HalfCheetahVel", 0.25, 1.75, 1.5),
    ("HopperParam", -3.0, 2.0, 5.0),
    ("WalkerParam", 1.5, -0.5, 2.0),
    ("PointGoal", [1.0, 0.0], [0.0, 1.0], math.sqrt(2)),
    ("PointGoal", [1.0, 0.0], [-1.0, 0.0], 2.0),
]


@pytest.mark.parametrize("name,a,b,expected", DISTANCES)
def test_distance(name, a, b, expected):
    family = get_family(name)
    assert family.distance(a, b) == pytest.approx(expected, abs=1e-12)
    assert family.distance(b, a) == pytest.approx(expected, abs=1e-12)
    assert family.distance(a, a) == 0.0


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_distance_matrix(name):
    family = get_family(name)
    a, b = family.sample_tasks(3, 0), family.sample_tasks(4, 1)
    matrix = family.distance_matrix(a, b)
    assert matrix.shape == (3, 4)
    assert matrix[2, 1] == family.distance(a[2], b[1])


IN_SPACE = {
    "AntDir": lambda t: 0 <= t < 2 * math.pi,
    "HalfCheetahVel": lambda t: 0 <= t <= 2,
    "HalfCheetahDir": lambda t: t in (-1.0, 1.0),
    "HopperParam": lambda t: -3 <= t <= 3,
    "WalkerParam": lambda t: -3 <= t <= 3,
    "PointGoal": lambda t: len(t) == 2 and abs(math.hypot(*t) - 1) < 1e-9 and t[1] >= 0,
}


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_sample_tasks_reproducible_and_in_task_space(name):
    family = get_family(name)
    tasks = family.sample_tasks(50, seed=3)
    assert len(tasks) == 50
    assert tasks == family.sample_tasks(50, seed=3)
    assert tasks == family.sample_tasks(50, seed=np.random.default_rng(3))
    assert tasks != family.sample_tasks(50, seed=4)
    assert all(IN_SPACE[name](t) for t in tasks)
    assert len({str(t) for t in tasks}) == (2 if name == "HalfCheetahDir" else 50)  # spread out
    assert family.task_to_array(tasks[0]).shape == (family.task_dim,)


# --- bad input -------------------------------------------------------------------------


def test_unknown_family():
    with pytest.raises(TaskError, match="'NoSuchFamily'") as err:
        get_family("NoSuchFamily")
    assert all(name in str(err.value) for name in FAMILY_NAMES)
    with pytest.raises(TaskError, match="NoSuchFamily"):
        make_env("NoSuchFamily", 1.0)


BAD_TASKS = [(name, task) for name, spec in SPECS.items() for task in spec.bad_tasks]


@pytest.mark.parametrize("name,task", BAD_TASKS)
def test_task_outside_task_space(name, task):
    family = get_family(name)
    for call in (
        lambda: family.validate_task(task),
        lambda: family.make_env(task),
        lambda: gym.make(f"bati/{name}-v0", task=task, noise=0.0),
    ):
        with pytest.raises(TaskError) as err:
            call()
        message = str(err.value)
        assert name in message and SPECS[name].range_text in message
        assert repr(task if isinstance(task, list) else float(task)) in message


@pytest.mark.parametrize("name,noise", [(n, -0.1) for n in FAMILY_NAMES] + [("HalfCheetahDir", 1.2)])
def test_bad_noise(name, noise):
    family = get_family(name)
    upper = "1" if name == "HalfCheetahDir" else "inf"
    for call in (
        lambda: family.validate_noise(noise),
        lambda: gym.make(f"bati/{name}-v0", task=SPECS[name].task, noise=noise),
    ):
        with pytest.raises(TaskError) as err:
            call()
        assert f"eps={noise:g}" in str(err.value) and f"[0, {upper}]" in str(err.value)


def test_noise_bounds_are_inclusive():
    assert get_family("HalfCheetahDir").validate_noise(1.0) == 1.0
    assert get_family("AntDir").validate_noise(0.0) == 0.0
    assert get_family("AntDir").validate_noise(5.0) == 5.0
    with pytest.raises(TaskError):
        get_family("AntDir").validate_noise(math.nan)


# --- gymnasium interface ---------------------------------------------------------------


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_gymnasium_make_episode_and_spaces(name):
    spec, family = SPECS[name], get_family(name)
    env = gym.make(f"bati/{name}-v0", task=spec.task, noise=family.default_noise)
    assert env.unwrapped.task == spec.task and env.unwrapped.noise == family.default_noise
    assert gym.make(f"bati/{name}-v0", task=spec.task).unwrapped.noise == family.default_noise
    assert env.observation_space.shape == (spec.obs_dim,)
    assert env.action_space.shape == (spec.act_dim,)
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (spec.obs_dim,)
    env.action_space.seed(0)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        steps += 1
        assert obs.shape == (spec.obs_dim,) and np.isfinite(reward)
        assert "reward_noise_free" in info and "task_used" in info
    assert (steps, terminated, truncated) == (EPISODE_LENGTH, False, True) == (200, False, True)


@pytest.mark.parametrize("name", FAMILY_NAMES)
def test_actions_are_clipped_to_unit_box(name):
    env = make(name, noise=0.0)
    warm_up(env)
    state = get_state(env)
    action = np.random.default_rng(9).uniform(-1, 1, env.action_space.shape)
    action[0] = 1.0
    big = action.copy()
    big[0] = 5.0
    results = []
    for a in (action, big):
        set_state(env, state)
        obs, reward, *_ = env.step(a)
        results.append((obs, reward))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    assert results[0][1] == results[1][1]


def test_a_broken_family_plugin_is_named_and_the_other_families_stay(monkeypatch):
    import importlib.metadata

    import bati.envs as envs_module
    from bati.errors import BatiWarning

    class Broken:
        name, value = "broken", "brokenpkg.families:register"

        def load(self):
            raise ImportError("No module named 'brokenpkg'")

    monkeypatch.setattr(envs_module, "_plugins_loaded", False)
    monkeypatch.setattr(importlib.metadata, "entry_points", lambda group: [Broken()])
    with pytest.warns(BatiWarning, match="entry point 'broken' .brokenpkg.families:register. failed and its families "
                                         "are left out: ImportError: No module named 'brokenpkg'"):
        names = envs_module.family_names()
    assert "HalfCheetahDir" in names and "PointGoal" in names
