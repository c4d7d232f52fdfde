"""WalkerParam: the 2-D walker moves forward under a task-specific friction and action map."""

from gymnasium.envs.mujoco.walker2d_v5 import Walker2dEnv

from bati.envs.friction_param import LogFrictionEnvMixin, LogFrictionFamily, log_friction_record


class WalkerParamFamily(LogFrictionFamily):
    record = log_friction_record("WalkerParam", expert_steps=600_000)


class WalkerParamEnv(LogFrictionEnvMixin, Walker2dEnv):
    family = WalkerParamFamily()
