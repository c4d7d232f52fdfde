"""`bati run`: the paper's central result end to end on one family: the `main` experiment on that family,
with its table and one line reading it.

The main job plans the `main` experiment (bati.experiments.pipeline) on one family with its methods, seeds,
scale and eps, runs it as every experiment runs (the sweep of its cells, each BATI run's likelihood split),
then `bati report` over its setting (the report builder: table with rliable intervals, CSVs, learning curves)
and one line reading the table. Data is collected (or reused) with the shipped experts; runs resume if
interrupted; a rerun trains only what is missing.

    <out>/main.sweep.json, <out>/<Family>/<scale>-eps<eps>-<hash>/<method>-seed<s>/   the experiment's cells
    <out>/report/                         report.md, CSVs, curves (bati.report.build)
    <out>/results.md, <out>/results.json  the report's table with the reading line; its rows as JSON
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from bati.cli_hints import DEFAULT_IN_DOC
from bati.config import ScaleName
from bati.errors import PartialFailure
from bati.experiments.pipeline import Plan, plan_experiment, run_experiment
from bati.experiments.specs import get_spec, status_file
from bati.experiments.sweep import SweepError
from bati.io import atomic_write_json, atomic_write_text, check_directory
from bati.methods import method_names
from bati.report import build_report
from bati.report.tables import METHOD_LABELS

MAIN_JOB_STEPS = {"quick": 12_000}
"""The main job's default budget: at the quick scale's 3,000 steps full BATI's inference has not converged on
PointGoal (p_test -360.9, below Recon); at 12,000 it has (-285.2, Recon -361.5):
results/quick/pointgoal-convergence/report/report.md."""

HOLDS = 0.1
"""A method holds under p_test contexts when its normalised p_test score is at most this below its p_train one."""


class MainJobFailed(PartialFailure):
    """Some of the main job's runs failed (the others finished); rerunning the command retries them."""


@dataclass
class MainJob:
    """The main job: data with the shipped experts, train BATI, BATI-R and Recon (or --methods), evaluate
    under context shift, and report (table with intervals, CSVs, curves, one line reading the table)."""

    family: str = "PointGoal"
    methods: tuple[str, ...] = ("bati", "bati-r", "recon")
    """Any of bati, bati-r, bati-auto, recon, unicorn, csro, focal, er-trl, dpt, oracle, no-context; or `all`."""
    seeds: tuple[int, ...] = (0,)
    scale: ScaleName = "quick"
    steps: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Gradient steps (default: quick 12,000, where full BATI has converged on PointGoal; else the scale's)."""
    noise: Annotated[float | None, DEFAULT_IN_DOC] = None
    """Per-step noise eps (default: the family's)."""
    out_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Experiment directory (default runs/main/<family>-<scale>)."""
    data_root: Path = Path("data")
    zoo_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where the family's expert is (default: the package zoo)."""
    workers: int = 1
    """Jobs (one method's seeds each) at a time."""
    settings: tuple[str, ...] = ()
    """KEY=VALUE TrainConfig settings for every run, e.g. `context_length=50 iql.hidden_dims=[64,64]`."""

    def plan(self) -> Plan:
        """The `main` experiment on the job's family: its cells of the job's methods and seeds (every setting
        checked, before any data is collected)."""
        if any(item.partition("=")[0].strip().replace("-", "_") in ("steps", "zoo_dir") for item in self.settings):
            raise SweepError("give the steps and the zoo with --steps and --zoo-dir, not as settings")
        try:
            methods = tuple(method_names(self.methods))
        except ValueError as err:
            raise SweepError(str(err)) from err
        steps = self.steps if self.steps is not None else MAIN_JOB_STEPS.get(self.scale)
        settings = (*([f"steps={steps}"] if steps is not None else []),
                    *([f"zoo_dir={self.zoo_dir}"] if self.zoo_dir is not None else []),
                    *([f"noise={self.noise}"] if self.noise is not None else []), *self.settings)
        return plan_experiment(get_spec("main"), self.scale, self.directory(), seeds=self.seeds, settings=settings,
                               methods=methods, families=(self.family,), data_root=self.data_root)

    def directory(self) -> Path:
        return self.out_dir or Path("runs") / "main" / f"{self.family}-{self.scale}"


def run_main_job(job: MainJob, show_progress: bool = True) -> dict:
    """Run the job's plan, report it, read the table. Returns {"markdown", "reading", "out_dir",
    "report_dir", "wall_time_s", "rows"}; bad settings raise (one line) before any data is collected."""
    start = time.perf_counter()
    out = job.directory()
    check_directory(out, "the experiment directory")
    plan = job.plan()  # every setting of every run, before the data is collected
    setting_dir = plan.cells[0].config.out_dir.parent  # the job's runs, apart from other settings run into `out`
    result = run_experiment(plan, out, data_root=job.data_root, workers=job.workers, show_progress=show_progress)
    failures = {**result.sweep.errors, **result.probe_errors}
    if failures:
        raise MainJobFailed(f"{len(failures)} run(s) or likelihood split(s) failed: " + "; ".join(failures.values())
                            + f" (recorded in {out}/{status_file(plan.spec)}); rerun the same command to retry them")
    report = build_report(setting_dir, out / "report")
    table = report["tables"][0]  # one family, scale, eps and settings: one table
    line = reading(table["rows"], table["settings"].get("steps"), len(job.seeds))
    markdown = table["markdown"] + f"\n{line}\n"
    wall_time = round(time.perf_counter() - start, 1)
    atomic_write_text(out / "results.md", markdown)
    rows = [{k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}  # JSON: no NaN
            for row in table["rows"]]
    atomic_write_json(out / "results.json", {"table": table["title"], "rows": rows, "reading": line,
                                             "wall_time_s": wall_time, "report": str(out / "report")})
    return {"markdown": markdown, "reading": line, "out_dir": out, "report_dir": out / "report",
            "wall_time_s": wall_time, "rows": table["rows"]}


def run_and_show_main_job(job: MainJob, *, console) -> None:
    """`bati run`: the main job (progress only on a terminal), then its table with the reading line, its wall
    time and where its files are, on the rich `console`."""
    from rich.markdown import Markdown

    results = run_main_job(job, show_progress=console.is_terminal)
    console.print(Markdown(compact_table(results["rows"]) + "\n" + results["reading"]))
    console.print(f"wall time {results['wall_time_s'] / 60:.1f} min; results in {results['out_dir']}/ "
                  f"(results.md, results.json; the report with CSVs and curves in {results['report_dir']}/)",
                  soft_wrap=True)


def compact_table(rows: list[dict]) -> str:
    """The few columns a reader needs, for an 80-column terminal (the full table: results.md and the report):
    normalised p_train and p_test scores, and the p_test task-inference error (a task distance, App. C.2)."""

    def score(row, source):
        mean, std = row[f"{source}_normalised_mean"], row[f"{source}_normalised_std"]
        return f"{mean:.2f}" + (f" ± {std:.2f}" if row["n_seeds"] > 1 else "")

    def error(row):
        mean = row.get("p_test_inference_error_mean")
        return "–" if mean is None or not math.isfinite(mean) else f"{mean:.2f}"

    def seeds(row):
        return f"{row['n_seeds']} seed{'s' if row['n_seeds'] > 1 else ''} ({' '.join(map(str, row['seeds']))})"

    lines = ["| method | seeds | p_train (normalised) | p_test (normalised) | p_test inference error (a task distance) |",
             "|---|---|---|---|---|"]
    lines += [f"| {METHOD_LABELS.get(r['method'], r['method'])} | {seeds(r)} | {score(r, 'p_train')} | "
              f"{score(r, 'p_test')} | {error(r)} |" for r in rows]
    return "\n".join(lines) + "\n"


def reading(rows: list[dict], steps: int | None, n_seeds: int) -> str:
    """One line reading the report's table (`bati.report.build.method_rows`): who holds under p_test
    contexts, who falls, who is best, and, when no BATI is best on p_test, that the paper's effect does not
    show at this budget."""
    label = lambda row: METHOD_LABELS.get(row["method"], row["method"])
    parts = []
    for row in rows:
        train, test = row["p_train_normalised_mean"], row["p_test_normalised_mean"]
        verb = "holds" if test >= train - HOLDS else "falls"
        parts.append(f"{label(row)} {verb} ({train:.2f} -> {test:.2f})")
    best = max(rows, key=lambda row: row["p_test_mean"])
    line = (f"Reading (normalised: random 0, experts 1; p_train -> p_test): {', '.join(parts)}; best on p_test: "
            f"{label(best)}.")
    if not best["method"].startswith("bati"):
        budget = f"{steps:,} steps and " if steps else ""
        line += (f" The paper's effect (BATI best under p_test contexts) does not show at {budget}"
                 f"{n_seeds} seed(s): see docs/claims.md for where it holds.")
    if n_seeds < 3:
        line += f" {n_seeds} seed(s) decide no ranking (`--seeds 0 1 2`; docs/claims.md has the intervals)."
    return line


__all__ = ["MAIN_JOB_STEPS", "MainJob", "MainJobFailed", "SweepError", "reading", "run_main_job"]
