"""Self-collected context (ours, beyond the paper): no given context; each policy gathers its own.

In every test task the policy starts from a prior latent, acts, and every k steps (`reinfer_every`)
re-infers z with the method's own `infer` from that env's own transitions so far: the most recent up
to C of them (C = the evaluation context length). A behaviour-agnostic likelihood (BATI's Eq. 8) is
sound on such a context, whoever acted; an encoder meets yet another behaviour (its own policy's).
All test tasks (and all repeats) step in lockstep with one batched policy call per step: the loop is
`bati.envs.rollout.rollout`, whose `on_step` writes each transition into a per-task record.

Choices (docs/methods.md, "Self-collected context"):

- **Window of fixed shape.** `infer` is compiled once for contexts of C transitions. With n =
  min(t, C) transitions at step t, slot j of the window holds transition t - n + floor(j n / C)
  (`window_indices`): each of the n fills floor(C / n) or ceil(C / n) slots, spread evenly. A method
  whose inference averages over the context's transitions (BATI's mean Eq. 8 NLL, the encoders' mean
  pooling) thus sees the mean over the n transitions, exactly when n divides C (up to one slot of
  weight per transition otherwise). BATI's refined inference weighs its evidence by C, not n, and
  DPT's causal transformer reads the repeats as a sequence: neither is exact on a partial window.
- **Schedule.** z is re-inferred at steps k, 2k, ... (once k transitions exist), from the last
  min(t, C); the latent inferred at step t is used from step t on. After the last step z is
  re-inferred once more if k divides the number of steps taken (the latent that would act next); it
  is the final latent whose inference error is reported.
- **Prior.** Before the first re-inference, env i acts with the reference latent of a training task
  drawn uniformly (per env, from the key): BATI its table mean, an encoder the latent of a context of
  that task's own training data (the references `Evaluator.inference_error` measures against), the
  Oracle that training task's parameters (so its row is the cost of the prior phase alone), the
  no-context control its empty latent.
- **Episodes.** With `episodes` > 1 the envs are reset after each episode and z and the record carry
  over (a window may span the boundary: all are the same task's transitions). Env i of run j is reset
  with seeds[j] + i + EPISODE_SEED_STRIDE e, so episode 1 starts as `Evaluator` starts its episode.

Families whose return is computed exactly rather than rolled out (KuhnPoker) are not supported.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from bati.envs.rollout import LockstepEnvs, rollout
from bati.errors import BatiError
from bati.evaluate import Evaluator, calibrate

EPISODE_SEED_STRIDE = 1_000_000
PRIOR = ("a training task drawn uniformly per env: its reference latent (BATI: table mean; encoders: the "
         "latent of a context of its own training data; Oracle: its parameters; no-context: empty)")


class OnlineError(BatiError, ValueError):
    """A self-collected evaluation that cannot run (bad setting, unsupported family): nothing was done."""


def check_setting(name: str, value, low: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise OnlineError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def window_indices(end: int, length: int) -> np.ndarray:
    """The record indices (of transitions 0 .. end - 1) that fill a window of `length` slots: the last
    n = min(end, length) transitions, each repeated floor or ceil of length / n times, in order."""
    end, length = check_setting("end", end), check_setting("length", length)
    n = min(end, length)
    return end - n + (np.arange(length) * n) // length


def reinference_steps(reinfer_every: int, total_steps: int) -> np.ndarray:
    """The steps (transitions taken so far) at which z is re-inferred: k, 2k, ... up to `total_steps`."""
    return np.arange(reinfer_every, total_steps + 1, reinfer_every)


@dataclass
class SelfCollected:
    """Runs x test tasks of self-collected episodes (leading axis: runs, e.g. a probe's repeats)."""

    returns: np.ndarray  # (runs, n_test, episodes)
    rewards: np.ndarray  # (runs, n_test, episodes * T): per step, episode after episode
    error_steps: np.ndarray  # (S + 1,): 0 (the prior), then each re-inference step
    inference_errors: np.ndarray  # (runs, S + 1, n_test): of the latent acting from that step on
    context_sizes: np.ndarray  # (S,): distinct transitions each re-inference read, min(step, C)
    prior_latents: np.ndarray  # (runs, n_test, latent)
    latents: np.ndarray  # (runs, n_test, latent): the final latent
    reference: np.ndarray  # (runs, n_train, latent)
    reinfer_every: int
    episodes: int
    context_length: int

    def summary(self, prefix: str = "self") -> dict:
        """Means over runs and test tasks (and stds over runs) for a result file; see docs/methods.md."""
        per_run = self.returns.mean(axis=1)  # (runs, episodes)
        errors = self.inference_errors
        finite = np.isfinite(errors).any()
        mean_error = lambda e: float(np.nanmean(e)) if finite else float("nan")  # noqa: E731
        out = {f"{prefix}_return": float(per_run[:, 0].mean()), f"{prefix}_return_std": float(per_run[:, 0].std()),
               f"{prefix}_returns": per_run[:, 0].round(3).tolist()}
        for e in range(1, self.episodes):
            out[f"{prefix}_ep{e + 1}_return"] = float(per_run[:, e].mean())
            out[f"{prefix}_ep{e + 1}_return_std"] = float(per_run[:, e].std())
        out[f"{prefix}_episode_returns"] = per_run.mean(0).round(3).tolist()
        out[f"{prefix}_inference_error"] = mean_error(errors[:, -1])
        out[f"{prefix}_prior_inference_error"] = mean_error(errors[:, 0])
        out[f"{prefix}_error_curve"] = {"steps": self.error_steps.tolist(),
                                        "error": [round(mean_error(errors[:, s]), 4) for s in range(errors.shape[1])]}
        out[f"{prefix}_reward_curve"] = self.rewards.mean(axis=(0, 1)).round(4).tolist()
        out[f"{prefix}_context_sizes"] = self.context_sizes.tolist()
        out[f"{prefix}_task_returns"] = self.returns[..., 0].mean(0).round(3).tolist()
        return out | {"reinfer_every": self.reinfer_every, "episodes": self.episodes,
                      "context_length": self.context_length, "prior": PRIOR}


class _Record:
    """Every env's transitions so far (all episodes), written by the rollout's `on_step` as they are taken."""

    def __init__(self, n_envs: int, total_steps: int, obs_dim: int, action_dim: int):
        self.arrays = {"observations": np.zeros((n_envs, total_steps, obs_dim), np.float32),
                       "actions": np.zeros((n_envs, total_steps, action_dim), np.float32),
                       "rewards": np.zeros((n_envs, total_steps), np.float32),
                       "next_observations": np.zeros((n_envs, total_steps, obs_dim), np.float32)}
        self.count = np.zeros(n_envs, np.int64)

    def write(self, _step: int, observations, actions, step) -> None:
        """`rollout`'s on_step: append each env's transition (an env whose episode ended writes nothing)."""
        rows = np.flatnonzero(step.alive)
        t = self.count[rows]
        self.arrays["observations"][rows, t] = observations[rows]
        self.arrays["actions"][rows, t] = actions[rows]
        self.arrays["rewards"][rows, t] = step.rewards[rows]
        self.arrays["next_observations"][rows, t] = step.observations[rows]
        self.count[rows] = t + 1

    def window(self, end: int, length: int, shape: tuple[int, int]) -> dict:
        """Each env's window of `length` slots over its transitions 0 .. end - 1, as (runs, n, length, ...)."""
        if not np.all(self.count == end):
            raise RuntimeError(f"envs out of step: {sorted(set(self.count.tolist()))} transitions, expected {end}")
        idx = window_indices(end, length)
        return {name: jnp.asarray(a[:, idx].reshape(shape + (length,) + a.shape[2:])) for name, a in self.arrays.items()}


class SelfCollector:
    """Evaluate runs with self-collected contexts (see the module): `run(states, keys, seeds)`.

    Uses the evaluator's method, policy, data (test tasks, noise, references) and context length.
    """

    def __init__(self, evaluator: Evaluator, reinfer_every: int, episodes: int = 1,
                 episode_length: int | None = None):
        self.reinfer_every = check_setting("reinfer_every", reinfer_every)
        self.episodes = check_setting("episodes", episodes)
        family = evaluator.family
        self.episode_length = check_setting(
            "episode_length", family.record.episode_length if episode_length is None else episode_length)
        if getattr(family, "return_unit", "episode") != "episode":
            raise OnlineError(f"{family.name}: its return is computed exactly per {family.return_unit}, not rolled "
                              f"out, so it has no self-collected context; choose a family evaluated by episodes")
        if evaluator.context_mix is not None:
            raise OnlineError("self-collected contexts replace the given ones: leave context_mix unset")
        self.evaluator = evaluator
        method, data = evaluator.method, evaluator.data
        self.infer = jax.jit(jax.vmap(evaluator._infer, in_axes=(0, 0, None, 0)))
        if method.calibrates:  # as `Evaluator.infer_latents` calibrates, with the same key
            def calibrated(params, key):
                return calibrate(method, params, data, evaluator.context_length, jax.random.fold_in(key, 0xCA1),
                                 evaluator.train_distances)[0]
            self.calibrate = jax.jit(jax.vmap(calibrated))
        else:
            self.calibrate = lambda params, keys: params

    def run(self, states, keys: jax.Array, seeds: list[int]) -> SelfCollected:
        """`states` and `keys` stacked over runs (as `Evaluator.evaluate_runs`); run j's env i is reset
        with seeds[j] + i (+ EPISODE_SEED_STRIDE per later episode)."""
        ev, k = self.evaluator, self.reinfer_every
        runs, n = len(seeds), len(ev.data.test_tasks)
        length, total = ev.context_length, self.episodes * self.episode_length
        # the references (and the given-context latents, unused) as the evaluator infers them
        latents, _ = jax.device_get(ev.latents_of_runs(states.method.params, keys))
        reference = np.asarray(latents["reference"])  # (runs, n_train, latent)
        k_prior, k_infer = jnp.moveaxis(jax.vmap(lambda key: jax.random.split(jax.random.fold_in(key, 0x5E1F)))(keys),
                                        1, 0)
        drawn = np.asarray(jax.vmap(lambda key: jax.random.randint(key, (n,), 0, reference.shape[1]))(k_prior))
        prior = np.take_along_axis(reference, drawn[..., None], axis=1)  # (runs, n, latent)
        method_params = self.calibrate(states.method.params, keys)
        policy_params = ev.policy.params(states)
        test_arrays = jnp.asarray(ev.data.test_task_arrays, jnp.float32)
        obs_dim, action_dim = ev.data.obs_dim, ev.data.action_dim
        record = _Record(runs * n, total, obs_dim, action_dim)
        schedule = reinference_steps(k, total)
        z = jnp.asarray(prior)
        trajectory = [prior]

        def reinfer(end: int):
            window = record.window(end, length, (runs, n))
            step_keys = jax.vmap(lambda key: jax.random.fold_in(key, end))(k_infer)
            return self.infer(method_params, window, test_arrays, step_keys)

        returns, rewards = [], []
        with LockstepEnvs(ev.family, ev.data.noise) as envs:
            for episode in range(self.episodes):
                def act(obs, step, episode=episode):
                    nonlocal z
                    done = episode * self.episode_length + step  # transitions taken so far
                    if done >= k and done % k == 0:
                        z = reinfer(done)
                        trajectory.append(np.asarray(z))
                    return ev.policy(policy_params, obs, z)

                reset = [s + i + EPISODE_SEED_STRIDE * episode for s in seeds for i in range(n)]
                episodes = rollout(ev.family, list(ev.data.test_tasks) * runs, act, noise=ev.data.noise, seed=reset,
                                   length=self.episode_length, envs=envs, on_step=record.write)
                returns.append(episodes.returns.reshape(runs, n))
                rewards.append(episodes.rewards.reshape(runs, n, -1))
        if total % k == 0:  # the latent that would act next
            z = reinfer(total)
            trajectory.append(np.asarray(z))
        trajectory = np.stack(trajectory, axis=1)  # (runs, S + 1, n, latent)
        errors = np.stack([np.stack([ev.inference_error(trajectory[j, s], reference[j])
                                     for s in range(trajectory.shape[1])]) for j in range(runs)])
        return SelfCollected(returns=np.stack(returns, -1), rewards=np.concatenate(rewards, -1),
                             error_steps=np.concatenate([[0], schedule]), inference_errors=errors,
                             context_sizes=np.minimum(schedule, length), prior_latents=prior,
                             latents=trajectory[:, -1], reference=reference, reinfer_every=k,
                             episodes=self.episodes, context_length=length)
