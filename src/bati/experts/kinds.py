"""Which experts collect a family's data, and how every output names them (no JAX: reports import this)."""

from __future__ import annotations

from typing import Literal

ExpertsKind = Literal["conditioned", "per-task"]
EXPERT_KINDS: tuple[ExpertsKind, ...] = ("conditioned", "per-task")
"""One task-conditioned SAC per family (ours) or one SAC per training task (the paper's, App. C.2)."""
CONDITIONED_SETTING = "experts=conditioned"
"""The setting of data collected by the family's one task-conditioned expert (the default is per-task experts)."""


EXPERT_LABELS = {"conditioned": "one task-conditioned expert", "per-task": "per-task experts"}
"""The name of each kind's data in live tables, progress bars, report headings, figures and the claims page."""


def check_kind(kind: str) -> str:
    if kind not in EXPERT_KINDS:
        raise ValueError(f"experts={kind!r}: choose one of {', '.join(EXPERT_KINDS)}")
    return kind


def family_experts(family, experts: ExpertsKind | None = None, seed: int = 0, tasks=None) -> ExpertsKind:
    """`experts`, or who collects `family`'s data (training tasks of `seed`, split `tasks`) unless told otherwise:
    the paper's way (App. C.2), one SAC per training task, where the family's record gives per-task experts a
    budget and the collection's training tasks are the ones they are trained for (data seed 0's, the default
    split); else the family's one expert: its task-conditioned SAC (any tasks: another seed or split), KuhnPoker's
    exact best responses, a family of your own with one trained expert. Records written before the setting
    existed are read as "conditioned" (their value then)."""
    if experts is not None:
        return check_kind(experts)
    default_split = tasks is None or not tasks.label()
    has_them = family.record.per_task_expert_steps is not None and seed == 0 and default_split
    return "per-task" if has_them else "conditioned"


def experts_label(kind: str | None, family=None) -> str:
    """"per-task experts" / "one task-conditioned expert"; a record from before kinds existed: conditioned.
    Given `family` (a TaskFamily or its name) whose expert is not a SAC, its record's `expert_name` (KuhnPoker:
    "exact best responses", whatever the kind)."""
    return (family is not None and named_expert(family)) or EXPERT_LABELS.get(kind or "conditioned", str(kind))


def data_label(kind: str | None, family=None) -> str:
    """"per-task experts' data" / "one task-conditioned expert's data" (`experts_label`'s, as data)."""
    label = experts_label(kind, family)
    return f"{label}' data" if label.endswith("s") else f"{label}'s data"


def named_expert(family) -> str:
    """The record's `expert_name` of `family` (a TaskFamily or its name): "" where its experts are SACs."""
    from bati.envs import FamilyUnavailable, TaskError, as_family

    try:
        return as_family(family).record.expert_name
    except (FamilyUnavailable, TaskError):  # a family not installed or registered here: named by its kind
        return ""
