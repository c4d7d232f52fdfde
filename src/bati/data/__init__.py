"""Offline datasets (Eq. 9) and test-time context data (Eq. 10), stored as Minari datasets.

>>> from bati.data import ensure_family_data, sample_batch, sample_contexts
>>> data = ensure_family_data("PointGoal", scale="quick", seed=0)

Names are imported lazily: `import bati.data` loads neither JAX nor MuJoCo; the collection code
(`bati.data.collect`) loads MuJoCo, through the envs, but not JAX (the `bati` CLI does load JAX, through
its configs).
"""

from __future__ import annotations

import importlib

# `bati.data.collect` is the module (its function: `bati.data.collect.collect`); a lazy name `collect` would be
# the function until the module is first imported and the module after, so there is none.
_EXPORTS = {
    "make_plan": "bati.data.collect",
    "CollectResult": "bati.data.collect",
    "DatasetError": "bati.data.store",
    "DatasetNotFoundError": "bati.data.store",
    "collection_dir": "bati.data.store",
    "TaskData": "bati.data.batch",
    "FamilyData": "bati.data.batch",
    "Collection": "bati.data.batch",
    "load_family_data": "bati.data.batch",
    "ensure_family_data": "bati.data.batch",
    "sample_batch": "bati.data.batch",
    "sample_contexts": "bati.data.batch",
    "sample_off_policy_contexts": "bati.data.batch",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    try:  # a submodule (`bati.data.collect`), as after its import
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as err:
        if err.name != f"{__name__}.{name}":
            raise
    raise AttributeError(f"module 'bati.data' has no attribute {name!r}")
