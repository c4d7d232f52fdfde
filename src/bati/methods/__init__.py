"""Task-inference methods: BATI and the paper's baselines, all on the shared IQL core."""

from __future__ import annotations

from bati.methods.base import MethodSpec, TaskInference
from bati.methods.bati import BATI, BATIReward
from bati.methods.recon import Recon

METHODS = {"bati": BATI, "bati-r": BATIReward, "recon": Recon}


def make_method(name: str, spec: MethodSpec) -> TaskInference:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of: {', '.join(METHODS)}")
    return METHODS[name](spec)


__all__ = ["METHODS", "MethodSpec", "TaskInference", "make_method"]
