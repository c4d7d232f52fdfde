"""Recon (GENTLE / UNICORN-SS-0): BATI's reconstruction loss with a learned context encoder.

z = encoder(context) both in training (contexts from the task's own offline data) and at test
time; the dynamics model decodes the batch's (r, s') from (s, a, z). It is the ablation that
isolates BATI's inference procedure (Sec. 5.3).
"""

from __future__ import annotations

import jax

from bati.methods.base import MethodSpec, TaskInference
from bati.methods.dynamics import DynamicsModel, context_nll, init_dynamics
from bati.methods.encoder import ContextEncoder, dummy_context


class Recon(TaskInference):
    needs_context = True

    def __init__(self, spec: MethodSpec, config=None):
        super().__init__(spec, config)
        self.encoder = ContextEncoder(spec.encoder_dims, spec.latent_dim)
        self.model = DynamicsModel(spec.decoder_dims, 1 + spec.obs_dim)

    def init(self, key):
        k_enc, k_model = jax.random.split(key)
        return {"encoder": self.encoder.init(k_enc, dummy_context(self.spec)),
                "dynamics": init_dynamics(self.model, k_model, self.spec)}

    def loss(self, params, batch, key):
        z = self.encoder.apply(params["encoder"], batch["context"])
        nll = context_nll(self.model, params["dynamics"], batch, z).mean()
        return nll, (z, {"recon_nll": nll})

    def infer(self, params, context, key):
        return self.encoder.apply(params["encoder"], context)
