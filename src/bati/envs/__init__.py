"""The paper's task families, registered with gymnasium as ``bati/<Name>-v0``.

>>> family = get_family("HalfCheetahVel")
>>> tasks = family.sample_tasks(20, seed=0)
>>> env = gymnasium.make("bati/HalfCheetahVel-v0", task=tasks[0], noise=0.5)
"""

from __future__ import annotations

import warnings

import gymnasium as gym

from bati.envs.base import (EPISODE_LENGTH, FamilyRecord, Task, TaskEnvMixin, TaskError, TaskFamily, TaskSplit,
                             scalar_task)
from bati.errors import BatiError, BatiWarning

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
"""The built-in families (`family_names()` adds the ones registered with `register_family`)."""
MUJOCO_FAMILIES = ("AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam")
"""The paper's five MuJoCo families (Table 4's), in the order its tables and ours show them."""
_REGISTERED: dict[str, type[TaskFamily]] = {}
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


PLUGIN_GROUP = "bati.families"
"""Entry-point group of installed packages' families: each entry point is a function that calls
`register_family` (and `bati.experts.register_expert`); loaded the first time a name is not found."""
_plugins_loaded = False


def _load_plugins() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    from importlib.metadata import entry_points

    for entry in entry_points(group=PLUGIN_GROUP):
        try:
            entry.load()()
        except Exception as err:  # one broken package must not hide every other family
            warnings.warn(f"the {PLUGIN_GROUP} entry point {entry.name!r} ({entry.value}) failed and its families are "
                          f"left out: {type(err).__name__}: {err}", BatiWarning, stacklevel=2)


def family_names() -> tuple[str, ...]:
    """Every family `get_family` knows: the built-in ones, then those registered (in this process or by an
    installed package's `bati.families` entry point)."""
    _load_plugins()
    return FAMILY_NAMES + tuple(n for n in _REGISTERED if n not in _FAMILIES)


def check_family_name(name: str) -> None:
    """TaskError (naming every family) unless a family is called `name`; nothing is imported or built."""
    if name not in _FAMILIES and name not in _REGISTERED:
        _load_plugins()
    if name not in _FAMILIES and name not in _REGISTERED:
        raise TaskError(f"unknown task family {name!r}; choose one of: {', '.join(family_names())}")


def register_family(family_class: type[TaskFamily], env_entry_point) -> None:
    """Make a family of your own known by name in this process (docs/extending.md): `get_family(name)`,
    every `bati` API that takes a family name, and ``gymnasium.make("bati/<name>-v0", task=..., noise=...)``
    (`env_entry_point`: the env class or "module:Class", kept as that string because the datasets'
    Minari metadata records it; its episodes are cut at the record's `episode_length`). Registering the
    same class again is a no-op."""
    record = getattr(family_class, "record", None)
    if not isinstance(record, FamilyRecord):
        raise TypeError(f"{family_class.__name__} has no FamilyRecord `record`: see docs/extending.md")
    name = record.name
    if name in _FAMILIES or _REGISTERED.get(name, family_class) is not family_class:
        raise ValueError(f"a family called {name!r} already exists; give yours another name")
    if _REGISTERED.get(name) is family_class:
        return
    if isinstance(env_entry_point, type):
        env_entry_point = f"{env_entry_point.__module__}:{env_entry_point.__qualname__}"
    if not isinstance(env_entry_point, str):
        raise TypeError(f"env_entry_point must be the env class or 'module:Class', got {env_entry_point!r}")
    env_id = f"bati/{name}-v0"
    if env_id not in gym.registry:
        gym.register(id=env_id, entry_point=env_entry_point, max_episode_steps=record.episode_length)
    try:
        check_spaces(family_class(), env_id)
    except Exception:
        gym.registry.pop(env_id, None)  # a family whose env breaks its own spaces is not registered
        raise
    _REGISTERED[name] = family_class


def check_spaces(family: TaskFamily, env_id: str) -> None:
    """One reset and one step of the family's env on one of its tasks: its observations must have the
    observation space's shape and its action space must be a Box (every method and the SAC expert size their
    networks and buffers from the spaces). ValueError naming the env and both shapes otherwise."""
    import numpy as np

    env = gym.make(env_id, task=family.sample_tasks(1, seed=0)[0], noise=0.0, disable_env_checker=True)
    try:
        if not isinstance(env.action_space, gym.spaces.Box):
            raise ValueError(f"{env_id}: its action_space is {env.action_space}, not a gymnasium.spaces.Box")
        expected = env.observation_space.shape
        obs, _ = env.reset(seed=0)
        after_step = env.step(env.action_space.sample())[0]
        for when, observation in (("reset", obs), ("step", after_step)):
            if np.shape(observation) != expected:
                raise ValueError(f"{env_id}: {when}() returns observations of shape {np.shape(observation)} but its "
                                 f"observation_space has shape {expected}; make them agree (docs/extending.md)")
    finally:
        env.close()


def get_family(name: str) -> TaskFamily:
    """The task family called `name` (one of `family_names()`)."""
    import importlib

    check_family_name(name)
    if name in _REGISTERED:
        return _REGISTERED[name]()
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


def as_family(family: str | TaskFamily) -> TaskFamily:
    """`family` itself when it is a TaskFamily already (resolved once by an entry point), else `get_family`."""
    return family if isinstance(family, TaskFamily) else get_family(family)


def families_with_extras(names: tuple[str, ...] | None = None) -> tuple[list[TaskFamily], list[tuple[str, str]]]:
    """The families `names` (default: all) that can be built here, and (name, install hint) for those whose
    optional extra is missing (`bati envs`)."""
    families, unavailable = [], []
    for name in names or family_names():
        try:
            families.append(get_family(name))
        except FamilyUnavailable as err:
            unavailable.append((name, str(err)))
    return families, unavailable


def random_episode(family: TaskFamily, task: Task, noise: float | None = None, seed: int = 0) -> dict:
    """One episode of uniformly random actions in one task (`bati envs --task`): its return, length, the
    eps it ran with and its wall time in ms."""
    import time

    env = family.make_env(task, noise)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    start, total, steps, done = time.perf_counter(), 0.0, 0, False
    while not done:
        _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        total, steps, done = total + float(reward), steps + 1, terminated or truncated
    eps = env.unwrapped.noise
    env.close()
    return {"return": total, "steps": steps, "noise": eps, "ms": 1e3 * (time.perf_counter() - start)}


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
    # every built-in family's record says episode_length = EPISODE_LENGTH (tests/test_config.py checks it)
    for name, (module, _, env_class) in _FAMILIES.items():
        env_id = f"bati/{name}-v0"
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"{module}:{env_class}", max_episode_steps=EPISODE_LENGTH)


_register()
_quiet_mujoco_deprecation()

__all__ = ["EPISODE_LENGTH", "FAMILY_NAMES", "FamilyRecord", "FamilyUnavailable", "Task", "TaskEnvMixin", "TaskError",
           "TaskFamily", "TaskSplit", "as_family", "check_family_name", "families_with_extras", "family_available",
           "family_names", "get_family", "make_env", "random_episode", "register_family", "scalar_task"]
