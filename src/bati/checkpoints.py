"""A run's checkpoint (checkpoint.msgpack): the TrainState of bati.trainer, written atomically, read back
in today's layout whatever version of bati wrote it.

Layouts read: today's (the method's and IQL's parameters each in a flax TrainState); before IQL used
TrainStates (actor, actor_opt, critic, target_critic, ...); before the method did (method, method_opt).
The upgrades only move entries: the numbers are the saved ones.
"""

from __future__ import annotations

from pathlib import Path

import flax
import jax
import jax.numpy as jnp

from bati.io import atomic_write_bytes

CHECKPOINT_NAME = "checkpoint.msgpack"


def save_checkpoint(path: Path, state) -> None:
    """Replace the checkpoint at `path` by `state` atomically (a kill leaves the old one or the new one)."""
    atomic_write_bytes(path, flax.serialization.to_bytes(state))


def load_checkpoint(path: Path, template):
    """The checkpoint at `path`, shaped like `template` (a TrainState). ValueError naming the file when it is
    not a checkpoint at all (delete it to restart) or holds other networks (another family or method)."""
    try:
        raw = flax.serialization.msgpack_restore(Path(path).read_bytes())
        if not isinstance(raw, dict):
            raise ValueError(f"it holds a {type(raw).__name__}")
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path} is damaged: not a readable checkpoint ({type(err).__name__}: {err}); delete it to "
                         "restart the run from step 0") from err
    raw = upgrade_train_state(raw)
    try:
        state = flax.serialization.from_state_dict(template, raw)
        shapes = jax.tree_util.tree_map(jnp.shape, (template, state))
        if shapes[0] != shapes[1]:
            raise ValueError("parameter shapes differ")
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path} does not match this run's networks (another family or method?): {err}") from err
    return state


def upgrade_train_state(raw: dict) -> dict:
    """A TrainState's state dict in today's layout (see the module); one already in it is returned as it is."""
    step = int(raw.get("step", 0))
    if isinstance(raw.get("iql"), dict):
        raw = {**raw, "iql": upgrade_iql_state(raw["iql"], step)}
    if "method_opt" in raw:  # saved before the method's parameters lived in a flax TrainState
        raw = {"method": {"step": step, "params": raw["method"], "opt_state": raw["method_opt"]},
               **{k: v for k, v in raw.items() if k not in ("method", "method_opt")}}
    return raw


def upgrade_iql_state(raw: dict, step: int) -> dict:
    """An IQLState's state dict saved before IQL used flax TrainStates (separate actor_opt, critic_opt,
    value_opt and target_critic entries), in today's layout; `step` (the run's) fills each TrainState's
    counter, which nothing reads. A dict already in today's layout is returned as it is."""
    if "actor_opt" not in raw:
        return raw
    return {"actor": {"step": step, "params": raw["actor"], "opt_state": raw["actor_opt"]},
            "critic": {"step": step, "params": raw["critic"], "target_params": raw["target_critic"],
                       "opt_state": raw["critic_opt"]},
            "value": {"step": step, "params": raw["value"], "opt_state": raw["value_opt"]}}
