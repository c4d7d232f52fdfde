"""`bati report DIR`: tables (Markdown + CSV) and learning curves (PNG) from result files only.

Runs (eval.json files, see bati.report.runs) are grouped by their settings: the resolved training
config apart from method, seed and paths. Each group gives one table (one row per method, mean ± std
over seeds of the run's number, the mean of its last evaluations), one CSV with the same numbers in
plain columns and one PNG of learning curves (p_test contexts like the paper's Fig. 4, p_train
contexts like Fig. 8). See docs/report.md for every column.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bati.errors import BatiError
from bati.experts.kinds import data_label
from bati.io import PathError, atomic_write_text, check_directory, make_dirs
from bati.report.convergence import NEGLIGIBLE, drift_interval, format_drift, run_drift
from bati.report.curves import save_figure
from bati.report.held_out import HELD_OUT_COLUMNS, held_out_markdown, held_out_rows, plot_held_out
from bati.report.runs import RunResult, find_eval_files, load_runs
from bati.report.stats import (
    BOOTSTRAP_REPS,
    improvement_interval,
    iqm_interval,
    performance_profile,
    require_rliable,
)
from bati.report.tables import METHOD_LABELS, csv_text, return_digits

# Methods that a probability of improvement is computed for (against every other method of the group).
IMPROVERS = ("bati", "bati-r")
FIRST_METHODS = ("bati", "bati-r")
LAST_METHODS = ("oracle", "no-context")
EXPECTED_EVALUATIONS = 5
# Settings shown in every title (when recorded); other settings appear when they differ between groups.
TITLE_KEYS = ("family", "scale", "noise", "experts", "steps", "context_length", "eval_context_length")

CSV_COLUMNS = (
    "table", "family", "scale", "noise", "steps", "task_batch", "batch_size", "context_length",
    "eval_context_length", "n_episodes", "n_context_episodes", "transitions",
    "random_return", "expert_return",
    "method", "n_seeds", "seeds", "missing_seeds", "evaluations_averaged",
    "p_train_mean", "p_train_std", "p_test_mean", "p_test_std", "test_train_ratio",
    "p_train_normalised_mean", "p_train_normalised_std", "p_test_normalised_mean", "p_test_normalised_std",
    "test_train_ratio_normalised",
    "p_train_inference_error_mean", "p_train_inference_error_std",
    "p_test_inference_error_mean", "p_test_inference_error_std",
    "iqm_score", "iqm_p_test", "iqm_low", "iqm_high", "p_test_drift", "p_test_drift_low", "p_test_drift_high",
    "p_bati_better", "p_bati_better_low", "p_bati_better_high",
    "p_bati_r_better", "p_bati_r_better_low", "p_bati_r_better_high",
)
RUN_COLUMNS = ("table", "family", "method", "seed", "scale", "noise", "steps", "evaluations_averaged",
               "p_train_return", "p_test_return", "p_train_normalised", "p_test_normalised",
               "p_train_inference_error", "p_test_inference_error", "p_test_drift", "random_return",
               "expert_return", "wall_time_s", "device", "commit", "path",
               "held_out_inference_accuracy", "held_out_representation_loss", "held_out_return")


def method_order(method: str) -> tuple:
    """bati, bati-r, the baselines alphabetically, then oracle and no-context."""
    if method in FIRST_METHODS:
        return (0, FIRST_METHODS.index(method), "")
    if method in LAST_METHODS:
        return (2, LAST_METHODS.index(method), "")
    return (1, 0, method)


def _mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and population std (ddof 0, as the repo's earlier tables) of the finite values; NaN if none."""
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return math.nan, math.nan
    return float(np.mean(finite)), float(np.std(finite))


def _fmt(value: float | None, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _fmt_mean_std(mean: float, std: float, n: int, digits: int) -> str:
    if not math.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f}" if n < 2 else f"{mean:.{digits}f} ± {std:.{digits}f}"


def _fmt_setting(value) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


@dataclass
class Group:
    """Runs with equal settings: one table."""

    settings: dict
    runs: list[RunResult]
    slug: str = ""

    @property
    def family(self) -> str:
        return self.settings["family"]

    @property
    def methods(self) -> list[str]:
        return sorted({r.method for r in self.runs}, key=method_order)

    def runs_of(self, method: str) -> list[RunResult]:
        return sorted((r for r in self.runs if r.method == method), key=lambda r: r.seed)

    @property
    def own_data(self) -> bool:
        """Runs on your own datasets: held-out metrics instead of returns (bati.report.held_out)."""
        return all(r.own_data for r in self.runs)

    @property
    def normalised(self) -> bool:
        """Normalised scores only when every run of the group has reference returns."""
        return all(r.reference_returns is not None for r in self.runs)

    def references(self) -> dict | None:
        refs = [r.reference_returns for r in self.runs if r.reference_returns is not None]
        if not refs:
            return None
        return {k: float(np.mean([ref[k] for ref in refs])) for k in ("random", "expert")}

    def data(self) -> dict | None:
        return next((r.data for r in self.runs if r.data is not None), None)

    def steps(self) -> int | None:
        steps = self.settings.get("steps")
        return steps if steps is not None else max((r.steps or 0 for r in self.runs), default=None)


def group_runs(runs: list[RunResult]) -> list[Group]:
    """Runs grouped by settings, sorted by family then settings; each group gets a unique file slug."""
    by_key: dict[str, Group] = {}
    for run in runs:
        by_key.setdefault(run.settings_key(), Group(run.settings(), [])).runs.append(run)
    groups = sorted(by_key.values(), key=lambda g: (g.family, repr(sorted(g.settings.items(), key=str))))
    used: set[str] = set()
    for g in groups:
        parts = [g.family, g.settings.get("scale")]
        if g.settings.get("noise") is not None:
            parts.append(f"eps{_fmt_setting(g.settings['noise'])}")
        if g.settings.get("experts") == "per-task":
            parts.append("per-task-experts")
        if g.steps():
            parts.append(f"{g.steps()}steps")
        base = re.sub(r"[^A-Za-z0-9.+-]+", "_", "-".join(str(p) for p in parts if p is not None))
        slug, i = base, 2
        while slug in used:
            slug, i = f"{base}-{i}", i + 1
        used.add(slug)
        g.slug = slug
    return groups


def differing_keys(groups: list[Group]) -> list[str]:
    """Setting keys with different values in the groups that record them (family and title keys excluded).

    A key absent from some groups (older result files record no config) does not count as a difference,
    except a method's hyperparameter: a run records it only where it differs from the method's default.
    """
    from bati.config import method_sections

    keys = sorted({k for g in groups for k in g.settings})
    methods = tuple(f"{name}." for name in method_sections())  # present only where not the method's default
    return [k for k in keys if k not in TITLE_KEYS
            and (k.startswith(methods) or len({repr(g.settings[k]) for g in groups if k in g.settings}) > 1)]


def _datasets(group: Group) -> list[str]:
    """The datasets of a group of runs on your own data (settings hold lists as JSON text)."""
    value = group.settings.get("datasets")
    try:
        value = json.loads(value) if isinstance(value, str) else value
    except ValueError:
        return [value]
    return [str(d) for d in value or []]


def group_title(group: Group, extra_keys: list[str]) -> str:
    s = group.settings
    parts = [group.family]
    if group.own_data:
        names = [Path(d).name for d in _datasets(group)]
        parts = [f"own data ({', '.join(names)})" if names else "own data"]
        extra_keys = [k for k in extra_keys if not k.startswith("datasets")]
    if s.get("scale") is not None:
        parts.append(f"{s['scale']} scale")
    if not group.own_data:  # your own data has no noise model of ours
        parts.append(f"eps = {_fmt_setting(s['noise'])}" if s.get("noise") is not None else "eps not recorded")
    if not group.own_data:
        parts.append(data_label(s.get("experts"), group.family))
    if group.steps():
        parts.append(f"{group.steps():,} steps")
    data = group.data()
    if data and data.get("n_episodes") is not None:
        parts.append(f"{data['n_episodes']} episodes per task")
    if s.get("context_length") is not None:
        parts.append(f"C = {s['context_length']}")
    if s.get("eval_context_length") not in (None, s.get("context_length")):
        parts.append(f"eval C = {s['eval_context_length']}")
    parts += [f"{k} = {_fmt_setting(s[k])}" for k in extra_keys if k in s]
    return ", ".join(parts)


def _reference_spread(group: Group, digits: int) -> str:
    """Where the runs of a group recorded different references (their data and references were computed on
    different machines): the range, and that each run is normalised by its own."""
    refs = [r.reference_returns for r in group.runs if r.reference_returns is not None]
    spread = {k: (min(ref[k] for ref in refs), max(ref[k] for ref in refs)) for k in ("random", "expert")}
    differing = [f"{name} {low:.{digits}f} to {high:.{digits}f}" for name, (low, high) in spread.items()
                 if f"{low:.{digits}f}" != f"{high:.{digits}f}"]
    fingerprints = {r.data["fingerprint"] for r in group.runs if r.data and r.data.get("fingerprint")}
    if len(fingerprints) > 1:  # runs recorded since fingerprints exist (eval.json's data.fingerprint)
        differing.append(f"{len(fingerprints)} different data fingerprints")
    if not differing:
        return ""
    return (f" (means over runs; the runs' own differ: {', '.join(differing)}, so their data came from different "
            "collections; each run is normalised by its own)")


def group_description(group: Group) -> str:
    """The settings line under a table's title: steps, batch, data size, references, provenance."""
    s, lines = group.settings, []
    steps = group.steps()
    batch = (f" of {s['task_batch']} tasks × {s['batch_size']} transitions"
             if s.get("task_batch") is not None and s.get("batch_size") is not None else "")
    lines.append(f"Steps: {steps:,} gradient steps{batch}." if steps else "Steps: not recorded.")
    data = group.data()
    if group.own_data:
        from bati.config import TrainConfig  # held_out at its default is left out of the settings

        lines.append(f"Data: your datasets {', '.join(_datasets(group)) or '(not recorded)'}"
                     + (f", {_fmt_setting(data['transitions'])} transitions" if data and data.get("transitions")
                        else "") + f"; held out: {_fmt_setting(s.get('held_out', TrainConfig.held_out))} of each task's "
                     "episodes (no simulator of your tasks: held-out metrics, not returns).")
    elif data:
        lines.append(f"Data: {data.get('n_episodes', '?')} episodes per training task, "
                     f"{data.get('n_context_episodes', '?')} per context dataset, "
                     f"{_fmt_setting(data.get('transitions', '?'))} transitions"
                     + (f" (data seed {s['data_seed']})." if s.get("data_seed") is not None else "."))
    else:
        lines.append("Data: size not recorded in these result files.")
    refs = group.references()
    if group.own_data:
        pass
    elif refs is not None:
        partial = "" if group.normalised else " (some runs lack them: no normalised scores)"
        d = return_digits(refs["random"], refs["expert"])
        lines.append(f"References (test tasks, same eps): random policy {refs['random']:.{d}f}, "
                     f"experts {refs['expert']:.{d}f}{partial}{_reference_spread(group, d)}.")
    else:
        lines.append("References: not recorded (no normalised scores).")
    evals = sorted({r.evaluations_averaged for r in group.runs if r.evaluations_averaged is not None})
    commits = sorted({r.commit for r in group.runs if r.commit})
    devices = sorted({r.machine for r in group.runs if r.machine})
    run_line = f"Runs: {len(group.runs)}; each run's number is the mean of its last " \
               f"{'/'.join(map(str, evals)) or '?'} evaluations, then mean ± std (ddof 0) over seeds"
    if commits:
        run_line += f"; commit {', '.join(commits)}"
    if devices:
        run_line += f"; device {', '.join(devices)}"
    changed = sum(r.uncommitted_changes for r in group.runs)
    if changed:
        run_line += f"; **{changed} run(s) from code with uncommitted changes**"
    lines.append(run_line + ".")
    return " ".join(lines)


def method_rows(group: Group, reps: int = BOOTSTRAP_REPS, seed: int = 0) -> list[dict]:
    """One dict per method (numbers as floats, NaN where undefined); see CSV_COLUMNS."""
    all_seeds = sorted({r.seed for r in group.runs})
    score_name = "p_test_normalised" if group.normalised else "p_test_return"

    def scores(method):
        runs = group.runs_of(method)
        return np.array([r.normalised(r.p_test_return) if group.normalised else r.p_test_return
                         for r in runs])

    rows = []
    for method in group.methods:
        runs = group.runs_of(method)
        seeds = [r.seed for r in runs]
        row = {"method": method, "n_seeds": len(runs), "seeds": seeds,
               "missing_seeds": [s for s in all_seeds if s not in seeds],
               "evaluations_averaged": min((r.evaluations_averaged for r in runs
                                            if r.evaluations_averaged is not None), default=None)}
        for source in ("p_train", "p_test"):
            returns = [getattr(r, f"{source}_return") for r in runs]
            row[f"{source}_mean"], row[f"{source}_std"] = _mean_std(returns)
            norm = [r.normalised(getattr(r, f"{source}_return")) for r in runs] if group.normalised else []
            row[f"{source}_normalised_mean"], row[f"{source}_normalised_std"] = _mean_std(norm)
            row[f"{source}_inference_error_mean"], row[f"{source}_inference_error_std"] = _mean_std(
                [getattr(r, f"{source}_inference_error") for r in runs])
        row["test_train_ratio"] = (row["p_test_mean"] / row["p_train_mean"]
                                   if row["p_train_mean"] else math.nan)
        row["test_train_ratio_normalised"] = (row["p_test_normalised_mean"] / row["p_train_normalised_mean"]
                                              if row["p_train_normalised_mean"] else math.nan)
        row["iqm_score"] = score_name
        row["iqm_p_test"] = row["iqm_low"] = row["iqm_high"] = math.nan
        if len(runs) >= 2:
            row["iqm_p_test"], row["iqm_low"], row["iqm_high"] = iqm_interval(scores(method), reps, seed)
        # converged? the drift of p_test over the evaluations the number averages (bati.report.convergence)
        row["p_test_drift"], row["p_test_drift_low"], row["p_test_drift_high"] = drift_interval(
            [run_drift(r, normalise=group.normalised) for r in runs], reps, seed)
        for improver in IMPROVERS:
            col = f"p_{improver.replace('-', '_')}_better"
            row[col] = row[f"{col}_low"] = row[f"{col}_high"] = math.nan
            if (improver != method and len(group.runs_of(improver)) >= 2 and len(runs) >= 2):
                row[col], row[f"{col}_low"], row[f"{col}_high"] = improvement_interval(
                    scores(improver), scores(method), reps, seed)
        notes = []
        if row["missing_seeds"]:
            notes.append(f"missing seed(s) {', '.join(map(str, row['missing_seeds']))}")
        if row["evaluations_averaged"] is not None and row["evaluations_averaged"] < EXPECTED_EVALUATIONS:
            notes.append(f"only {row['evaluations_averaged']} evaluation(s) averaged")
        row["notes"] = "; ".join(notes)
        rows.append(row)
    return rows


def table_markdown(group: Group, rows: list[dict], title: str) -> str:
    """The group's pasteable Markdown: heading, settings line, table."""
    norm = group.normalised
    improvers = [m for m in IMPROVERS
                 if any(math.isfinite(r[f"p_{m.replace('-', '_')}_better"]) for r in rows)]
    has_iqm = any(math.isfinite(r["iqm_p_test"]) for r in rows)
    has_notes = any(r["notes"] for r in rows)
    has_drift = any(math.isfinite(r["p_test_drift"]) for r in rows)
    rd = return_digits(*(r[f"{s}_mean"] for r in rows for s in ("p_train", "p_test")))  # 3 for per-hand returns
    header = ["method", "seeds", "p_train return", "p_test return"]
    if norm:
        header += ["p_train normalised", "p_test normalised", "p_test / p_train (normalised)"]
    else:
        header += ["p_test / p_train (returns)"]
    header += ["task-inference error p_train", "task-inference error p_test"]
    if has_iqm:
        header.append(f"IQM p_test{' normalised' if norm else ''} [95% CI]")
    header += [f"P({METHOD_LABELS.get(m, m)} > method) [95% CI]" for m in improvers]
    if has_drift:
        header.append("p_test drift over the scored window [95% CI]")
    if has_notes:
        header.append("notes")
    lines = [f"### {title}", "", group_description(group), "",
             "| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    for r in rows:
        n = r["n_seeds"]
        cells = [METHOD_LABELS.get(r["method"], r["method"]), ", ".join(map(str, r["seeds"])),
                 _fmt_mean_std(r["p_train_mean"], r["p_train_std"], n, rd),
                 _fmt_mean_std(r["p_test_mean"], r["p_test_std"], n, rd)]
        if norm:
            cells += [_fmt_mean_std(r["p_train_normalised_mean"], r["p_train_normalised_std"], n, 2),
                      _fmt_mean_std(r["p_test_normalised_mean"], r["p_test_normalised_std"], n, 2),
                      _fmt(r["test_train_ratio_normalised"], 2)]
        else:
            cells.append(_fmt(r["test_train_ratio"], 2))
        for source in ("p_train", "p_test"):
            cells.append(_fmt_mean_std(r[f"{source}_inference_error_mean"],
                                       r[f"{source}_inference_error_std"], n, 2))
        if has_iqm:
            digits = 2 if norm else rd
            cells.append("–" if not math.isfinite(r["iqm_p_test"]) else
                         f"{r['iqm_p_test']:.{digits}f} "
                         f"[{r['iqm_low']:.{digits}f}, {r['iqm_high']:.{digits}f}]")
        for m in improvers:
            col = f"p_{m.replace('-', '_')}_better"
            cells.append("–" if not math.isfinite(r[col]) else
                         f"{r[col]:.2f} [{r[f'{col}_low']:.2f}, {r[f'{col}_high']:.2f}]")
        if has_drift:
            cells.append(format_drift(r["p_test_drift"], r["p_test_drift_low"], r["p_test_drift_high"],
                                      2 if norm else rd, NEGLIGIBLE if norm else 0.0))
        if has_notes:
            cells.append(r["notes"])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table_records(group: Group, rows: list[dict]) -> list[dict]:
    s, data, refs = group.settings, group.data() or {}, group.references() or {}
    common = {"table": group.slug, "family": group.family, "scale": s.get("scale"), "noise": s.get("noise"),
              "steps": group.steps(), "task_batch": s.get("task_batch"), "batch_size": s.get("batch_size"),
              "context_length": s.get("context_length"), "eval_context_length": s.get("eval_context_length"),
              "n_episodes": data.get("n_episodes"), "n_context_episodes": data.get("n_context_episodes"),
              "transitions": data.get("transitions"), "random_return": refs.get("random"),
              "expert_return": refs.get("expert")}
    return [{**common, **row} for row in rows]


def run_records(group: Group) -> list[dict]:
    records = []
    for method in group.methods:
        for r in group.runs_of(method):
            refs = r.reference_returns or {}
            records.append({
                "table": group.slug, "family": r.family, "method": r.method, "seed": r.seed, "scale": r.scale,
                "noise": group.settings.get("noise"), "steps": r.steps,
                "evaluations_averaged": r.evaluations_averaged,
                "p_train_return": r.p_train_return, "p_test_return": r.p_test_return,
                "p_train_normalised": r.normalised(r.p_train_return),
                "p_test_normalised": r.normalised(r.p_test_return),
                "p_train_inference_error": r.p_train_inference_error,
                "p_test_inference_error": r.p_test_inference_error,
                "p_test_drift": run_drift(r, normalise=group.normalised),
                "random_return": refs.get("random"), "expert_return": refs.get("expert"),
                "wall_time_s": r.wall_time_s, "device": r.machine, "commit": r.commit, "path": str(r.path),
                **r.held_out})
    return records


def _curve_stats(runs: list[RunResult], key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Mean and std over seeds at the evaluation steps every seed has (None if no seed has the key)."""
    curves = []
    for r in runs:
        points = {int(e["step"]): float(e[key]) for e in r.curve
                  if "step" in e and e.get(key) is not None and math.isfinite(float(e[key]))}
        if points:
            curves.append(points)
    if not curves:
        return None
    steps = sorted(set.intersection(*(set(c) for c in curves)))
    if not steps:
        return None
    values = np.array([[c[s] for s in steps] for c in curves])
    return np.array(steps), values.mean(0), values.std(0)


def plot_group(group: Group, path: Path, title: str, metric: str = "return") -> bool:
    """Two panels, p_test contexts (Fig. 4) and p_train contexts (Fig. 8): mean over seeds, ±std band.

    metric "return" draws the experts' (dashed) and the random policy's (dotted) references when known;
    "inference_error" plots the task-inference error. Returns False (nothing written) without data.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    drawn = False
    for ax, source, fig_name in zip(axes, ("p_test", "p_train"), ("Fig. 4", "Fig. 8")):
        for method in group.methods:
            stats = _curve_stats(group.runs_of(method), f"{source}_{metric}")
            if stats is None:
                continue
            steps, mean, std = stats
            (line,) = ax.plot(steps, mean, label=METHOD_LABELS.get(method, method))
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2, linewidth=0)
            drawn = True
        refs = group.references()
        if metric == "return" and refs is not None:
            ax.axhline(refs["expert"], color="black", linestyle="--", linewidth=1, label="experts")
            ax.axhline(refs["random"], color="gray", linestyle=":", linewidth=1, label="random policy")
        ax.set_title(f"{source} contexts (as the paper's {fig_name})")
        ax.set_xlabel("gradient steps")
        ax.grid(alpha=0.3)
    if not drawn:
        plt.close(fig)
        return False
    axes[0].set_ylabel("episodic return" if metric == "return" else "task-inference error")
    axes[1].legend(loc="best", fontsize="small")
    fig.suptitle(title, fontsize="medium")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return True


def profile_scores(runs: list[RunResult]) -> tuple[dict[str, np.ndarray], bool]:
    """Per method, a (runs, families) matrix of p_test scores (normalised when every run has references;
    the first n runs of each family, n the fewest), and whether they are normalised."""
    normalised = all(r.reference_returns is not None for r in runs)
    families = sorted({r.family for r in runs})
    scores = {}
    for method in sorted({r.method for r in runs}, key=method_order):
        columns = [[r.normalised(r.p_test_return) if normalised else r.p_test_return
                    for r in runs if r.method == method and r.family == f] for f in families]
        n = min(len(c) for c in columns)
        if n:
            scores[method] = np.array([c[:n] for c in columns]).T
    return scores, normalised


def plot_profile(runs: list[RunResult], path: Path, title: str) -> bool:
    """rliable's performance profile of the p_test scores: the fraction of (run, family) scores above
    tau, one line per method (methods with runs on every family only). False (nothing written) without
    two runs of some method."""
    scores, normalised = profile_scores(runs)
    if not scores or max(m.size for m in scores.values()) < 2:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.concatenate([m.ravel() for m in scores.values()])
    taus = np.linspace(values.min(), values.max(), 101)
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, matrix in scores.items():
        ax.plot(taus, performance_profile(matrix, taus), label=f"{METHOD_LABELS.get(method, method)} ({matrix.size})")
    ax.set_xlabel("p_test " + ("normalised score" if normalised else "return") + " tau")
    ax.set_ylabel("fraction of runs with score > tau")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="x-small", loc="best")
    ax.set_title(title, fontsize="small")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return True


def check_results_dir(results_dir: Path) -> None:
    """One-line BatiError unless results_dir is a directory holding at least one eval.json."""
    results_dir = Path(results_dir)
    if not results_dir.exists():
        raise BatiError(f"results directory {results_dir} does not exist")
    if not results_dir.is_dir():
        raise BatiError(f"{results_dir} is a file; give the directory that holds the runs' eval.json files")
    if not find_eval_files(results_dir):
        raise BatiError(f"no eval.json under {results_dir}; a training run writes one into its run directory "
                        "when it finishes")


def build_report(results_dir: Path, out_dir: Path | None = None, reps: int = BOOTSTRAP_REPS,
                 seed: int = 0) -> dict:
    """Tables and curves of every run under results_dir, written to out_dir (default results_dir/report).

    Writes report.md (all tables, pasteable into docs), <slug>.csv per table, runs.csv (one row per
    run), <slug>_curves.png per table and <slug>_inference.png where curves record the inference
    error. Returns {"out_dir", "markdown", "tables": [{"title", "slug", "rows", "csv", "curves", ...}],
    "runs", "files"}. Bad input raises BatiError before anything is written.
    """
    results_dir = Path(results_dir)
    check_results_dir(results_dir)
    require_rliable()
    runs = load_runs(results_dir)
    if not runs:
        raise BatiError(f"no readable eval.json under {results_dir} "
                        "(every one was skipped, see the warnings)")
    out = Path(out_dir) if out_dir is not None else results_dir / "report"
    try:  # outside the package, and writable: named now, not as the staging folder that could not be made
        check_directory(out, "the report directory")
    except PathError as err:
        raise BatiError(str(err)) from err
    make_dirs(out.parent)
    # Everything is written into a staging directory first and moved into `out` file by file at the end, so
    # a full disk or an error leaves the previous report as it was, and the error names `out`.
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        report_md, tables, files = _write_report(runs, results_dir, staging, reps, seed)
        out.mkdir(parents=True, exist_ok=True)
        for file in sorted(staging.iterdir()):
            os.replace(file, out / file.name)
    except OSError as err:
        raise OSError(err.errno, err.strerror, str(out)) from err
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for entry in tables:
        for key in ("csv", "curves", "inference_curves", "profile"):
            if entry.get(key) is not None:
                entry[key] = out / entry[key].name
    files = [out / f.name for f in files]
    return {"out_dir": out, "markdown": report_md, "tables": tables, "runs": len(runs), "files": files}


def build_and_show_report(results_dir: Path, out_dir: Path | None = None, *, console) -> None:
    """`bati report`: build the report, then print its tables and the files it wrote on the rich `console`
    (files skipped are warnings, shown as they happen)."""
    from rich.markdown import Markdown

    report = build_report(results_dir, out_dir)
    console.print(Markdown(report["markdown"]))
    console.print(f"{report['runs']} run(s), {len(report['tables'])} table(s); "
                  f"files in {report['out_dir']}/: " + ", ".join(p.name for p in report["files"]), soft_wrap=True)

def _write_held_out_table(group: Group, title: str, out: Path) -> dict:
    """A group of runs on your own datasets: held-out metrics table, its CSV and curves (bati.report.held_out)."""
    rows = held_out_rows(group.runs_of, group.methods)
    markdown = held_out_markdown(rows, title, group_description(group))
    s = group.settings
    common = {"table": group.slug, "datasets": ";".join(_datasets(group)), "steps": group.steps(),
              "context_length": s.get("context_length")}
    csv_path = out / f"{group.slug}.csv"
    atomic_write_text(csv_path, csv_text(HELD_OUT_COLUMNS, [{**common, **row} for row in rows]))
    curves = out / f"{group.slug}_held_out.png"
    drawn = plot_held_out(group.runs_of, group.methods, curves, title, save_figure)
    return {"title": title, "slug": group.slug, "settings": group.settings, "rows": rows, "markdown": markdown,
            "csv": csv_path, "curves": curves if drawn else None, "inference_curves": None, "profile": None}


def _write_report(runs: list[RunResult], results_dir: Path, out: Path, reps: int, seed: int):
    """Write the report's files into `out`; (report.md's text, the tables, the files written)."""
    groups = group_runs(runs)
    extra = differing_keys(groups)
    sections, tables, all_runs, files = [], [], [], []
    for group in groups:
        title = group_title(group, extra)
        if group.own_data:
            entry = _write_held_out_table(group, title, out)
            files += [entry[k] for k in ("csv", "curves") if entry[k] is not None]
            sections.append(entry["markdown"] + (f"\n![{group.slug} held-out metrics]({entry['curves'].name})\n"
                                                 if entry["curves"] is not None else ""))
            tables.append(entry)
            all_runs += run_records(group)
            continue
        rows = method_rows(group, reps, seed)
        markdown = table_markdown(group, rows, title)
        csv_path = out / f"{group.slug}.csv"
        atomic_write_text(csv_path, csv_text(CSV_COLUMNS, table_records(group, rows)))
        files.append(csv_path)
        entry = {"title": title, "slug": group.slug, "settings": group.settings, "rows": rows,
                 "markdown": markdown, "csv": csv_path, "curves": None, "inference_curves": None}
        figures = []
        curves = out / f"{group.slug}_curves.png"
        if plot_group(group, curves, title, "return"):
            entry["curves"] = curves
            figures.append(f"![{group.slug} learning curves]({curves.name})")
        inference = out / f"{group.slug}_inference.png"
        if plot_group(group, inference, title, "inference_error"):
            entry["inference_curves"] = inference
            figures.append(f"![{group.slug} task-inference error]({inference.name})")
        profile = out / f"{group.slug}_profile.png"
        entry["profile"] = profile if plot_profile(group.runs, profile, f"performance profile: {title}") else None
        if entry["profile"] is not None:
            figures.append(f"![{group.slug} performance profile]({profile.name})")
        files += [entry[k] for k in ("curves", "inference_curves", "profile") if entry[k] is not None]
        sections.append(markdown + ("\n" + "\n\n".join(figures) + "\n" if figures else ""))
        tables.append(entry)
        all_runs += run_records(group)
    runs_csv = out / "runs.csv"
    atomic_write_text(runs_csv, csv_text(RUN_COLUMNS, all_runs))
    header = (f"# Results report\n\nGenerated by `bati report` from {len(runs)} result file(s) under "
              f"`{results_dir}` ({len(groups)} table(s)). Returns: mean over the test tasks of an episode's "
              "return; normalised: (return - random) / (experts - random). IQM, P(X > method) and the "
              f"performance profiles through rliable: {reps:,} stratified-bootstrap replicates "
              f"(seed {seed}), 95% percentile intervals, over seeds (see docs/report.md).\n\n")
    report_md = header + "\n".join(sections)
    atomic_write_text(out / "report.md", report_md)
    files = [out / "report.md", runs_csv, *files]
    return report_md, tables, files
