"""HopperParam and WalkerParam: tasks differ in the physics P_M, through a log-friction m.

Per step, m_t = m + N(0, eps^2) sets
- the friction of every geom: friction = default_friction * 1.5 ** m_t (rand_param_envs' scale);
- a task-dependent invertible affine action map applied before the simulator:
  a_sim = clip(R(theta(m_t)) a + b(m_t), -1, 1), where R(theta) is the product of Givens
  rotations by theta over consecutive action-dimension pairs (0,1), (1,2), ..., theta(m) =
  pi * m / 6 in [-pi/2, pi/2], and b(m) = 0.1 * m / 3 on every dimension.
Reward = forward velocity (x displacement / dt) - 0.001 ||a||^2; no early termination.
See docs/environments.md for why.

Version 2 (FamilyRecord.version): the rotation reaches pi/2 (version 1: pi/4, theta = pi m / 12). With
pi/4 one behaviour served every task (the expert conditioned on a single fixed m earned 110% of the
per-task experts' HopperParam return, 97% on WalkerParam), so the families did not test task inference;
at pi/2 the extremes swap the roles of adjacent joints and the best fixed-task expert earns 77% / 82%.
"""

from __future__ import annotations

import math

import numpy as np

from bati.envs.base import FamilyRecord, TaskEnvMixin, TaskFamily, scalar_task

FRICTION_BASE = 1.5
CONTROL_COST = 1e-3
MAX_ROTATION = math.pi / 2  # version 2 (version 1: pi / 4)
MAX_BIAS = 0.1
LOG_FRICTION_RANGE = 3.0


def action_map(action: np.ndarray, log_friction: float) -> np.ndarray:
    """The invertible part of the task's action map: R(theta(m)) a + b(m) (before clipping)."""
    out = np.array(action, dtype=np.float64)
    theta = MAX_ROTATION * log_friction / LOG_FRICTION_RANGE
    c, s = math.cos(theta), math.sin(theta)
    for i in range(out.shape[-1] - 1):
        x, y = out[..., i].copy(), out[..., i + 1].copy()
        out[..., i], out[..., i + 1] = c * x - s * y, s * x + c * y
    return out + MAX_BIAS * log_friction / LOG_FRICTION_RANGE


def inverse_action_map(mapped: np.ndarray, log_friction: float) -> np.ndarray:
    """Inverse of `action_map` (undo the bias, then the rotations in reverse order)."""
    out = np.array(mapped, dtype=np.float64) - MAX_BIAS * log_friction / LOG_FRICTION_RANGE
    theta = MAX_ROTATION * log_friction / LOG_FRICTION_RANGE
    c, s = math.cos(theta), math.sin(theta)
    for i in reversed(range(out.shape[-1] - 1)):
        x, y = out[..., i].copy(), out[..., i + 1].copy()
        out[..., i], out[..., i + 1] = c * x + s * y, -s * x + c * y
    return out


def log_friction_record(name: str, expert_steps: int) -> FamilyRecord:
    """The record HopperParam and WalkerParam share (Table 3's dynamics families)."""
    return FamilyRecord(
        name=name,
        task_space="a log-friction coefficient m in [-3, 3] (friction scale 1.5**m)",
        task_dim=1,
        default_noise=1.0,
        noise_meaning="std of the Gaussian noise added to the log-friction at every step (friction and action map)",
        kind="dynamics",
        parameter_range=(-LOG_FRICTION_RANGE, LOG_FRICTION_RANGE),
        latent_dim=40,
        net_dims=(128, 128),
        paper_episodes=1500,  # Table 3: 3e5 transitions per task
        expert_steps=expert_steps,
        per_task_expert_steps=200_000,  # HopperParam's shipped: 2 parts of 10 tasks, ~64 min each on one core
        unicorn_weight=1.5,
        club_weight=2.5,
        version=2,  # the action map's rotation reaches pi/2 (version 1: pi/4)
    )


class LogFrictionFamily(TaskFamily):

    def _sample(self, n, rng):
        return [float(x) for x in rng.uniform(-LOG_FRICTION_RANGE, LOG_FRICTION_RANGE, size=n)]

    def _check(self, task):
        return scalar_task(self, task, -LOG_FRICTION_RANGE, LOG_FRICTION_RANGE)

    def distance(self, a, b):
        return abs(self._check(a) - self._check(b))


class LogFrictionEnvMixin(TaskEnvMixin):
    """Step logic shared by HopperParam and WalkerParam (mixed into gymnasium's v5 envs)."""

    def __init__(self, task, noise: float | None = None, **kwargs):
        self._set_task(task, noise)
        super().__init__(terminate_when_unhealthy=False, **kwargs)
        self._default_friction = self.model.geom_friction.copy()

    def set_log_friction(self, log_friction: float) -> None:
        self.model.geom_friction[:] = self._default_friction * FRICTION_BASE**log_friction

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        log_friction_t = self.task + self.noise * self.np_random.standard_normal()
        self.set_log_friction(log_friction_t)
        sim_action = np.clip(action_map(action, log_friction_t), -1.0, 1.0)
        x_before = self.data.qpos[0]
        self.do_simulation(sim_action, self.frame_skip)
        velocity = (self.data.qpos[0] - x_before) / self.dt
        reward = velocity - CONTROL_COST * float(np.sum(action**2))
        # The noise acts on the dynamics: the reward formula itself has no noise term.
        info = {"reward_noise_free": reward, "task_used": log_friction_t, "x_velocity": velocity}
        return self._get_obs(), reward, False, False, info
