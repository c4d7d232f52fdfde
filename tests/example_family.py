"""A task family defined outside bati's source, exactly as docs/extending.md builds it.

LineGoal: a point on a line must stay at a goal g in [-1, 1]; the reward is -|x - g_t| with a
per-step noisy goal g_t = g + N(0, eps^2). Its expert is scripted (head for the goal), so no SAC
needs training. tests/test_extending.py runs it through collect -> train -> evaluate.
"""

from __future__ import annotations

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from bati.envs import FamilyRecord, TaskEnvMixin, TaskFamily, register_family, scalar_task
from bati.experts import Expert, register_expert

STEP_SIZE = 0.1


class LineGoalFamily(TaskFamily):
    record = FamilyRecord(
        name="LineGoal",
        task_space="a goal position in [-1, 1]",
        task_dim=1,
        default_noise=0.5,
        noise_meaning="std of the Gaussian noise added to the goal at every step",
        parameter_range=(-1.0, 1.0),
        episode_length=50,
        context_length=50,
        latent_dim=2,
        net_dims=(32, 32),
        expert_steps=20_000,
    )

    def _sample(self, n, rng):
        return [float(x) for x in rng.uniform(-1.0, 1.0, size=n)]

    def _check(self, task):
        return scalar_task(self, task, -1.0, 1.0)

    def distance(self, a, b):
        return abs(self._check(a) - self._check(b))


class LineGoalEnv(TaskEnvMixin, gym.Env):
    metadata = {"render_modes": []}
    family = LineGoalFamily()

    def __init__(self, task, noise=None):
        self._set_task(task, noise)
        self.observation_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self._x = np.zeros(1)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._x = np.zeros(1)
        return self._x.copy(), {}

    def step(self, action):
        self._x = np.clip(self._x + STEP_SIZE * np.clip(np.asarray(action, np.float64), -1.0, 1.0), -2.0, 2.0)
        goal = self.task + self.noise * self.np_random.standard_normal()
        info = {"reward_noise_free": -float(abs(self._x[0] - self.task))}
        return self._x.copy(), -float(abs(self._x[0] - goal)), False, False, info


class LineGoalExpert(Expert):
    """Scripted: move toward the goal at full speed; Gaussian exploration (std 0.3) when stochastic."""

    def __init__(self, family: LineGoalFamily):
        self.family = family
        self.meta = {"family": "LineGoal", "kind": "scripted"}

    def mean_action(self, obs, task_arrays):
        return jnp.clip((task_arrays - obs) / STEP_SIZE, -1.0, 1.0)

    def act_from_arrays(self, obs, task_arrays, deterministic, key):
        mean = np.asarray(self.mean_action(jnp.asarray(obs), jnp.asarray(task_arrays, jnp.float32)))
        if deterministic:
            return mean
        return np.clip(mean + 0.3 * np.asarray(jax.random.normal(key, mean.shape)), -1.0, 1.0).astype(np.float32)


def register() -> None:
    register_family(LineGoalFamily, LineGoalEnv)
    register_expert("LineGoal", LineGoalExpert)
