"""Which experts collect a family's data, and how every output names them (no JAX: reports import this)."""

from __future__ import annotations

EXPERT_KINDS = ("conditioned", "per-task")
"""One task-conditioned SAC per family (ours) or one SAC per training task (the paper's, App. C.2)."""

EXPERT_LABELS = {"conditioned": "one task-conditioned expert", "per-task": "per-task experts"}
"""The name of each kind's data in live tables, progress bars, report headings, figures and the claims page."""


def check_kind(kind: str) -> str:
    if kind not in EXPERT_KINDS:
        raise ValueError(f"experts={kind!r}: choose one of {', '.join(EXPERT_KINDS)}")
    return kind


def experts_label(kind: str | None) -> str:
    """"per-task experts" / "one task-conditioned expert"; a record from before kinds existed: conditioned."""
    return EXPERT_LABELS.get(kind or "conditioned", str(kind))


def data_label(kind: str | None) -> str:
    """"per-task experts' data" / "one task-conditioned expert's data"."""
    label = experts_label(kind)
    return f"{label}' data" if label.endswith("s") else f"{label}'s data"
