"""HopperParam: the hopper moves forward under a task-specific friction and action map."""

from gymnasium.envs.mujoco.hopper_v5 import HopperEnv

from bati.envs.friction_param import LogFrictionEnvMixin, LogFrictionFamily


class HopperParamFamily(LogFrictionFamily):
    name = "HopperParam"


class HopperParamEnv(LogFrictionEnvMixin, HopperEnv):
    family = HopperParamFamily()
