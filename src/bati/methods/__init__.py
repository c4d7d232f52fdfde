"""Task-inference methods: BATI and the paper's baselines, all on the shared IQL core."""

from __future__ import annotations

from bati.methods.base import MethodSpec, TaskInference
from bati.methods.bati import BATI, BATIAuto, BATIReward
from bati.methods.csro import CSRO
from bati.methods.dpt import DPT
from bati.methods.er_trl import ERTRL
from bati.methods.focal import FOCAL
from bati.methods.no_context import NoContext
from bati.methods.oracle import Oracle
from bati.methods.recon import Recon
from bati.methods.unicorn import UNICORN

METHODS = {"bati": BATI, "bati-r": BATIReward, "bati-auto": BATIAuto, "recon": Recon, "unicorn": UNICORN, "csro": CSRO,
           "focal": FOCAL, "er-trl": ERTRL, "dpt": DPT, "oracle": Oracle, "no-context": NoContext}


def make_method(name: str, spec: MethodSpec, config=None) -> TaskInference:
    """Method `name` for data described by `spec`, with its hyperparameters `config` (an instance of
    its `Config`; default: the Config's defaults, family-dependent ones from `spec.family`)."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of: {', '.join(METHODS)}")
    return METHODS[name](spec, config)


__all__ = ["METHODS", "MethodSpec", "TaskInference", "make_method"]
