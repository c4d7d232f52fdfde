"""BATI: Behavior-agnostic Task Inference (Sec. 4).

Training: a table of Gaussian task embeddings, one per training task (learnable mean, fixed
log-variance -4), and the dynamics model are fit jointly by the reconstruction NLL (Eq. 6-7);
the batch's z is a reparameterised sample of its own task's entry.
Test time (Eq. 8): sample N latents from the table (pick an entry, sample its Gaussian) and
keep the one under which the context's transitions are most likely. Only p(r, s' | s, a, z) is
used, so who collected the context does not matter.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from bati.methods.base import MethodSpec, TaskInference
from bati.methods.dynamics import DynamicsModel, context_nll, init_dynamics

EMBEDDING_LOG_VAR = -4.0


class BATI(TaskInference):
    reward_only_inference = False

    def __init__(self, spec: MethodSpec, num_latent_samples: int = 40):
        super().__init__(spec)
        self.num_latent_samples = num_latent_samples
        self.model = DynamicsModel(spec.decoder_dims, 1 + spec.obs_dim)
        self.std = jnp.exp(0.5 * EMBEDDING_LOG_VAR)

    def init(self, key):
        k_table, k_model = jax.random.split(key)
        s = self.spec
        table = jax.random.normal(k_table, (s.n_train_tasks, s.latent_dim))  # N(0, I), like nn.Embedding
        return {"table": table, "dynamics": init_dynamics(self.model, k_model, s)}

    def task_latents(self, params):
        """The table's means: the latent of each training task."""
        return params["table"]

    def sample_task_latents(self, params, task_ids, key):
        """z ~ N(table[task], exp(-4)) with the reparameterisation trick."""
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
        def nll_of(ctx, z):
            return context_nll(self.model, params["dynamics"], ctx, z, reward_only=self.reward_only_inference)

        nll = jax.vmap(lambda ctx, zs: jax.vmap(lambda z: nll_of(ctx, z))(zs))(context, candidates)
        best = jnp.argmin(nll, axis=1)
        return jnp.take_along_axis(candidates, best[:, None, None], axis=1)[:, 0]


class BATIReward(BATI):
    """BATI whose Eq. 8 scores latents by the reward's likelihood only (training is unchanged).

    Not in the paper: for families whose tasks differ only in the reward (AntDir, HalfCheetahVel/Dir,
    PointGoal) the true p(s' | s, a, M) is the same for every task, but a learned z-conditioned state
    model is most accurate on the states each task's own expert visits, so its state NLL quietly
    favours the task whose expert collected the context. Scoring the reward alone removes that path
    (measured in docs/results.md). It needs to know the family's tasks differ in R_M only.
    """

    reward_only_inference = True
