"""An experiment's report: its table beside the paper's numbers, and its figures, from result files only.

Records come from the plan's cells: a run's eval.json (mean of its last 5 evaluations) or, for a
spec with probes, each probe's JSON (mean of its repeated evaluations of the final checkpoint). A
table cell is the mean ± std over seeds (std is shown from 2 seeds on), with the paper's value beside
it. Writes `<out>/report.md`, `<out>/table.csv`, `<out>/plan.json` (the plan its tables cover, for the readers
that do not plan again: `bati.report.stored_plan`) and the spec's figures (an earlier report's figures
left in `<out>`, e.g. of families this run did not select, are removed so none is mistaken for this one's):

- curves: p_test and p_train learning curves per setting (the paper's Fig. 4 / 8 layout);
- vs: the final metric against the table's column key, one panel per family;
- tsne: t-SNE of the latents inferred from interpolated contexts (Fig. 6).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from bati.errors import BatiError
from bati.experiments.pipeline import Plan
from bati.experiments.specs import Spec
from bati.experiments.sweep import Cell
from bati.experts.kinds import data_label
from bati.io import atomic_write_text, short_commit
from bati.report.build import (
    group_runs,
    group_title,
    method_order,
    method_rows,
    plot_group,
    plot_profile,
)
from bati.report.build import table_markdown as group_table
from bati.report.curves import save_figure
from bati.report.likelihood import SOURCES
from bati.report.probes import probe_path, read_probe
from bati.report.runs import RunResult, jobs_wall_time
from bati.report.stored_plan import PLAN_FILE
from bati.report.tables import METHOD_LABELS, csv_text

CSV_FIELDS = ("row", "column", "n_seeds", "seeds", "mean", "std", "paper")


CURVE_FIELDS = ("setting", "method", "seed", "step", "p_test_return", "p_train_return", "p_test_inference_error",
                "p_test_normalised")


def curve_records(setting: str, run: RunResult) -> list[dict]:
    """A run's learning curve, one record per evaluation; `p_test_normalised`: (return - random) /
    (expert - random) with the run's own reference returns (empty without them)."""
    refs = run.reference_returns or {}
    low, high = refs.get("random"), refs.get("expert")
    scale = (high - low) if low is not None and high is not None and high != low else None
    return [{"setting": setting, "method": run.method, "seed": run.seed, "step": point.get("step"),
             "p_test_return": point.get("p_test_return"), "p_train_return": point.get("p_train_return"),
             "p_test_inference_error": point.get("p_test_inference_error"),
             "p_test_normalised": (point["p_test_return"] - low) / scale
             if scale and point.get("p_test_return") is not None else None}
            for point in run.curve]


def cell_records(plan: Plan) -> tuple[list[dict], list[RunResult]]:
    """One record per finished cell (or per finished probe of a cell), and the finished runs."""
    records, runs = [], []
    for cell, planned in zip(plan.cells, plan.stored().cells):
        finished = planned.read()
        if finished is None:  # not finished (yet), or damaged (said, never dropped silently)
            continue
        c, run = cell.config, finished.run
        runs.append(run)
        base = {"method": c.method, "family": c.family, "seed": c.seed, "noise": f"{c.noise:g}",
                "family_noise": f"{c.family} eps={c.noise:g}", "split": f"{c.n_train_tasks}/{c.n_test_tasks}",
                "context_length": str(c.eval_context_length), "commit": run.commit, "device": run.machine,
                "task_range": _task_range(c), "probe": "run", "family_probe": f"{c.family} run",
                "family_experts": f"{c.family} {c.experts}", "wall_time_s": run.wall_time_s,
                "experts_return": (run.reference_returns or {}).get("expert")}
        if not planned.probes:
            split = finished.likelihood_split if plan.spec.likelihood_split else None
            task_returns = {f"{source}_task_returns": getattr(run, f"{source}_task_returns") for source in SOURCES}
            records.append({**base, "p_test_return": run.p_test_return, "p_train_return": run.p_train_return,
                            "p_test_inference_error": run.p_test_inference_error, **run.diagnostics,
                            **{f"likelihood_{k}": split[k] for k in LIKELIHOOD_COLUMNS if split is not None},
                            **(returns_by_task_value(cell, task_returns) if plan.spec.by_task_value else {})})
            continue
        for probe, saved in finished.probes:
            kept = ("_return", "_inference_error", "_auroc", "_flagged")
            records.append({**base, **{k: v for k, v in saved.items() if k.endswith(kept)},
                            "context_length": str(saved["context_length"]),
                            "context_mix": "" if probe.context_mix is None else f"{probe.context_mix:g}",
                            "probe": probe.name, "family_probe": f"{c.family} {probe.name}",
                            "wall_time_s": saved.get("wall_time_s")})
    return records, runs


def _task_range(config) -> str:
    """The tasks' ranges of a cell, e.g. "train [0, 3.14), test [3.14, 6.28)", or "default"."""
    if config.train_task_range is None and config.test_task_range is None:
        return "default"
    fmt = lambda r: "default" if r is None else f"[{r[0]:.3g}, {r[1]:.3g})"  # noqa: E731
    return f"train {fmt(config.train_task_range)}, test {fmt(config.test_task_range)}"


_NUMBER = re.compile(r"\d+(?:\.\d+)?(?:e-?\d+)?")


def _sort_key(value: str):
    try:
        return (0, float(value.split("/")[0]), value)
    except ValueError:  # text: numbers in it compare as numbers ("self10" before "self200", "eps=0.25" before 0.5)
        parts = re.split(f"({_NUMBER.pattern})", value)  # text, number, text, number, ..., text
        return (1, 0.0, [(0, float(part), "") if i % 2 else (1, 0, part) for i, part in enumerate(parts)])


def column_position(value: str) -> float | None:
    """A column's place on the vs figure's x axis: the number it starts with ("10/30": 10, "200": 200),
    else the last number in it ("AntDir eps=0.5": 0.5); None when it holds no number."""
    try:
        return float(value.split("/")[0])
    except ValueError:
        numbers = _NUMBER.findall(value)
        return float(numbers[-1]) if numbers else None


PRE_IQL = "experts (Pre-IQL)"
"""The paper's "Oracle (Pre-IQL)" row: the data-collecting experts' own return on the test tasks (each run's
expert reference), not an IQL agent told the task (our `oracle` row)."""


def table_rows(spec: Spec, records: list[dict], metric: str) -> tuple[list[str], list[str], list[dict]]:
    """Rows, columns and one entry per (row, column): mean, std and seeds of `metric`, paper value."""
    rows = sorted({r[spec.rows] for r in records}, key=method_order if spec.rows == "method" else _sort_key)
    # columns whose records all lack the metric (another probe's keys) are left out
    columns = sorted({r[spec.columns] for r in records if metric in r}, key=_sort_key)
    paper = spec.paper.values if spec.paper and metric == spec.metric else {}
    entries = []
    for row in rows:
        for column in columns:
            chosen = [r for r in records if r[spec.rows] == row and r[spec.columns] == column
                      and r.get(metric) is not None and math.isfinite(r[metric])]
            values = [r[metric] for r in chosen]
            entries.append({"row": row, "column": column, "n_seeds": len(values),
                            "seeds": " ".join(str(r["seed"]) for r in chosen),
                            "mean": float(np.mean(values)) if values else math.nan,
                            "std": float(np.std(values)) if values else math.nan,
                            "paper": paper.get(row, {}).get(column, "")})
    if PRE_IQL in paper and metric == "p_test_return":  # the experts' own return: the runs' reference
        rows.append(PRE_IQL)
        for column in columns:
            values = [r["experts_return"] for r in records if r[spec.columns] == column
                      and r.get("experts_return") is not None and math.isfinite(r["experts_return"])]
            entries.append({"row": PRE_IQL, "column": column, "n_seeds": int(bool(values)), "seeds": "",
                            "mean": float(np.mean(values)) if values else math.nan, "std": 0.0,
                            "paper": paper[PRE_IQL].get(column, "")})
    return rows, columns, entries


def _fmt(entry: dict) -> str:
    if not entry["n_seeds"]:
        return "–"
    size = abs(entry["mean"])
    digits = 1 if size >= 10 else 2 if size >= 1 else 3  # returns; errors; KuhnPoker's returns per hand, weights
    text = f"{entry['mean']:.{digits}f}"
    return text + (f" ± {entry['std']:.{digits}f}" if entry["n_seeds"] > 1 else "")


# The likelihood split's table (`bati likelihood`, saved per run): column key, heading
LIKELIHOOD_COLUMNS = {"p_train_full_error": "p_train, full NLL", "p_test_full_error": "p_test, full NLL (BATI)",
                      "p_test_reward_error": "p_test, reward only (BATI-R)",
                      "p_test_state_error": "p_test, state only",
                      "p_test_state_picks_collector": "p_test, state only: share = collector's task"}


MAX_TASK_VALUES = 4
"""A family whose test tasks take at most this many values (HalfCheetahDir: left, right) gets the by-value table."""


def returns_by_task_value(cell: Cell, task_returns: dict) -> dict:
    """The run's last evaluation (`task_returns`: its `<source>_task_returns`), its returns averaged over the test
    tasks of each task value:
    {"by_task_<p_train|p_test>_<value>": mean}. Empty unless the family's test tasks are a few scalars (the
    tasks are drawn again from the run's split and data seed: runs do not store them)."""
    try:
        _, test_tasks = cell.config.task_split().draw(cell.family, cell.config.data_seed)
        values = np.asarray(test_tasks, float)
    except (ValueError, TypeError, KeyError, BatiError):
        return {}
    if values.ndim != 1 or len(np.unique(values)) > MAX_TASK_VALUES:
        return {}
    out = {}
    for source in SOURCES:
        returns = np.asarray(task_returns.get(f"{source}_task_returns") or [], float)
        if returns.shape != values.shape:
            continue
        out.update({f"by_task_{source}_{value:g}": float(returns[values == value].mean())
                    for value in np.unique(values)})
    return out


def by_task_value_section(spec: Spec, records: list[dict]) -> tuple[str, list[dict]]:
    """Return per test-task value, one row per (setting, method): mean ± std over seeds; and the CSV rows (metric
    `by_task_<source>_<value>`). Empty when no record has them."""
    def source_and_value(key: str) -> tuple[str, str]:  # "by_task_p_train_-1" -> ("p_train", "-1")
        source, value = key[len("by_task_"):].rsplit("_", 1)
        return source, value

    keys = sorted({k for r in records for k in r if k.startswith("by_task_")},
                  key=lambda k: (SOURCES.index(source_and_value(k)[0]), float(source_and_value(k)[1])))
    if not keys:
        return "", []
    title = ("**Return by the test task's value** (the last evaluation's return per test task, averaged over the test "
             "tasks of each value; mean ± std over seeds; p_train contexts come from the expert of a training task "
             "with the same value, p_test ones from one with another value)")
    labels = ["{}, task {}".format(*source_and_value(k)) for k in keys]
    lines = [title, "", "| " + " | ".join([spec.columns.replace("_", " "), "method", "seeds", *labels]) + " |",
             "|" + "---|" * (3 + len(keys))]
    tables, csv_rows = {}, []
    for key in keys:
        _, _, entries = table_rows(spec, [r for r in records if key in r], key)
        tables[key] = {(e["row"], e["column"]): e for e in entries}
        csv_rows += [{**e, "metric": key} for e in entries if e["n_seeds"]]
    cells = sorted({cell for table in tables.values() for cell in table},
                   key=lambda rc: (_sort_key(rc[1]), method_order(rc[0])))
    for row, column in cells:
        entries = [tables[key].get((row, column)) for key in keys]
        if not any(e and e["n_seeds"] for e in entries):
            continue
        seeds = next(e["seeds"] for e in entries if e and e["n_seeds"])
        lines.append("| " + " | ".join([column, METHOD_LABELS.get(row, row), seeds,
                                        *(_fmt(e) if e else "–" for e in entries)]) + " |")
    return "\n".join(lines) + "\n", csv_rows


def likelihood_section(spec: Spec, records: list[dict]) -> tuple[str, list[dict]]:
    """Which term of Eq. 8 picks the task: one row per (setting, method) with saved splits, the mean ± std over
    seeds of each column; and the CSV rows (metric `likelihood_<key>`). Empty when no run has a split."""
    split = [r for r in records if "likelihood_p_test_full_error" in r]
    if not split:
        return "", []
    title = ("**Which term of Eq. 8 picks the task** (`bati likelihood` on each run's last checkpoint: task-inference "
             "error of the arg-min over the table means with the full NLL, the reward term alone and the state "
             "terms alone, one context per test task; and how often the state terms' arg-min is the context "
             "collector's task, i.e. the state model reads the behaviour)")
    lines = [title, "",
             "| " + " | ".join([spec.columns.replace("_", " "), "method", "seeds", *LIKELIHOOD_COLUMNS.values()]) + " |",
             "|" + "---|" * (3 + len(LIKELIHOOD_COLUMNS))]
    csv_rows, tables = [], {}
    for key in LIKELIHOOD_COLUMNS:
        _, _, entries = table_rows(spec, split, f"likelihood_{key}")
        tables[key] = {(e["row"], e["column"]): e for e in entries}
        csv_rows += [{**e, "metric": f"likelihood_{key}"} for e in entries if e["n_seeds"]]
    for (row, column), first in sorted(tables["p_test_full_error"].items(), key=lambda kv: (_sort_key(kv[0][1]),
                                                                                           method_order(kv[0][0]))):
        if not first["n_seeds"]:
            continue
        cells = [_fmt(tables[key][(row, column)]) for key in LIKELIHOOD_COLUMNS]
        lines.append("| " + " | ".join([column, METHOD_LABELS.get(row, row), first["seeds"], *cells]) + " |")
    return "\n".join(lines) + "\n", csv_rows


def table_markdown(spec: Spec, metric: str, rows, columns, entries, title: str) -> str:
    with_paper = any(e["paper"] for e in entries)
    head = [spec.rows] + [f"{c} (ours{' / paper' if with_paper else ''})" for c in columns]
    lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lookup = {(e["row"], e["column"]): e for e in entries}
    for row in rows:
        cells = []
        for column in columns:
            e = lookup[(row, column)]
            cells.append(_fmt(e) + (f" / {e['paper']}" if with_paper and e["paper"] else ""))
        label = METHOD_LABELS.get(row, row) if spec.rows == "method" else row
        lines.append("| " + " | ".join([label] + cells) + " |")
    paper_only = sorted({row for row in (spec.paper.values if spec.paper and metric == spec.metric else {})}
                        - set(rows))
    if paper_only:
        lines.append("")
        lines.append("Paper rows without a run here: " + ", ".join(
            f"{r} ({'; '.join(f'{c}: {v}' for c, v in spec.paper.values[r].items())})" for r in paper_only) + ".")
    return "\n".join(lines) + "\n"


def plot_vs(spec: Spec, records: list[dict], metric: str, path: Path) -> bool:
    """The final metric against the column key (numeric), one line per row (method), one panel per family."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = sorted({r["family"] for r in records})
    if not families:
        return False
    fig, axes = plt.subplots(1, len(families), figsize=(5.5 * len(families), 4), squeeze=False)
    for ax, family in zip(axes[0], families):
        subset = [r for r in records if r["family"] == family]
        rows, columns, entries = table_rows(spec, subset, metric)
        xs = [column_position(c) for c in columns]
        for row in rows:
            points = [(x, e) for x, c in zip(xs, columns) if x is not None
                      for e in entries if e["row"] == row and e["column"] == c and e["n_seeds"]]
            if not points:
                continue
            x = [p[0] for p in points]
            (line,) = ax.plot(x, [p[1]["mean"] for p in points], marker="o",
                              label=METHOD_LABELS.get(row, row) if spec.rows == "method" else row)
            ax.errorbar(x, [p[1]["mean"] for p in points], yerr=[p[1]["std"] for p in points], fmt="none",
                        ecolor=line.get_color(), alpha=0.5)
        ax.set_xlabel(spec.columns.replace("family_noise", "eps").replace("_", " "))
        ax.set_ylabel(metric.replace("_", " "))
        ax.set_title(family)
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize="small")
    fig.suptitle(spec.title, fontsize="small")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return True


def plot_tsne(plan: Plan, path: Path, methods=("bati", "recon"), paths_for: int = 3) -> bool:
    """Fig. 6: t-SNE of each method's latents (first seed): the test tasks' latents from every mixing ratio
    and the training table, coloured by task; the first `paths_for` tasks' latents joined over r."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.manifold import TSNE

    panels = []
    for method in methods:
        cell = next((c for c in plan.cells if c.config.method == method and plan.probes.get(c.id)), None)
        if cell is None:
            continue
        probes = sorted((p for p in plan.probes[cell.id] if p.context_mix is not None), key=lambda p: p.context_mix)
        latents, mixes, tasks = [], [], None
        for probe in probes:
            rule = method if cell.host else None
            saved = read_probe(cell.config.out_dir, probe, rule)
            file = probe_path(cell.config.out_dir, probe, rule).with_name(f"{probe.name}-latents.npz")
            if saved is None or not file.exists():
                continue
            with np.load(file) as arrays:
                latents.append(arrays["mixed"])
                reference = arrays["reference"]
            mixes.append(probe.context_mix)
            tasks = saved["test_tasks"], saved["train_tasks"]
        if latents and latents[0].shape[-1] > 0:
            panels.append((method, np.stack(latents), mixes, reference, tasks))
    if not panels:
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 5), squeeze=False)
    for ax, (method, latents, mixes, reference, (test_tasks, train_tasks)) in zip(axes[0], panels):
        n_mix, n_test, dim = latents.shape
        points = np.concatenate([latents.reshape(-1, dim), reference])
        embedded = TSNE(n_components=2, perplexity=min(30.0, (len(points) - 1) / 3), init="pca",
                        random_state=0).fit_transform(points)
        mixed, table = embedded[: n_mix * n_test].reshape(n_mix, n_test, 2), embedded[n_mix * n_test:]
        colour = lambda tasks: np.asarray(tasks, float).reshape(len(tasks), -1)[:, 0]  # noqa: E731
        ax.scatter(table[:, 0], table[:, 1], c=colour(train_tasks), cmap="viridis", marker="s", s=30,
                   label="training table / reference")
        first = mixed[0]
        sc = ax.scatter(first[:, 0], first[:, 1], c=colour(test_tasks), cmap="viridis", s=25,
                        label=f"test tasks, r = {mixes[0]:g}")
        for task in range(min(paths_for, n_test)):
            path_points = mixed[:, task]
            ax.plot(path_points[:, 0], path_points[:, 1], color="tab:blue", linewidth=1)
            ax.scatter(path_points[1:, 0], path_points[1:, 1], color="black", s=12)
        fig.colorbar(sc, ax=ax, label="task (target velocity)")
        ax.set_title(f"{METHOD_LABELS.get(method, method)}: r = {', '.join(f'{m:g}' for m in mixes)}")
        ax.legend(fontsize="x-small", loc="best")
    fig.suptitle("t-SNE of inferred latents (as the paper's Fig. 6)", fontsize="small")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    return True


def cells_line(plan: Plan, selection: Plan | None, n_done: int) -> str:
    """How many cells are finished: of the command's selection, and of the whole experiment the tables cover."""
    line = f"- cells finished: {n_done} of {len(plan.cells)}; seeds {list(plan.seeds)}"
    if selection is None or {c.id for c in selection.cells} == {c.id for c in plan.cells}:
        return line
    ids = {c.id for c in selection.cells}
    mine = sum((c.config.out_dir / "eval.json").is_file() for c in plan.cells if c.id in ids)
    return (f"- cells finished: {mine} of the command's {len(selection.cells)}; the tables hold every finished cell "
            f"of the experiment in this folder: {n_done} of {len(plan.cells)}; seeds {list(plan.seeds)}")


def experiment_report(plan: Plan, out_dir: Path, command: str = "", selection: Plan | None = None) -> dict:
    """Write the experiment's report.md, table.csv and figures into out_dir; see the module docstring. `plan`:
    every cell the report covers; `selection`: the cells `command` runs (default: all of `plan`'s)."""
    spec = plan.spec
    records, runs = cell_records(plan)
    out_dir = Path(out_dir)
    metrics = [spec.metric] + (["p_train_return", "p_test_inference_error"] if spec.metric == "p_test_return" else [])
    metrics += list(spec.extra_metrics)
    sections, csv_rows, files = [], [], []
    for metric in metrics:
        rows, columns, entries = table_rows(spec, records, metric)
        if not entries:
            continue
        source = f" (paper: {spec.paper.source})" if spec.paper and metric == spec.metric else ""
        sections.append(table_markdown(spec, metric, rows, columns, entries, f"{metric.replace('_', ' ')}{source}"))
        csv_rows += [{**e, "row": e["row"], "column": e["column"], "metric": metric} for e in entries]
    if spec.likelihood_split:
        section, rows_of_split = likelihood_section(spec, records)
        if section:
            sections.append(section)
            csv_rows += rows_of_split
    if spec.by_task_value:
        section, rows_by_value = by_task_value_section(spec, records)
        if section:
            sections.append(section)
            csv_rows += rows_by_value
    groups = group_runs(runs)
    seeded = [g for g in groups if any(len(g.runs_of(m)) >= 2 for m in g.methods)]
    if spec.metric == "p_test_return" and seeded:  # rliable's IQM and P(BATI > method), per family and setting
        sections.append("**Statistics over seeds** (rliable: IQM and probability of improvement with 95% "
                        "stratified-bootstrap intervals, as `bati report`)\n")
        sections += [group_table(g, method_rows(g), group_title(g, [])) for g in seeded]
    figures, curve_rows = _figures(spec, plan, runs, records, groups, out_dir)
    header = _header(plan, selection, records, runs, command)
    markdown = "\n".join(line for line in header if line is not None) + "\n" + "\n".join(sections)
    markdown += "".join(f"\n![{name}]({name})\n" for name in figures)
    atomic_write_text(out_dir / "report.md", markdown)
    atomic_write_text(out_dir / "table.csv", csv_text(("metric",) + CSV_FIELDS, csv_rows))
    plan.stored(selection).write(out_dir)  # what `bati claims` and `bati results` read instead of planning again
    if curve_rows:
        atomic_write_text(out_dir / "curves.csv", csv_text(CURVE_FIELDS, curve_rows))
    for old in [*out_dir.glob("curves-*.png"), *out_dir.glob("profile*.png"), out_dir / "vs.png", out_dir / "tsne.png"]:
        if old.name not in figures:  # an earlier report's figure (other families or settings): not this one's
            old.unlink(missing_ok=True)
    files = [out_dir / "report.md", out_dir / "table.csv", out_dir / PLAN_FILE] + [out_dir / "curves.csv"] * bool(curve_rows)
    files += [out_dir / f for f in figures]
    return {"markdown": markdown, "files": files, "records": records, "cells_done": len(runs)}


def _figures(spec, plan: Plan, runs: list, records: list[dict], groups: list, out_dir: Path) -> tuple[list[str], list]:
    """The report's figures (their file names) and the learning curves' rows of curves.csv."""
    figures = []
    by_experts: dict[str, list] = {}
    for run in runs:  # one profile per data setting: pooling two settings' runs would count a method twice
        by_experts.setdefault(run.settings().get("experts") or "conditioned", []).append(run)
    for kind, kind_runs in sorted(by_experts.items()):
        name = "profile.png" if len(by_experts) == 1 else f"profile-{kind}-experts.png"
        families = {run.family for run in kind_runs}
        data = data_label(kind, *families) if len(families) == 1 else data_label(kind)
        title = f"{spec.name}: p_test, every family ({plan.scale} scale, {data})"
        if spec.metric == "p_test_return" and plot_profile(kind_runs, out_dir / name, title):
            figures.append(name)
    if "vs" in spec.figures and plot_vs(spec, records, spec.metric, out_dir / "vs.png"):
        figures.append("vs.png")
    if "tsne" in spec.figures and plot_tsne(plan, out_dir / "tsne.png"):
        figures.append("tsne.png")
    curve_rows = []
    if "curves" in spec.figures:
        for group in groups:
            name = f"curves-{group.slug}.png"
            if plot_group(group, out_dir / name, f"{spec.name}: {group.slug}", "return"):
                figures.append(name)
            curve_rows += [row for run in group.runs for row in curve_records(group.slug, run)]
    return figures, curve_rows


def _header(plan: Plan, selection: Plan | None, records: list[dict], runs: list, command: str) -> list[str | None]:
    """The report's header lines: its command, cells, commits and devices, wall time and how numbers are read."""
    spec = plan.spec
    commits = sorted({r["commit"] for r in records if r.get("commit")})
    devices = sorted({r["device"] for r in records if r.get("device")})
    train_wall = jobs_wall_time(((run.path.parent.parent, run.method), run.total_wall_time()) for run in runs)
    header = [
        f"# Experiment `{spec.name}` ({plan.scale} scale)", "", spec.title + ".", "",
        f"Paper's claim: {spec.claim}.", "",
        f"- command: `{command}`" if command else "",
        cells_line(plan, selection, len(runs)),
        f"- commit(s): {', '.join(short_commit(c) for c in commits) or 'unknown'}; "
        f"device(s): {', '.join(devices) or 'unknown'}",
        (f"- **{changed} run(s) from code with uncommitted changes** (their commit alone does not give them back)"
         if (changed := sum(run.uncommitted_changes for run in runs)) else None),
        f"- summed wall time of the finished training jobs: {train_wall / 60:.1f} min (the seeds of a job share its "
        "time; a resumed job's sessions add up)",
        "- numbers: mean over seeds (± std from 2 seeds on) of each run's mean of its last 5 evaluations"
        + ("; probes: mean of 5 evaluations of the final checkpoint" if plan.probes and any(plan.probes.values())
           else ""),
        "",
    ]
    return header
