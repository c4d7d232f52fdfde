"""HopperParam: the hopper moves forward under a task-specific friction and action map."""

from gymnasium.envs.mujoco.hopper_v5 import HopperEnv

from bati.envs.friction_param import LogFrictionEnvMixin, LogFrictionFamily, log_friction_record


class HopperParamFamily(LogFrictionFamily):
    record = log_friction_record("HopperParam", expert_steps=400_000)


class HopperParamEnv(LogFrictionEnvMixin, HopperEnv):
    family = HopperParamFamily()
