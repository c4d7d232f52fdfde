"""BATI: Behavior-agnostic Task Inference (Sec. 4).

Training: a table of Gaussian task embeddings, one per training task (learnable mean, fixed
log-variance `embedding_log_var`, -4 by default), and the dynamics model are fit jointly by the
reconstruction NLL (Eq. 6-7); the batch's z is a reparameterised sample of its own task's entry.
Test time (Eq. 8): sample N latents from the table (pick an entry, sample its Gaussian) and
keep the one under which the context's transitions are most likely. Only p(r, s' | s, a, z) is
used, so who collected the context does not matter.

Refined inference (ours, off by default: `refine_steps` = 0): from the arg-min sample, `refine_steps`
Adam steps on the negative log posterior of z: the context's NLL (C transitions, each Eq. 7 / 2) plus
the negative log-density of the table's Gaussian mixture (each entry's N(mean, exp(embedding_log_var)))
as the prior, which keeps z where the table has support while letting it move between entries (a task between
training tasks) as far as the context's evidence says. Probes set it on finished runs (`bati experiment refined-inference`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import optax

from bati.checks import check_number
from bati.methods.base import MethodSpec, TaskInference
from bati.methods.dynamics import DynamicsModel, context_nll, context_nll_terms, init_dynamics

@dataclass(frozen=True)
class BATIConfig:
    """BATI's hyperparameters (shared by bati, bati-r and bati-auto)."""

    latent_samples: int = 40
    """N: table samples scored by Eq. 8 at test time."""
    embedding_log_var: float = -4.0
    """Fixed log-variance of each task embedding's Gaussian (Sec. 4)."""
    refine_steps: int = 0
    """Refined inference (ours): Adam steps on the posterior of z after Eq. 8's arg-min (0: the paper's BATI)."""
    refine_learning_rate: float = 0.01

    def check(self, section: str = "bati") -> None:
        """ValueError (one line, naming `section`.<setting>) for settings BATI cannot run with."""
        if isinstance(self.latent_samples, bool) or not isinstance(self.latent_samples, int) or self.latent_samples < 1:
            raise ValueError(f"{section}.latent_samples must be an integer >= 1, got {self.latent_samples!r}")
        if isinstance(self.refine_steps, bool) or not isinstance(self.refine_steps, int) or self.refine_steps < 0:
            raise ValueError(f"{section}.refine_steps must be an integer >= 0, got {self.refine_steps!r}")
        check_number(f"{section}.refine_learning_rate", self.refine_learning_rate)


class BATI(TaskInference):
    Config = BATIConfig
    config_key = "bati"
    config_help = "bati, bati-r and bati-auto."
    reward_only_inference = False

    def __init__(self, spec: MethodSpec, config: BATIConfig | None = None):
        super().__init__(spec, config)
        self.num_latent_samples = self.config.latent_samples
        self.refine_steps = self.config.refine_steps
        self.refine_learning_rate = self.config.refine_learning_rate
        self.model = DynamicsModel(spec.decoder_dims, 1 + spec.obs_dim)
        self.std = jnp.exp(0.5 * self.config.embedding_log_var)

    def init(self, key):
        k_table, k_model = jax.random.split(key)
        s = self.spec
        table = jax.random.normal(k_table, (s.n_train_tasks, s.latent_dim))  # N(0, I), like nn.Embedding
        return {"table": table, "dynamics": init_dynamics(self.model, k_model, s)}

    def task_latents(self, params):
        """The table's means: the latent of each training task."""
        return params["table"]

    def sample_task_latents(self, params, task_ids, key):
        """z ~ N(table[task], exp(embedding_log_var)) with the reparameterisation trick."""
        mean = params["table"][task_ids]
        return mean + self.std * jax.random.normal(key, mean.shape)

    def loss(self, params, batch, key):
        z = self.sample_task_latents(params, batch["task_ids"], key)
        nll = context_nll(self.model, params["dynamics"], batch, z).mean()
        return nll, (z, {"recon_nll": nll})

    def infer(self, params, context, key):
        """Eq. 8 for each of K contexts: argmin over N table samples of the context NLL."""
        k_entry, k_noise = jax.random.split(key)
        n_contexts = context["rewards"].shape[0]
        shape = (n_contexts, self.num_latent_samples)
        entries = jax.random.randint(k_entry, shape, 0, self.spec.n_train_tasks)
        candidates = params["table"][entries] + self.std * jax.random.normal(k_noise, shape + (self.spec.latent_dim,))
        # (K, N): NLL of context k under candidate n.
        nll = jax.vmap(lambda ctx, zs: jax.vmap(lambda z: self.score(params, ctx, z))(zs))(context, candidates)
        best = jnp.argmin(nll, axis=1)
        z = jnp.take_along_axis(candidates, best[:, None, None], axis=1)[:, 0]
        return self.refine(params, context, z) if self.refine_steps else z

    def table_prior(self, params, z):
        """-log of the table's Gaussian mixture density at z (up to a constant)."""
        sq = jnp.sum((z[None] - params["table"]) ** 2, axis=-1) / (2.0 * self.std**2)
        return -jax.nn.logsumexp(-sq)

    def refine(self, params, context, z):
        """`refine_steps` Adam steps on each context's objective + the table prior, from z (K, latent)."""
        n = context["rewards"].shape[-1]  # Eq. 7's mean NLL is twice a Gaussian NLL per transition

        def objective(z):  # -log posterior, separable over the K contexts: the sum's gradient is each one's
            per_context = jax.vmap(lambda ctx, zk: 0.5 * n * self.score(params, ctx, zk) + self.table_prior(params, zk))
            return per_context(context, z).sum()

        optimizer = optax.adam(self.refine_learning_rate)

        def step(_, carry):
            z, opt_state = carry
            updates, opt_state = optimizer.update(jax.grad(objective)(z), opt_state)
            return optax.apply_updates(z, updates), opt_state

        z, _ = jax.lax.fori_loop(0, self.refine_steps, step, (z, optimizer.init(z)))
        return z

    def score(self, params, context, z):
        """Eq. 8's objective: the context's NLL under latent z (lower is more likely)."""
        return context_nll(self.model, params["dynamics"], context, z, reward_only=self.reward_only_inference)


class BATIReward(BATI):
    """BATI whose Eq. 8 scores latents by the reward's likelihood only (training is unchanged).

    Not in the paper: for families whose tasks differ only in the reward (AntDir, HalfCheetahVel/Dir,
    PointGoal) the true p(s' | s, a, M) is the same for every task, but a learned z-conditioned state
    model is most accurate on the states each task's own expert visits, so its state NLL quietly
    favours the task whose expert collected the context. Scoring the reward alone removes that path
    (measured in docs/results.md). It needs to know the family's tasks differ in R_M only.
    """

    reward_only_inference = True
    trains_as = "bati"


STATE_WEIGHTS = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)


class BATIAuto(BATI):
    """BATI that weighs Eq. 8's reward and state terms by how well each identifies tasks under a
    foreign behaviour, measured on the training data itself (not in the paper; docs/methods.md).

    Training is BATI's. Before inference, `calibrate` takes one context per training task from an
    episode that ANOTHER task's expert collected (Eq. 9's 10% share: task i's rewards and dynamics
    under task j's behaviour, as a p_test context has them), scores it under every table entry with
    each term, and picks the weight w in STATE_WEIGHTS of the objective (1 - w) reward + w state whose
    argmin lands nearest (the family's task distance) to the true task. w = 0.5 is the paper's Eq. 8
    (up to a factor 2), w = 0 BATI-R. A state model that leaks the behaviour points to the collector's
    task on these contexts and is weighted down; one that carries the dynamics (HopperParam) is kept.
    No knowledge of the family's kind is needed. Ties go to the weight nearest 0.5.
    """

    calibrates = True
    trains_as = "bati"

    def calibrate(self, params, contexts, distances):
        """`contexts` (n_train, C, ...): off-policy contexts of the training tasks, in task order;
        `distances` (n_train, n_train): the family's distances between training tasks. Returns the
        params with the chosen "state_weight" and a dict of diagnostics."""
        table = params["table"]
        terms = jax.vmap(lambda ctx: jax.vmap(
            lambda z: context_nll_terms(self.model, params["dynamics"], ctx, z))(table))(contexts)
        reward, state = terms  # each (n_train contexts, n_train entries)
        weights = jnp.asarray(STATE_WEIGHTS)
        scores = (1.0 - weights)[:, None, None] * reward + weights[:, None, None] * state  # (W, n, n)
        picked = jnp.argmin(scores, axis=-1)  # (W, n)
        errors = jnp.take_along_axis(distances[None], picked[..., None], axis=-1)[..., 0].mean(-1)  # (W,)
        best = jnp.argmin(errors + 1e-6 * jnp.abs(weights - 0.5))
        diagnostics = {"state_weight": weights[best], "calibration_error": errors[best],
                       "calibration_error_full": errors[STATE_WEIGHTS.index(0.5)],
                       "calibration_error_reward": errors[0]}
        return {**params, "state_weight": weights[best]}, diagnostics

    def score(self, params, context, z):
        reward, state = context_nll_terms(self.model, params["dynamics"], context, z)
        weight = params.get("state_weight", 0.5)  # uncalibrated: the paper's Eq. 8
        return (1.0 - weight) * reward + weight * state
