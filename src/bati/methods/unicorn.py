"""UNICORN-SS (Li et al., 2024): reconstruction plus FOCAL's metric loss.

L = L_recon + w * L_FOCAL with Table 3's UNICORN weight w (0.15 for the reward families, 1.5
for HopperParam / WalkerParam). With w = 0 it is Recon ("UNICORN-SS-0"). The decoder is the
same dynamics model p(r, s' | s, a, z) as BATI's and Recon's.
"""

from __future__ import annotations

import jax

from bati.methods.base import MethodSpec
from bati.methods.dynamics import DynamicsModel, context_nll, init_dynamics
from bati.methods.focal import FOCAL

UNICORN_WEIGHTS = {"HopperParam": 1.5, "WalkerParam": 1.5}
DEFAULT_UNICORN_WEIGHT = 0.15  # AntDir, HalfCheetahVel, HalfCheetahDir (and PointGoal)


class UNICORN(FOCAL):
    def __init__(self, spec: MethodSpec):
        super().__init__(spec)
        self.model = DynamicsModel(spec.decoder_dims, 1 + spec.obs_dim)
        self.weight = UNICORN_WEIGHTS.get(spec.family, DEFAULT_UNICORN_WEIGHT)

    def init(self, key):
        k_enc, k_model = jax.random.split(key)
        return {**super().init(k_enc), "dynamics": init_dynamics(self.model, k_model, self.spec)}

    def loss(self, params, batch, key):
        metric, z = self.contrastive_loss(params, batch)
        nll = context_nll(self.model, params["dynamics"], batch, z).mean()
        return nll + self.weight * metric, (z, {"metric_loss": metric, "recon_nll": nll})
