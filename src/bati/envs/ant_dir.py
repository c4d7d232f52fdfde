"""AntDir: the ant must run in a goal direction (App. C.1).

Reward = torso planar velocity (displacement / dt) projected on the per-step goal direction
M_t = M* + N(0, eps^2), minus a control cost 0.05 ||a||^2. No contact cost, no survival
bonus, no early termination: every episode lasts 200 steps. Observations exclude contact
forces (27-D).
"""

from __future__ import annotations

import math

import numpy as np
from gymnasium.envs.mujoco.ant_v5 import AntEnv

from bati.envs.base import FamilyRecord, TaskEnvMixin, TaskFamily, scalar_task

CONTROL_COST = 0.05


class AntDirFamily(TaskFamily):
    record = FamilyRecord(
        name="AntDir",
        task_space="a goal direction in radians, in [0, 2*pi)",
        task_dim=2,  # the angle as (cos, sin): seamless at the 2*pi wrap-around
        default_noise=1.0,
        noise_meaning="std (radians) of the Gaussian noise added to the goal direction at every step",
        parameter_range=(0.0, 2 * math.pi),
        paper_episodes=500,  # Table 3: 1e5 transitions per task
        expert_steps=600_000,
        per_task_expert_steps=200_000,  # shipped: 4 parts of 5 tasks, ~70 min each on 2 CPU cores
        club_weight=5.0,
    )

    def _sample(self, n, rng):
        return [float(x) for x in rng.uniform(0.0, 2 * math.pi, size=n)]

    def _check(self, task):
        return scalar_task(self, task, 0.0, 2 * math.pi, closed_high=False)

    def distance(self, a, b):
        lo, hi = sorted((self._check(a), self._check(b)))
        return min(hi - lo, lo + 2 * math.pi - hi)

    def task_to_array(self, task):
        angle = self.validate_task(task)
        return np.array([math.cos(angle), math.sin(angle)], dtype=np.float32)


class AntDirEnv(TaskEnvMixin, AntEnv):
    family = AntDirFamily()

    def __init__(self, task, noise: float | None = None, **kwargs):
        self._set_task(task, noise)
        super().__init__(
            include_cfrc_ext_in_observation=False,
            terminate_when_unhealthy=False,
            **kwargs,
        )

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        xy_before = self.data.body(self._main_body).xpos[:2].copy()
        self.do_simulation(action, self.frame_skip)
        velocity = (self.data.body(self._main_body).xpos[:2] - xy_before) / self.dt
        goal_t = self.task + self.noise * self.np_random.standard_normal()
        control_cost = CONTROL_COST * float(np.sum(action**2))
        reward = float(velocity @ [math.cos(goal_t), math.sin(goal_t)]) - control_cost
        noise_free = float(velocity @ [math.cos(self.task), math.sin(self.task)]) - control_cost
        info = {"reward_noise_free": noise_free, "task_used": goal_t, "velocity": velocity.copy()}
        return self._get_obs(), reward, False, False, info
