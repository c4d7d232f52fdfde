"""`bati experiment NAME`: one of the paper's experiments end to end (plan, sweep, probes, report).

`ExperimentJob` is the command's settings (the CLI is this dataclass); `run_experiment_job` plans the
experiment at its scale, runs what is not finished under the experiment's sweep record and writes its
report over every finished cell of the experiment, trained by this command or another;
`run_and_show_experiment` is the command on a rich console (`bati experiment list`: `show_experiment_list`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal

from bati.cli_hints import DEFAULT_IN_DOC
from bati.config import ScaleName
from bati.experiments.pipeline import ExperimentResult, Plan, plan_experiment, run_experiment, spec_parts
from bati.experiments.report import experiment_report
from bati.experiments.specs import SPECS, ExperimentError, default_out_dir, describe, get_spec, status_file
from bati.experiments.sweep import SweepFailed, record_lock

WIDE = 120
"""Console columns from which the titles fit in the list's table (narrower: below it, not in a column of 8)."""


@dataclass
class ExperimentJob:
    """Run one of the paper's experiments (`bati experiment list` shows them) and write its report."""

    name: str
    """The experiment (main, noise, context-length, ...), or `list`."""
    scale: ScaleName = "quick"
    seeds: Annotated[tuple[int, ...] | None, DEFAULT_IN_DOC] = None
    """Training seeds (default: quick 0; cpu 0 1 2; paper 0 1 2 3 4)."""
    methods: Annotated[tuple[str, ...], DEFAULT_IN_DOC] = ()
    """Keep only these of the experiment's methods (default: all of them)."""
    families: Annotated[tuple[str, ...], DEFAULT_IN_DOC] = ()
    """Keep only these of the experiment's families (default: all of them)."""
    settings: tuple[str, ...] = ()
    """KEY=VALUE TrainConfig settings for every cell, e.g. `steps=12000` (not those the experiment sets)."""
    out_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Results directory shared by the experiments (default: runs/experiments/<scale>; the committed studies:
    --out-dir results/<scale>/experiments); the report goes to OUT_DIR/<name>/."""
    data_root: Path = Path("data")
    zoo_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where the experts of the families are (default: the shipped ones); a family of your own's
    `bati experts train` exports to runs/experts/<family>/zoo."""
    workers: int = 1
    """Jobs at a time (local: processes; several may share one GPU)."""
    backend: Literal["local", "ray"] = "local"
    address: str | None = None
    """Ray cluster address (backend ray; default: a local Ray)."""
    report_only: bool = False
    """Train nothing: write the report from the cells already finished."""

    def command_line(self, whole: bool = False) -> str:
        """The command that reproduces this experiment (options that differ from the defaults; `whole`:
        all of its methods and families, as its report covers them)."""
        parts = ["bati experiment", self.name, "--scale", self.scale]
        for name in ("seeds", "settings") if whole else ("seeds", "methods", "families", "settings"):
            value = getattr(self, name)
            if value:
                parts += [f"--{name}", *map(str, value)]
        for name, default in (("out_dir", None), ("data_root", Path("data")), ("zoo_dir", None), ("workers", 1),
                              ("backend", "local"), ("address", None)):
            value = getattr(self, name)
            if value != default:
                parts += [f"--{name.replace('_', '-')}", str(value)]
        return " ".join(parts)


@dataclass
class ExperimentOutcome:
    report: dict
    """experiment_report's result (markdown, files) over every finished cell of the experiment."""
    report_dir: Path
    run: ExperimentResult | None = None
    """What this command trained and probed (None with report_only)."""
    failures: dict[str, str] = field(default_factory=dict)
    """Failed cells and probes: label -> error."""


def job_plans(job: ExperimentJob, out: Path) -> tuple[Plan, Plan]:
    """The cells the job runs, and those its report covers: every cell of the experiment at this scale in `out`,
    finished by this command or another (the spec's families and any other family the job names). Planned once:
    the job's cells are a selection of the whole."""
    spec = get_spec(job.name)
    settings = job.settings + ((f"zoo_dir={job.zoo_dir}",) if job.zoo_dir is not None else ())
    spec_parts(spec, job.methods, job.families)  # a method or family the experiment lacks: one line, first
    paper_families = tuple(dict.fromkeys(f for part in spec.parts for f in part.families))
    others = tuple(f for f in job.families if f not in paper_families)
    whole = plan_experiment(spec, job.scale, out, seeds=job.seeds, settings=settings, data_root=job.data_root,
                            families=paper_families + others if others else ())
    return whole.select(job.methods, job.families), whole


def run_experiment_job(job: ExperimentJob, show_progress: bool = True,
                       on_probe: Callable[[str], None] | None = None) -> ExperimentOutcome:
    """Plan, run and report one experiment; bad settings raise ExperimentError before any work."""
    from bati.report.stats import require_rliable

    require_rliable()  # the report at the end needs it: say so before hours of training
    spec = get_spec(job.name)
    out = job.out_dir or default_out_dir(job.scale)
    plan, whole = job_plans(job, out)
    command = job.command_line()  # what reruns exactly this command's cells
    check_report_settings(out / spec.name, command)
    if job.report_only:  # reads finished cells only, so it needs no lock: a sweep may be running
        return ExperimentOutcome(experiment_report(whole, out / spec.name, command=command, selection=plan),
                                 out / spec.name)
    with record_lock(out, status_file(spec)):  # one process at a time runs and reports this experiment here
        result = run_experiment(plan, out, data_root=job.data_root, workers=job.workers, backend=job.backend,
                                address=job.address, show_progress=show_progress, locked=True, on_probe=on_probe)
        report = experiment_report(whole, out / spec.name, command=command, selection=plan)
    return ExperimentOutcome(report, out / spec.name, result, {**result.sweep.errors, **result.probe_errors})


def check_report_settings(report_dir: Path, command: str) -> None:
    """ExperimentError (one line, before any work) where `report_dir` holds this experiment's report for other
    settings (another `--settings`, e.g. the task-conditioned expert's data): this command's report would replace
    that table."""
    path = report_dir / "report.md"
    try:
        found = re.search(r"^- command: `(.*)`$", path.read_text(), re.M)
    except (OSError, UnicodeDecodeError):
        return  # no report yet
    if found is not None and _settings_of(found.group(1)) != _settings_of(command):
        old = " ".join(_settings_of(found.group(1))) or "none"
        raise ExperimentError(f"{path} is the report of this experiment with the settings {old} (`{found.group(1)}`); "
                              f"this command's ({' '.join(_settings_of(command)) or 'none'}) would replace it: give "
                              "another --out-dir, or move that report first")


def _settings_of(command: str) -> tuple[str, ...]:
    """The KEY=VALUE settings of an experiment command line, sorted."""
    words = command.split()
    start = words.index("--settings") + 1 if "--settings" in words else len(words)
    end = next((i for i in range(start, len(words)) if words[i].startswith("--")), len(words))
    return tuple(sorted(words[start:end]))


def experiment_list() -> list[dict]:
    """Every experiment: name, paper source, title, probes (quick) and cells per scale {quick, cpu, paper}
    (`bati experiment list`)."""
    rows = []
    for spec in SPECS.values():
        counts = {scale: describe(spec, scale) for scale in ("quick", "cpu", "paper")}
        rows.append({"name": spec.name, "paper": counts["quick"]["paper"], "title": spec.title,
                     "probes": counts["quick"]["probes"], "cells": {scale: c["cells"] for scale, c in counts.items()}})
    return rows


def show_experiment_list(*, console) -> None:
    """`bati experiment list`: every experiment's name, paper source, cells per scale, probes and title."""
    from rich.markup import escape
    from rich.table import Table

    table = Table(title="bati experiments (cells: runs at the quick / cpu / paper scale; probes: quick)")
    table.add_column("name", no_wrap=True)
    table.add_column("paper", max_width=20, overflow="fold")  # the counts keep their width on 80 columns
    for column in ("quick", "cpu", "paper", "probes"):
        table.add_column(column, justify="right", no_wrap=True, min_width=len(column))
    rows = experiment_list()
    wide = console.width >= WIDE
    if wide:
        table.add_column("what", ratio=1)
    for row in rows:
        table.add_row(row["name"], row["paper"], *(str(row["cells"][k]) for k in ("quick", "cpu", "paper")),
                      str(row["probes"]), *([escape(row["title"])] if wide else []))
    console.print(table)
    if not wide:
        for row in rows:
            console.print(f"[bold]{row['name']}[/]: {escape(row['title'])}", soft_wrap=True)


def run_and_show_experiment(job: ExperimentJob, *, console, error_console) -> None:
    """`bati experiment NAME` (or `list`): the experiment run (its progress and probes shown only on a
    terminal), its report's tables, one line counting what ran, each failure on `error_console`;
    SweepFailed if a cell or probe failed."""
    from rich.markdown import Markdown
    from rich.markup import escape

    if job.name == "list":
        return show_experiment_list(console=console)
    outcome = run_experiment_job(job, show_progress=console.is_terminal,
                                 on_probe=lambda label: console.print(f"probe {label}") if console.is_terminal
                                 else None)
    console.print(Markdown(outcome.report["markdown"]))
    if outcome.run is None:
        console.print(f"experiment {job.name}: report in {outcome.report_dir}/ (nothing trained)", soft_wrap=True)
        return
    sweep, run = outcome.run.sweep, outcome.run
    counts = {s: sweep.count(s) for s in ("done", "skipped", "failed")}
    console.print(f"experiment {job.name}: {counts['done']} cell(s) run, {counts['skipped']} already done, "
                  f"{counts['failed']} failed, {run.probes_done} probe(s), in {run.wall_time_s / 60:.1f} min; "
                  f"report in {outcome.report_dir}/", soft_wrap=True)
    for label, error in outcome.failures.items():
        error_console.print(f"[red]failed[/] {label}: {escape(error)}", soft_wrap=True)
    if outcome.failures:
        raise SweepFailed(f"{counts['failed']} cell(s) and {len(run.probe_errors)} probe(s) failed; rerun the "
                          "same command to retry them")
