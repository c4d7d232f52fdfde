"""Tables and curves of runs on your own datasets (`bati train --datasets`), for `bati report`.

Such a run has no p_train / p_test returns (no simulator of your tasks) but held-out metrics
(evaluate.OfflineEvaluator): the share of held-out windows whose task is inferred right, the method's
representation loss on held-out data, and, with `--eval-env`, the return in your env on the held-out
windows' tasks. One table per group of runs with the same settings: one row per method, mean ± std
over seeds of each run's mean of its last evaluations.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bati.report.runs import HELD_OUT_KEYS, RunResult

HELD_OUT_LABELS = {"held_out_inference_accuracy": "held-out task-inference accuracy",
                   "held_out_representation_loss": "held-out representation loss",
                   "held_out_return": "return in your env (held-out tasks)"}
HELD_OUT_COLUMNS = ("table", "datasets", "steps", "context_length", "method", "n_seeds", "seeds", "missing_seeds",
                    "evaluations_averaged", *(f"{k}_{stat}" for k in HELD_OUT_KEYS for stat in ("mean", "std")))


def held_out_rows(runs_of, methods: list[str]) -> list[dict]:
    """One dict per method: seeds and mean / std (ddof 0) over seeds of each held-out metric (NaN where
    no run has it). `runs_of(method)` gives the method's runs."""
    all_seeds = sorted({r.seed for m in methods for r in runs_of(m)})
    rows = []
    for method in methods:
        runs: list[RunResult] = runs_of(method)
        seeds = [r.seed for r in runs]
        row = {"method": method, "n_seeds": len(runs), "seeds": seeds,
               "missing_seeds": [s for s in all_seeds if s not in seeds],
               "evaluations_averaged": min((r.evaluations_averaged for r in runs
                                            if r.evaluations_averaged is not None), default=None)}
        for key in HELD_OUT_KEYS:
            values = np.array([r.held_out[key] for r in runs if key in r.held_out], float)
            row[f"{key}_mean"] = float(values.mean()) if values.size else math.nan
            row[f"{key}_std"] = float(values.std()) if values.size else math.nan
        rows.append(row)
    return rows


def _cell(row: dict, key: str) -> str:
    mean, std = row[f"{key}_mean"], row[f"{key}_std"]
    if not math.isfinite(mean):
        return "–"
    digits = 3 if key != "held_out_return" else 1
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if row["n_seeds"] > 1 else "")


def held_out_markdown(rows: list[dict], title: str, description: str) -> str:
    """The table as pasteable Markdown: heading, settings line, one row per method."""
    keys = [k for k in HELD_OUT_KEYS if any(math.isfinite(r[f"{k}_mean"]) for r in rows)]
    header = ["method", "seeds", *(HELD_OUT_LABELS[k] for k in keys), "notes"]
    lines = [f"### {title}", "", description, "", "| " + " | ".join(header) + " |",
             "| " + " | ".join("---" for _ in header) + " |"]
    for row in rows:
        notes = f"missing seed(s) {', '.join(map(str, row['missing_seeds']))}" if row["missing_seeds"] else ""
        cells = [row["method"], ", ".join(map(str, row["seeds"])), *(_cell(row, k) for k in keys), notes]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_held_out(runs_of, methods: list[str], path: Path, title: str, save_figure) -> bool:
    """One panel per recorded held-out metric over training steps (mean over seeds, ±std band); False
    (nothing written) when no run recorded a curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    for key in HELD_OUT_KEYS:
        for method in methods:
            stats = _curve(runs_of(method), key)
            if stats is not None:
                curves.setdefault(key, {})[method] = stats
    if not curves:
        return False
    fig, axes = plt.subplots(1, len(curves), figsize=(5.5 * len(curves), 4), squeeze=False)
    for ax, (key, by_method) in zip(axes[0], curves.items()):
        for method, (steps, mean, std) in by_method.items():
            (line,) = ax.plot(steps, mean, label=method)
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2, linewidth=0)
        ax.set_title(HELD_OUT_LABELS[key], fontsize="medium")
        ax.set_xlabel("gradient steps")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(loc="best", fontsize="small")
    fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return True


def _curve(runs: list[RunResult], key: str):
    """(steps, mean, std) over seeds at the evaluation steps every seed recorded `key` at; None if none did."""
    points = [{int(e["step"]): float(e[key]) for e in r.curve if isinstance(e.get(key), (int, float))} for r in runs]
    points = [p for p in points if p]
    steps = sorted(set.intersection(*(set(p) for p in points))) if points else []
    if not steps:
        return None
    values = np.array([[p[s] for s in steps] for p in points])
    return np.array(steps), values.mean(0), values.std(0)
