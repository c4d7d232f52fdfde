"""Online evaluation under context shift (Alg. 2).

For each test task: draw a context of C transitions from its p_test (or p_train) context data,
infer z from the context alone, then roll the policy out for one episode in the task. All test
tasks step in lockstep with one batched policy call per step. We also report the task-inference
error: the App. C.2 distance between the true test task and the training task whose reference
latent (inferred from that task's own training data) is nearest to the inferred z.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from bati.data import FamilyData, sample_contexts
from bati.envs import get_family
from bati.envs.rollout import rollout

SOURCES = ("p_test", "p_train")


@dataclass
class EvalResult:
    returns: dict[str, np.ndarray]  # source -> (n_test_tasks,)
    inference_errors: dict[str, np.ndarray]  # source -> (n_test_tasks,)
    latents: dict[str, np.ndarray]

    def summary(self) -> dict:
        out = {}
        for s in SOURCES:
            out[f"{s}_return"] = float(self.returns[s].mean())
            out[f"{s}_inference_error"] = float(self.inference_errors[s].mean())
            out[f"{s}_task_returns"] = self.returns[s].round(3).tolist()
        return out


class Evaluator:
    def __init__(self, method, iql, data: FamilyData, context_length: int):
        self.method, self.iql, self.data = method, iql, data
        self.family = get_family(data.family)
        self.context_length = context_length
        self.infer = jax.jit(self._infer)
        # The policy: IQL's actor on z, or the method itself (DPT).
        self.act = jax.jit(method.act if method.acts_itself else iql.act)
        train, test = data.train_tasks, data.test_tasks
        self.distances = self.family.distance_matrix(test, train)  # (n_test, n_train)

    def _infer(self, params, task_data, task_arrays, key):
        k_context, k_infer = jax.random.split(key)
        task_ids = jnp.arange(task_data.rewards.shape[0])
        contexts = sample_contexts(task_data, k_context, task_ids, self.context_length)
        contexts["task_arrays"] = task_arrays  # the true tasks: only the Oracle reads them
        return self.method.infer(params, contexts, k_infer)

    def infer_latents(self, method_params, key) -> dict[str, np.ndarray]:
        keys = jax.random.split(key, len(SOURCES) + 1)
        test_arrays = jnp.asarray(self.data.test_task_arrays, jnp.float32)
        latents = {s: np.asarray(self.infer(method_params, getattr(self.data, s), test_arrays, k))
                   for s, k in zip(SOURCES, keys)}
        if hasattr(self.method, "task_latents"):  # methods with a latent per training task (BATI)
            latents["reference"] = np.asarray(self.method.task_latents(method_params))
        else:
            train_arrays = jnp.asarray(self.data.train_task_arrays, jnp.float32)
            latents["reference"] = np.asarray(self.infer(method_params, self.data.train, train_arrays, keys[-1]))
        return latents

    def evaluate(self, state, key, seed: int) -> EvalResult:
        latents = self.infer_latents(state.method, key)
        returns, errors = {}, {}
        policy_params = state.method if self.method.acts_itself else state.iql.actor
        for source in SOURCES:
            z = jnp.asarray(latents[source])
            episodes = rollout(self.family, self.data.test_tasks,
                               lambda obs, _, z=z: self.act(policy_params, jnp.asarray(obs, jnp.float32), z),
                               noise=self.data.noise, seed=seed)
            returns[source] = episodes.returns
            errors[source] = self.inference_error(latents[source], latents["reference"])
        return EvalResult(returns, errors, latents)

    def inference_error(self, z: np.ndarray, reference: np.ndarray) -> np.ndarray:
        nearest = np.argmin(((z[:, None, :] - reference[None, :, :]) ** 2).sum(-1), axis=1)
        return self.distances[np.arange(len(z)), nearest]
