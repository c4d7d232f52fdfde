"""The paper's task families, registered with gymnasium as ``bati/<Name>-v0``.

>>> family = get_family("HalfCheetahVel")
>>> tasks = family.sample_tasks(20, seed=0)
>>> env = gymnasium.make("bati/HalfCheetahVel-v0", task=tasks[0], noise=0.5)
"""

from __future__ import annotations

import gymnasium as gym

from bati.envs.base import EPISODE_LENGTH, Task, TaskError, TaskFamily, TaskSplit
from bati.errors import BatiError

# family name -> (module, family class, env class); modules are imported lazily so that
# `import bati.envs` stays cheap and PointGoal works without loading MuJoCo.
_FAMILIES = {
    "AntDir": ("bati.envs.ant_dir", "AntDirFamily", "AntDirEnv"),
    "HalfCheetahVel": ("bati.envs.half_cheetah", "HalfCheetahVelFamily", "HalfCheetahVelEnv"),
    "HalfCheetahDir": ("bati.envs.half_cheetah", "HalfCheetahDirFamily", "HalfCheetahDirEnv"),
    "HopperParam": ("bati.envs.hopper_param", "HopperParamFamily", "HopperParamEnv"),
    "WalkerParam": ("bati.envs.walker_param", "WalkerParamFamily", "WalkerParamEnv"),
    "PointGoal": ("bati.envs.point", "PointGoalFamily", "PointGoalEnv"),
    "KuhnPoker": ("bati.envs.kuhn", "KuhnPokerFamily", "KuhnPokerEnv"),
}
FAMILY_NAMES = tuple(_FAMILIES)
# families that need an optional extra: name -> (module it imports, extra, what it is, its pip package)
_EXTRAS = {"KuhnPoker": ("pyspiel", "games", "OpenSpiel", "open_spiel")}


class FamilyUnavailable(BatiError, ImportError):
    """A family whose optional dependency is not installed (the message says how to install it)."""


def family_available(name: str) -> bool:
    """Whether `get_family(name)` works here (False for a family whose extra is missing)."""
    try:
        get_family(name)
    except FamilyUnavailable:
        return False
    return True


def _check_name(name: str) -> None:
    if name not in _FAMILIES:
        raise TaskError(f"unknown task family {name!r}; choose one of: {', '.join(FAMILY_NAMES)}")


def get_family(name: str) -> TaskFamily:
    """The task family called `name` (one of FAMILY_NAMES)."""
    import importlib

    _check_name(name)
    module, family_class, _ = _FAMILIES[name]
    try:
        loaded = importlib.import_module(module)
    except ImportError as err:
        if name in _EXTRAS and err.name == _EXTRAS[name][0]:
            _, extra, what, package = _EXTRAS[name]
            raise FamilyUnavailable(f"{name} needs {what}, which is not installed; install it with "
                                    f"`pip install 'bati[{extra}]'` (or `pip install {package}`)") from err
        raise
    return getattr(loaded, family_class)()


def make_env(name: str, task: Task, noise: float | None = None, **kwargs) -> gym.Env:
    """Shortcut for ``get_family(name).make_env(task, noise)``."""
    return get_family(name).make_env(task, noise, **kwargs)


def _quiet_mujoco_deprecation() -> None:
    """gymnasium's HalfCheetah XML uses `settotalmass`, which MuJoCo >= 3.3 warns about on every
    env construction (to stdout). Drop that one message; route other MuJoCo warnings to Python's."""
    try:
        import mujoco
    except ImportError:
        return

    def on_warning(message: str) -> None:
        if "settotalmass" not in message:
            import warnings

            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    if hasattr(mujoco, "set_mju_user_warning"):
        mujoco.set_mju_user_warning(on_warning)


def _register() -> None:
    for name, (module, _, env_class) in _FAMILIES.items():
        env_id = f"bati/{name}-v0"
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{module}:{env_class}", max_episode_steps=EPISODE_LENGTH)


_register()
_quiet_mujoco_deprecation()

__all__ = ["EPISODE_LENGTH", "FAMILY_NAMES", "FamilyUnavailable", "Task", "TaskError", "TaskFamily", "TaskSplit",
           "family_available", "get_family", "make_env"]
