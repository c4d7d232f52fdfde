"""Online evaluation under context shift (Alg. 2).

For each test task: draw a context of C transitions from its p_test (or p_train) context data,
infer z from the context alone, then roll the policy out for one episode in the task. All test
tasks step in lockstep with one batched policy call per step. We also report the task-inference
error: the App. C.2 distance between the true test task and the training task whose reference
latent (inferred from that task's own training data) is nearest to the inferred z.
A family that computes a policy's expected return exactly (`TaskFamily.exact_returns`; KuhnPoker:
per hand, enumerating the deals) is evaluated that way instead of by a rollout.

With `context_mix=r` the evaluator instead draws interpolated contexts (Sec. 5.8): N (1 - r)
transitions from p_train followed by N r from p_test, one source called "mixed".
"""

from __future__ import annotations

import copy
import threading
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from bati.data import FamilyData, sample_contexts, sample_off_policy_contexts
from bati.envs import TaskFamily
from bati.envs.rollout import LockstepEnvs, lockstep_envs, rollout

SOURCES = ("p_test", "p_train")


@dataclass
class EvalResult:
    returns: dict[str, np.ndarray]  # source -> (n_test_tasks,)
    inference_errors: dict[str, np.ndarray]  # source -> (n_test_tasks,)
    latents: dict[str, np.ndarray]
    diagnostics: dict[str, float] = field(default_factory=dict)  # e.g. BATI-auto's calibrated state weight

    def summary(self) -> dict:
        out = {}
        for s in self.returns:
            out[f"{s}_return"] = float(self.returns[s].mean())
            out[f"{s}_inference_error"] = float(self.inference_errors[s].mean())
            out[f"{s}_task_returns"] = self.returns[s].round(3).tolist()
        return out | {name: float(value) for name, value in self.diagnostics.items()}


def reference_latents(method, params, train, task_arrays: jax.Array, context_length: int, k_context: jax.Array,
                      k_infer: jax.Array, per_task: int = 1) -> jax.Array:
    """Each training task's reference latent (n_tasks, latent_dim): its table entry for a method with one
    (BATI), else the mean latent inferred from `per_task` contexts of the task's own training data."""
    if hasattr(method, "task_latents"):
        return method.task_latents(params)
    n = train.rewards.shape[0]
    ids = jnp.repeat(jnp.arange(n), per_task)
    contexts = {**sample_contexts(train, k_context, ids, context_length), "task_arrays": task_arrays[ids]}
    z = method.infer(params, contexts, k_infer)
    return z.reshape(n, per_task, z.shape[-1]).mean(axis=1)


def mixed_context_lengths(length: int, mix: float) -> tuple[int, int]:
    """(p_train, p_test) transitions of an interpolated context of `length` with a p_test ratio `mix`."""
    n_test = round(length * mix)
    return length - n_test, n_test


class RunsPolicy:
    """The policy of k runs acting in k x n lockstep envs: IQL's actor on a latent, or the method itself
    (DPT), vmapped over runs and jitted once."""

    def __init__(self, method, iql):
        self.method = method
        self.apply = jax.jit(jax.vmap(method.act if method.acts_itself else iql.act))

    def params(self, states):
        """The policy's parameters in `states` (stacked over runs)."""
        return states.method.params if self.method.acts_itself else states.iql.actor.params

    def __call__(self, params, observations, z) -> np.ndarray:
        """Actions (k * n, action_dim) for observations (k * n, obs_dim) and latents z (k, n, latent_dim)."""
        k, n = z.shape[:2]
        observations = jnp.asarray(observations, jnp.float32).reshape(k, n, -1)
        return np.asarray(self.apply(params, observations, z)).reshape(k * n, -1)


class WarmsUp:
    """An evaluator whose first evaluation's one-off work (compiling its programs for the runs' shapes,
    starting its envs) can begin in a thread while training goes on: on a GPU the first evaluation of a job
    took 17-35 s against 2-5 s for the later ones (docs/performance.md). Its evaluations and `close` wait
    for that thread. No number changes: the programs compiled are the ones the evaluation would compile,
    and each rollout resets every env with its own seed."""

    _warming: threading.Thread | None = None

    def warm_up(self, states, keys: jax.Array, seeds: list[int]) -> None:
        """Begin the one-off work for runs stacked as `evaluate_runs` takes them (once per evaluator)."""
        if self._warming is None:
            self._warming = threading.Thread(target=self._warm_quietly, args=(states, keys, seeds), daemon=True)
            self._warming.start()

    def _warm_quietly(self, states, keys, seeds) -> None:
        try:
            self._warm(states, keys, seeds)
        except Exception:  # noqa: BLE001 - the evaluation itself meets, and raises, whatever went wrong here
            pass

    def _warm(self, states, keys, seeds) -> None:
        raise NotImplementedError

    def _warmed(self) -> None:
        """Wait for the warm-up thread, if one was started."""
        if self._warming is not None:
            self._warming.join()


class Evaluator(WarmsUp):
    def __init__(self, method, iql, data: FamilyData, context_length: int, context_mix: float | None = None, *,
                 family: TaskFamily, workers: int = 1):
        """`family`: the TaskFamily the data came from (resolved once by the caller); `workers`: processes
        that step the envs (`lockstep_envs`)."""
        self.method, self.iql, self.data = method, iql, data
        self.family = family
        self.context_length = context_length
        if context_mix is not None and not 0.0 <= context_mix <= 1.0:
            raise ValueError(f"context_mix must be in [0, 1] (the share of p_test transitions), got {context_mix!r}")
        self.context_mix = context_mix
        self.sources = SOURCES if context_mix is None else ("mixed",)
        self.infer = jax.jit(self._infer)
        self.policy = RunsPolicy(method, iql)
        self.latents_of_runs = jax.jit(jax.vmap(self.infer_latents))
        train, test = data.train_tasks, data.test_tasks
        self.distances = self.family.distance_matrix(test, train)  # (n_test, n_train)
        self.train_distances = jnp.asarray(self.family.distance_matrix(train, train), jnp.float32)
        self.envs = lockstep_envs(self.family, data.noise, workers)  # made at the first evaluation, then reused
        self.shares_envs = False  # another evaluator's envs (`inferring_with`): that one starts and closes them

    def close(self) -> None:
        """Stop the env pool (its worker processes, if any)."""
        self._warmed()
        if not self.shares_envs:
            self.envs.close()

    def inferring_with(self, method) -> Evaluator:
        """This evaluator with `method`'s inference instead (one that trains as this one's method and reads the
        same parameters: bati-r and bati-auto for bati): the same data, contexts, policy and envs (closed by
        this evaluator), its own compiled inference and warm-up."""
        other = copy.copy(self)
        other.method, other._warming, other.shares_envs = method, None, True
        other.infer, other.latents_of_runs = jax.jit(other._infer), jax.jit(jax.vmap(other.infer_latents))
        if method.acts_itself or self.method.acts_itself:
            other.policy = RunsPolicy(method, self.iql)
        return other

    def _warm(self, states, keys, seeds) -> None:
        latents, _ = jax.device_get(self.latents_of_runs(states.method.params, keys))
        k, n = len(seeds), len(self.data.test_tasks)
        observations = np.zeros((k * n, self.data.obs_dim), np.float32)
        self.policy(self.policy.params(states), observations, jnp.asarray(latents[self.sources[0]]))
        if type(self.family).exact_returns is TaskFamily.exact_returns and not self.shares_envs:  # start the envs
            self.envs.reset(list(self.data.test_tasks) * k, [s + i for s in seeds for i in range(n)])

    def contexts(self, source: str, key: jax.Array) -> dict:
        """One context of `context_length` transitions per test task from `source` ("p_test",
        "p_train", or "mixed": the p_train part first, then the p_test part)."""
        if source != "mixed":
            task_data = getattr(self.data, source)
            return sample_contexts(task_data, key, jnp.arange(task_data.rewards.shape[0]), self.context_length)
        lengths = mixed_context_lengths(self.context_length, self.context_mix)
        parts = [sample_contexts(getattr(self.data, s), k, jnp.arange(self.data.p_test.rewards.shape[0]), n)
                 for s, n, k in zip(("p_train", "p_test"), lengths, jax.random.split(key)) if n > 0]
        return {name: jnp.concatenate([p[name] for p in parts], axis=1) for name in parts[0]}

    def _infer(self, params, contexts, task_arrays, key):
        contexts = {**contexts, "task_arrays": task_arrays}  # the true tasks: only the Oracle reads them
        return self.method.infer(params, contexts, key)

    def infer_latents(self, method_params, key) -> tuple[dict[str, jax.Array], dict[str, jax.Array]]:
        """The latent inferred from a context of each test task per source, and the reference latent of
        each training task (its table entry, or inferred from its own training data); and the
        method's calibration diagnostics (a calibrating method is calibrated first, see `calibrates`)."""
        keys = jax.random.split(key, len(self.sources) + 1)
        diagnostics = {}
        if self.method.calibrates:  # its own key: the other methods' draws stay as they were
            method_params, diagnostics = calibrate(self.method, method_params, self.data, self.context_length,
                                                   jax.random.fold_in(key, 0xCA1), self.train_distances)
        test_arrays = jnp.asarray(self.data.test_task_arrays, jnp.float32)
        latents = {}
        for source, k in zip(self.sources, keys):
            k_context, k_infer = jax.random.split(k)
            latents[source] = self._infer(method_params, self.contexts(source, k_context), test_arrays, k_infer)
        latents["reference"] = reference_latents(self.method, method_params, self.data.train,
                                                 jnp.asarray(self.data.train_task_arrays, jnp.float32),
                                                 self.context_length, *jax.random.split(keys[-1]))
        return latents, diagnostics

    @staticmethod
    def status(results: list[EvalResult]) -> str:
        """The progress bar's line: mean returns over the runs."""
        return (f"p_test {np.mean([r.returns['p_test'].mean() for r in results]):.1f} "
                f"p_train {np.mean([r.returns['p_train'].mean() for r in results]):.1f}")

    def evaluate(self, state, key, seed: int) -> EvalResult:
        """Evaluate one run's state (env i of the rollout is reset with seed + i)."""
        stacked = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], state)
        return self.evaluate_runs(stacked, key[None], [seed])[0]

    def evaluate_runs(self, states, keys: jax.Array, seeds: list[int]) -> list[EvalResult]:
        """Evaluate k runs at once: `states` and `keys` stacked on a leading axis of size k (seeds).

        Each source's episodes of all k runs step in one lockstep rollout of k x n_test envs with one
        batched (vmapped) policy call per step; run j's env i is reset with seeds[j] + i, as `evaluate`.
        """
        self._warmed()
        k, n = len(seeds), len(self.data.test_tasks)
        latents, diagnostics = jax.device_get(self.latents_of_runs(states.method.params, keys))
        policy_params = self.policy.params(states)
        returns = {}
        for source in self.sources:
            z = jnp.asarray(latents[source])  # (k, n, latent_dim)

            def act(obs, _, z=z):
                return self.policy(policy_params, obs, z)

            tasks = list(self.data.test_tasks) * k
            exact = self.family.exact_returns(lambda obs, act=act: act(obs, 0), tasks, self.data.noise)
            if exact is not None:  # the expected return, computed (KuhnPoker: per hand, over the deals)
                returns[source] = np.asarray(exact).reshape(k, n)
                continue
            episodes = rollout(self.family, tasks, act, noise=self.data.noise,
                               seed=[s + i for s in seeds for i in range(n)], envs=self.envs)
            returns[source] = episodes.returns.reshape(k, n)
        results = []
        for j in range(k):
            run_latents = {name: np.asarray(value[j]) for name, value in latents.items()}
            errors = {s: self.inference_error(run_latents[s], run_latents["reference"]) for s in self.sources}
            results.append(EvalResult({s: returns[s][j] for s in self.sources}, errors, run_latents,
                                      {name: float(value[j]) for name, value in diagnostics.items()}))
        return results

    def inference_error(self, z: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """App. C.2 distance from each true test task to the training task nearest to its latent
        (NaN for a method whose latent is empty, e.g. `no-context`)."""
        if z.shape[-1] == 0:
            return np.full(len(z), np.nan)
        nearest = np.argmin(((z[:, None, :] - reference[None, :, :]) ** 2).sum(-1), axis=1)
        return self.distances[np.arange(len(z)), nearest]


def calibrate(method, params, data: FamilyData, context_length: int, key: jax.Array, train_distances: jax.Array):
    """A calibrating method's params for inference (see `TaskInference.calibrates`), and its diagnostics:
    one off-policy window (at most an episode) per training task."""
    length = min(context_length, data.train.episode_length)
    return method.calibrate(params, sample_off_policy_contexts(data.train, key, length), train_distances)


def reference_returns(data: FamilyData, *, family: TaskFamily, expert, seed: int = 0) -> dict[str, float]:
    """Mean return on the test tasks of a uniform random policy (0 on a normalised scale) and of the
    data-collecting `expert`, acting for each task (1; the paper's "Oracle (Pre-IQL)"). `family`: the data's
    TaskFamily."""
    from bati.experts.card import expert_episodes

    exact_random = family.exact_returns(None, data.test_tasks, data.noise)
    if exact_random is not None:  # computed expectations (KuhnPoker: per hand), as `Evaluator` reports them
        arrays = np.stack([family.task_to_array(t) for t in data.test_tasks])
        key = jax.random.PRNGKey(seed)
        exact_expert = family.exact_returns(lambda obs: expert.act_from_arrays(obs, arrays, True, key),
                                            data.test_tasks, data.noise)
        return {"random": float(np.mean(exact_random)), "expert": float(np.mean(exact_expert))}
    rng = np.random.default_rng(seed)
    probe = family.make_env(data.test_tasks[0], data.noise)
    low, high = probe.action_space.low, probe.action_space.high
    probe.close()
    random_episodes = rollout(family, data.test_tasks, lambda obs, _: rng.uniform(low, high, (len(obs), len(low))),
                              noise=data.noise, seed=3000 + seed)
    experts = expert_episodes(expert, data.test_tasks, data.test_tasks, data.noise, seed=2000 + seed)
    return {"random": float(random_episodes.returns.mean()), "expert": float(experts.returns.mean())}


@dataclass
class OfflineResult:
    """Diagnostics of a run on a user's own data (and its returns in their env, when given)."""

    values: dict

    def summary(self) -> dict:
        return dict(self.values)


class OfflineEvaluator(WarmsUp):
    """Offline diagnostics for a user's own datasets (`bati.data.own`), and returns in their env if given.

    On the held-out segments of every task: `held_out_inference_accuracy`, the share of held-out contexts
    (CONTEXTS_PER_TASK per task) whose inferred latent is nearest to their own task's reference latent
    (BATI: its table entry; encoders: the mean latent of contexts of the task's training data); NaN for a
    method that infers nothing (no-context). `held_out_representation_loss`: the method's training loss on
    a batch of held-out data (overfitting shows as a gap to the training loss in metrics.jsonl).
    With `env_family` (an `OwnFamily` with the user's env): `held_out_return`, the mean return of one
    episode per held-out context, acting on that context's inferred latent in its task (run j's env i
    reset with seeds[j] + i), and `held_out_task_returns`, its mean per task.
    BATI-auto is not calibrated here (it scores with Eq. 8's equal weights).
    """

    CONTEXTS_PER_TASK = 8

    def __init__(self, trainer, data, context_length: int, env_family=None, episode_length: int | None = None):
        self.trainer, self.method, self.data = trainer, trainer.method, data
        self.context_length = context_length
        self.task_arrays = jnp.asarray(data.train_task_arrays, jnp.float32)
        self.of_runs = jax.jit(jax.vmap(self._diagnostics))
        self.ids = np.repeat(np.arange(data.train.n_tasks), self.CONTEXTS_PER_TASK)
        self.envs = None if env_family is None else LockstepEnvs(env_family)
        self.episode_length = episode_length
        self.policy = RunsPolicy(trainer.method, trainer.iql)

    def close(self) -> None:
        self._warmed()
        if self.envs is not None:
            self.envs.close()

    def _warm(self, states, keys, seeds) -> None:
        jax.block_until_ready(self.of_runs(states.method.params, keys))

    def _contexts(self, data, key, ids):
        contexts = sample_contexts(data, key, ids, self.context_length)
        return {**contexts, "task_arrays": self.task_arrays[ids]}

    def _diagnostics(self, params, key) -> dict:
        k_held, k_infer, k_train, k_ref, k_batch, k_context, k_loss = jax.random.split(key, 7)
        ids = jnp.asarray(self.ids)
        z = self.method.infer(params, self._contexts(self.data.held_out, k_held, ids), k_infer)
        references = reference_latents(self.method, params, self.data.train, self.task_arrays, self.context_length,
                                       k_train, k_ref, per_task=self.CONTEXTS_PER_TASK)
        nearest = jnp.argmin(jnp.sum((z[:, None] - references[None]) ** 2, axis=-1), axis=1)
        accuracy = jnp.mean(nearest == ids) if self.method.infers_task else jnp.nan
        batch = self.trainer.make_batch(self.data.held_out, k_batch, k_context)
        loss, _ = self.method.loss(params, batch, k_loss)
        return {"held_out_inference_accuracy": accuracy, "held_out_representation_loss": loss}, z

    def evaluate_runs(self, states, keys: jax.Array, seeds: list[int]) -> list[OfflineResult]:
        self._warmed()
        values, latents = jax.device_get(self.of_runs(states.method.params, keys))
        results = [{k: float(v[j]) for k, v in values.items()} for j in range(len(seeds))]
        if self.envs is not None:
            returns = self._returns(states, jnp.asarray(latents), seeds)  # (runs, contexts)
            n_tasks = self.data.train.n_tasks
            for j, result in enumerate(results):
                result["held_out_return"] = float(returns[j].mean())
                result["held_out_task_returns"] = returns[j].reshape(n_tasks, -1).mean(1).round(3).tolist()
        return [OfflineResult(r) for r in results]

    def _returns(self, states, z: jax.Array, seeds: list[int]) -> np.ndarray:
        """(runs, contexts): the return of one episode per held-out context in the user's env."""
        k, n = z.shape[:2]
        policy_params = self.policy.params(states)
        act = lambda obs, _: self.policy(policy_params, obs, z)  # noqa: E731
        tasks = [self.data.train_tasks[i] for i in self.ids] * k
        episodes = rollout(self.envs.family, tasks, act, noise=None, seed=[s + i for s in seeds for i in range(n)],
                           length=self.episode_length, envs=self.envs)
        return episodes.returns.reshape(k, n)

    @staticmethod
    def status(results: list[OfflineResult]) -> str:
        status = f"held-out inference accuracy {np.mean([r.values['held_out_inference_accuracy'] for r in results]):.2f}"
        if "held_out_return" in results[0].values:
            status += f", return {np.mean([r.values['held_out_return'] for r in results]):.1f}"
        return status
