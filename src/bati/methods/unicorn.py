"""UNICORN-SS (Li et al., 2024): reconstruction plus FOCAL's metric loss.

L = L_recon + w * L_FOCAL with Table 3's UNICORN weight w (0.15 for the reward families, 1.5
for HopperParam / WalkerParam). With w = 0 it is Recon ("UNICORN-SS-0"). The decoder is the
same dynamics model p(r, s' | s, a, z) as BATI's and Recon's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated

import jax

from bati.cli_hints import DEFAULT_IN_DOC
from bati.envs.base import FamilyRecord, record_default
from bati.methods.base import MethodSpec
from bati.methods.dynamics import DynamicsModel, context_nll, init_dynamics
from bati.methods.focal import FOCAL, FOCALConfig


@dataclass(frozen=True)
class UNICORNConfig(FOCALConfig):
    focal_weight: Annotated[float | None, DEFAULT_IN_DOC] = None
    """w, the FOCAL term's weight (default: the family's, Table 3: FamilyRecord.unicorn_weight)."""

    def for_family(self, record: FamilyRecord | None) -> UNICORNConfig:
        if self.focal_weight is not None:
            return self
        return replace(self, focal_weight=record.unicorn_weight if record else record_default("unicorn_weight"))


class UNICORN(FOCAL):
    Config = UNICORNConfig
    config_key = "unicorn"

    def __init__(self, spec: MethodSpec, config: UNICORNConfig | None = None):
        super().__init__(spec, config)
        self.model = DynamicsModel(spec.decoder_dims, 1 + spec.obs_dim)
        self.weight = self.config.focal_weight

    def init(self, key):
        k_enc, k_model = jax.random.split(key)
        return {**super().init(k_enc), "dynamics": init_dynamics(self.model, k_model, self.spec)}

    def loss(self, params, batch, key):
        metric, z = self.contrastive_loss(params, batch)
        nll = context_nll(self.model, params["dynamics"], batch, z).mean()
        return nll + self.weight * metric, (z, {"metric_loss": metric, "recon_nll": nll})
