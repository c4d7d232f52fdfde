"""Which part of Eq. 8's likelihood picks the task? The saved likelihood split of a run, read into tables.

`bati.experiments.probes.save_likelihood_split` computes the split from a run's checkpoint and keeps it
beside the run, `<run>/likelihood.json` (with the commit, the context length and the wall time): for every
test task's context (p_train and p_test), the task-inference error (App. C.2 distance to the true task) of
the arg-min over the training tasks' table entries of the full Eq. 7 NLL (BATI's Eq. 8), its reward term
alone (BATI-R) and its state terms alone, plus how often the arg-min is the context collector's task (a
training task with the collector's parameters). Reports read the JSON (checkpoints are not committed, the
JSON is).
"""

from __future__ import annotations

import json
from pathlib import Path

LIKELIHOOD_FILE = "likelihood.json"
SOURCES, TERMS = ("p_train", "p_test"), ("full", "reward", "state")


def read_likelihood_split(run_dir: Path) -> dict | None:
    """The run's saved split, None when it is missing or unreadable."""
    try:
        saved = json.loads((Path(run_dir) / LIKELIHOOD_FILE).read_text())
    except (OSError, ValueError):
        return None
    keys = [f"{s}_{t}_{k}" for s in SOURCES for t in TERMS for k in ("error", "picks_collector")]
    return saved if isinstance(saved, dict) and all(isinstance(saved.get(k), (int, float)) for k in keys) else None


def likelihood_split_markdown(report: dict) -> str:
    lines = [f"Eq. 8 over the table means, {report['method']} on {report['family']} at step {report['step']}:", "",
             "| contexts | NLL used | task-inference error | arg-min = collector's task |", "| --- | --- | --- | --- |"]
    for source in SOURCES:
        for name in TERMS:
            lines.append(f"| {source} | {name} | {report[f'{source}_{name}_error']:.2f} | "
                         f"{100 * report[f'{source}_{name}_picks_collector']:.0f}% |")
    return "\n".join(lines) + "\n"
