"""PointGoal: a fast 2-D point robot that must reach a goal on the upper half unit circle.

The family our tests and quick demos lean on: pure numpy, one 200-step episode in a few
milliseconds. Reward = -||position - goal_t||, with goal_t = goal + N(0, eps^2 I) each step.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np

from bati.envs.base import FamilyRecord, TaskEnvMixin, TaskError, TaskFamily

STEP_SIZE = 0.1  # position change per step at full action
POSITION_BOUND = 2.0


class PointGoalFamily(TaskFamily):
    record = FamilyRecord(
        name="PointGoal",
        task_space="a goal [cos(angle), sin(angle)], angle in [0, pi]",
        task_dim=2,
        default_noise=1.0,
        noise_meaning="std of the Gaussian noise added to the goal (both coordinates) at every step",
        parameter_range=(0.0, math.pi),  # the goal's angle
        paper_episodes=500,  # ours (not in the paper): AntDir's size
        expert_steps=20_000,
        per_task_expert_steps=20_000,  # shipped: one program of 20 tasks, ~40 min on one busy CPU core
    )

    def task_from_parameter(self, value):
        return [float(np.cos(value)), float(np.sin(value))]

    def _sample(self, n, rng):
        angles = rng.uniform(0.0, math.pi, size=n)
        return [[float(np.cos(a)), float(np.sin(a))] for a in angles]

    def _check(self, task):
        goal = np.asarray(task, dtype=np.float64)
        if goal.shape != (2,):
            raise TaskError(f"{self.name}: task {task!r} must be a 2-vector goal, {self.task_space}")
        if not np.all(np.isfinite(goal)) or abs(np.linalg.norm(goal) - 1.0) > 1e-5 or goal[1] < -1e-6:
            raise TaskError(f"{self.name}: task {task!r} is outside the task space: {self.task_space}")
        return [float(goal[0]), float(goal[1])]

    def distance(self, a, b):
        return float(np.linalg.norm(np.asarray(self._check(a)) - np.asarray(self._check(b))))


class PointGoalEnv(TaskEnvMixin, gym.Env):
    """Position in [-2, 2]^2 starting at the origin; the action moves it by 0.1 * action."""

    metadata = {"render_modes": []}
    family = PointGoalFamily()

    def __init__(self, task, noise: float | None = None):
        self._set_task(task, noise)
        self.observation_space = gym.spaces.Box(-POSITION_BOUND, POSITION_BOUND, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._position = np.zeros(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._position = np.zeros(2)
        return self._position.copy(), {}

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self._position = np.clip(self._position + STEP_SIZE * action, -POSITION_BOUND, POSITION_BOUND)
        goal = np.asarray(self.task)
        noisy_goal = goal + self.noise * self.np_random.standard_normal(2)
        reward = -float(np.linalg.norm(self._position - noisy_goal))
        noise_free = -float(np.linalg.norm(self._position - goal))
        info = {"reward_noise_free": noise_free, "task_used": noisy_goal.tolist()}
        return self._position.copy(), reward, False, False, info
