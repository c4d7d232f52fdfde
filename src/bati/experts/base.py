"""The interface of an expert (a context-collection policy): `policy(obs, task) -> action`."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from bati.envs import Task, TaskError


class Expert:
    """A family's expert: `policy(obs, task)` -> action, batched or not.

    `task` is a task of the family (or a list of them for a batch of observations);
    `deterministic=False` samples from the policy with the given `key` (a jax PRNG key).
    Subclasses give `act_from_arrays` (batched actions from task arrays) and `mean_action`.
    """

    family: Any
    meta: dict

    def task_arrays(self, task: Task | list[Task], batch: int | None) -> np.ndarray:
        """One task (broadcast over the batch) or one task per observation, as arrays."""
        try:
            single = self.family.task_to_array(task)
        except TaskError:
            if batch is None:
                raise
            return np.stack([self.family.task_to_array(t) for t in task])
        return single if batch is None else np.broadcast_to(single, (batch, single.shape[0]))

    def __call__(self, obs, task, deterministic: bool = True, key: jax.Array | None = None) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        batch = obs.shape[0] if obs.ndim == 2 else None
        tasks = self.task_arrays(task, batch)
        if not deterministic and key is None:
            raise ValueError("a stochastic expert action needs a PRNG key: policy(obs, task, deterministic=False, key=key)")
        key = jax.random.PRNGKey(0) if key is None else key
        return self.act_from_arrays(obs, tasks, deterministic, key)

    def act_from_arrays(self, obs: np.ndarray, task_arrays: np.ndarray, deterministic: bool, key) -> np.ndarray:
        raise NotImplementedError

    def act_for_collectors(self, obs: np.ndarray, collectors: np.ndarray, task_arrays: np.ndarray,
                           deterministic: bool, key) -> np.ndarray:
        """Actions of the experts of the training tasks `collectors` (one index per row; `task_arrays`:
        those tasks' arrays), as a collection plan names them. One expert per family: conditioned on the
        task's array; per-task experts (App. C.2) run expert `collectors[k]` itself."""
        return self.act_from_arrays(obs, task_arrays, deterministic, key)

    def mean_action(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        raise NotImplementedError

    def task_mean_actions(self, obs: jax.Array, task_arrays: jax.Array) -> jax.Array:
        """Deterministic actions on a batch of tasks' rows (DPT's labels): `obs` (B, T, obs_dim), each row of
        `obs[b]` in task b, `task_arrays` (B, task_dim); a jax function (inside a jitted training step)."""
        tasks = jax.numpy.broadcast_to(task_arrays[:, None], obs.shape[:2] + task_arrays.shape[-1:])
        return self.mean_action(obs, tasks)
