"""Shipped experts: save / load a trained task-conditioned actor as `policy(obs, task) -> action`."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import flax
import jax
import numpy as np

from bati.envs import TaskFamily, check_family_name, get_family
from bati.experts.base import Expert
from bati.experts.kinds import EXPERT_KINDS, ExpertsKind, check_kind, family_experts  # noqa: F401 (the zoo's names)
from bati.io import atomic_write_bytes, atomic_write_json

ZOO_DIR = Path(__file__).parent / "zoo"


class ExpertPolicy(Expert):
    """A trained task-conditioned SAC actor (the MuJoCo families and PointGoal)."""

    def __init__(self, family: TaskFamily, actor_params: Any, meta: dict):
        from bati.experts.sac import SAC, SACConfig

        self.family = family
        self.meta = meta
        self._sac = SAC(meta["obs_dim"], meta["task_dim"], meta["action_dim"], SACConfig(tuple(meta["hidden_dims"])))
        self.actor_params = actor_params

    def mean_action(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        """Deterministic actions as a jax function of arrays (usable inside a jitted training step)."""
        return self._sac.act(self.actor_params, obs, task_arrays, jax.random.PRNGKey(0), deterministic=True)

    def act_from_arrays(self, obs: np.ndarray, task_arrays: np.ndarray, deterministic: bool, key) -> np.ndarray:
        """Batched actions when the task arrays are already built (the fast path for rollouts)."""
        return np.asarray(self._sac.act(self.actor_params, obs, task_arrays, key, deterministic=deterministic))


def save_expert(directory: Path, family_name: str, actor_params: Any, meta: dict) -> None:
    atomic_write_bytes(directory / "actor.msgpack", flax.serialization.to_bytes(actor_params))
    atomic_write_json(directory / "expert.json", {"family": family_name, **meta})


def _kuhn_best_responses(family: TaskFamily) -> Expert:
    from bati.experts.kuhn import BestResponseExpert

    return BestResponseExpert(family)


# Families whose expert is computed or scripted rather than a trained SAC: name -> factory(family).
_EXPERT_FACTORIES: dict[str, Callable[[TaskFamily], Expert]] = {"KuhnPoker": _kuhn_best_responses}


def register_expert(family_name: str, factory: Callable[[TaskFamily], Expert]) -> None:
    """Give a family an expert that is not a trained SAC (a scripted or exact policy): `factory(family)`
    returns an `Expert` of the family object it is given. `load(family_name)` then returns it instead of
    looking in the zoo (docs/extending.md)."""
    check_family_name(family_name)
    _EXPERT_FACTORIES[family_name] = factory


def load(family_name: str, zoo_dir: str | Path | None = None, kind: ExpertsKind | None = None) -> Expert:
    """The shipped (or `zoo_dir`'s) expert of the family called `family_name` (`load_for`); an unknown name is a
    TaskError."""
    return load_for(get_family(family_name), zoo_dir, kind)


def load_for(family: TaskFamily, zoo_dir: str | Path | None = None, kind: ExpertsKind | None = None) -> Expert:
    """The shipped (or `zoo_dir`'s) expert of `family`, or the one `register_expert` gave it
    (KuhnPoker: exact best responses, nothing shipped). `kind`: "conditioned" (one task-conditioned SAC)
    or "per-task" (one SAC per training task, App. C.2: `bati.experts.per_task`); default: the family's
    (`family_experts`)."""
    from bati.experts.sac import SAC, SACConfig

    kind = family_experts(family, kind)
    family_name = family.name
    directory = Path(zoo_dir or ZOO_DIR) / family_name
    meta_path = directory / "expert.json"
    if kind == "per-task":
        from bati.experts.per_task import PER_TASK_DIR, load_per_task

        if family_name in _EXPERT_FACTORIES:
            raise ValueError(f"{family_name}'s expert is computed or scripted, not trained per task: use --experts conditioned")
        return load_per_task(family, directory / PER_TASK_DIR)
    if family_name in _EXPERT_FACTORIES:  # computed or scripted: nothing to load
        return _EXPERT_FACTORIES[family_name](family)
    if not meta_path.exists():
        raise FileNotFoundError(
            f"no expert for {family_name} in {directory}; `bati experts train --family {family_name}` trains one "
            f"and exports it to runs/experts/{family_name}/zoo/ (its --export-dir): point at that with "
            f"--zoo-dir runs/experts/{family_name}/zoo")
    meta = read_expert_meta(meta_path, f"bati experts train --family {family_name}")
    if meta.get("family") != family_name:
        raise ValueError(f"{meta_path} holds an expert of {meta.get('family')!r}, not {family_name!r}")
    version, current = meta.get("family_version", 1), family.record.version
    if version != current:
        raise ValueError(f"{meta_path} is an expert for {family_name}'s env version {version}, not the current "
                         f"version {current}; retrain it with `bati experts train --family {family_name}`")
    sac = SAC(meta["obs_dim"], meta["task_dim"], meta["action_dim"], SACConfig(tuple(meta["hidden_dims"])))
    template = jax.eval_shape(sac.init, jax.random.PRNGKey(0)).actor.params  # shapes only: no compute
    params = read_actors(directory / "actor.msgpack", template, f"bati experts train --family {family_name}")
    return ExpertPolicy(family, params, meta)


def read_expert_meta(path: Path, retrain: str) -> dict:
    """An expert's expert.json; ValueError naming the file and what to do where it is torn or not an object."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is damaged ({err}); export the expert again (`{retrain}`) or restore the file") from err
    if not isinstance(meta, dict):
        raise ValueError(f"{path} holds a JSON {type(meta).__name__}, not an expert's record; export the expert again "
                         f"(`{retrain}`) or restore the file")
    return meta


def read_actors(path: Path, template, retrain: str):
    """Actor parameters saved with flax (msgpack) in the shapes of `template`; ValueError naming the file."""
    try:
        return flax.serialization.from_bytes(template, path.read_bytes())
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{path} is missing beside its expert.json; export the expert again (`{retrain}`)") from err
    except Exception as err:  # msgpack's and flax's errors for truncated or foreign bytes have no common base
        raise ValueError(f"{path} is damaged ({type(err).__name__}: {err}); export the expert again (`{retrain}`) "
                         "or restore the file") from err
