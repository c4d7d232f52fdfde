"""HalfCheetahVel and HalfCheetahDir: the cheetah runs at a target velocity / in a direction.

Both use the forward velocity (x displacement / dt) and a control cost 0.05 ||a||^2 and never
terminate early.
- HalfCheetahVel: reward = -|v - v_t| - control cost, v_t = v* + N(0, eps^2) each step.
- HalfCheetahDir: reward = d_t * v - control cost, where d_t is the true direction with
  probability 1 - eps and a uniformly random direction in {-1, +1} with probability eps.
"""

from __future__ import annotations

import numpy as np
from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv

from bati.envs.base import FamilyRecord, TaskEnvMixin, TaskError, TaskFamily, scalar_task

CONTROL_COST = 0.05


class HalfCheetahVelFamily(TaskFamily):
    record = FamilyRecord(
        name="HalfCheetahVel",
        task_space="a target velocity in [0, 2]",
        task_dim=1,
        default_noise=1.0,
        noise_meaning="std of the Gaussian noise added to the target velocity at every step",
        parameter_range=(0.0, 2.0),
        paper_episodes=1000,  # Table 3: 2e5 transitions per task
        expert_steps=300_000,
        per_task_expert_steps=100_000,  # shipped: 2 parts of 10 tasks, ~30 min each on one CPU core
        entropy_weight=2.5,  # ER-TRL's cheetah-vel setting
    )

    def _sample(self, n, rng):
        return [float(x) for x in rng.uniform(0.0, 2.0, size=n)]

    def _check(self, task):
        return scalar_task(self, task, 0.0, 2.0)

    def distance(self, a, b):
        return abs(self._check(a) - self._check(b))


class HalfCheetahDirFamily(TaskFamily):
    record = FamilyRecord(
        name="HalfCheetahDir",
        task_space="a direction in {-1.0 (left), +1.0 (right)}",
        task_dim=1,
        default_noise=0.8,
        noise_meaning="probability that a step's reward uses a uniformly random direction instead of the true one",
        max_noise=1.0,
        paper_episodes=1000,  # Table 3: 2e5 transitions per task
        expert_steps=200_000,
        per_task_expert_steps=200_000,  # shipped: 2 parts of 10 tasks, ~195 min each on one CPU core; flat at the end
        entropy_weight=2.5,  # ours: ER-TRL has no cheetah-dir setting; its cheetah-vel one
    )

    def _sample(self, n, rng):
        return [float(x) for x in rng.choice([-1.0, 1.0], size=n)]

    def _check(self, task):
        value = scalar_task(self, task, -1.0, 1.0)
        if value not in (-1.0, 1.0):
            raise TaskError(f"{self.name}: task {value!r} is outside the task space {self.task_space}")
        return value

    def distance(self, a, b):
        return float(self._check(a) != self._check(b))


class _CheetahTaskEnv(TaskEnvMixin, HalfCheetahEnv):
    def __init__(self, task, noise: float | None = None, **kwargs):
        self._set_task(task, noise)
        super().__init__(**kwargs)

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        x_before = self.data.qpos[0]
        self.do_simulation(action, self.frame_skip)
        velocity = (self.data.qpos[0] - x_before) / self.dt
        control_cost = CONTROL_COST * float(np.sum(action**2))
        task_t = self._noisy_task()
        reward = self._task_reward(velocity, task_t) - control_cost
        noise_free = self._task_reward(velocity, self.task) - control_cost
        info = {"reward_noise_free": noise_free, "task_used": task_t, "x_velocity": velocity}
        return self._get_obs(), reward, False, False, info


class HalfCheetahVelEnv(_CheetahTaskEnv):
    family = HalfCheetahVelFamily()

    def _noisy_task(self):
        return self.task + self.noise * self.np_random.standard_normal()

    @staticmethod
    def _task_reward(velocity, target_velocity):
        return -abs(velocity - target_velocity)


class HalfCheetahDirEnv(_CheetahTaskEnv):
    family = HalfCheetahDirFamily()

    def _noisy_task(self):
        if self.np_random.random() < self.noise:
            return float(self.np_random.choice([-1.0, 1.0]))
        return self.task

    @staticmethod
    def _task_reward(velocity, direction):
        return direction * velocity
