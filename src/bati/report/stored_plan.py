"""An experiment's plan as its report stores it: `<report folder>/plan.json`, read without JAX.

`bati experiment` plans once (`bati.experiments.pipeline.plan_experiment`: resolving every cell's config, which
needs the methods and the data layer) and its report writes that plan beside report.md. The readers of finished
experiments (`bati claims`, `bati results`) read the stored plan instead of planning again: which cells the
experiment has, where their runs are and which probes each cell has.

Run directories are stored relative to the report folder, so a results tree moved or cloned elsewhere reads the same.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

from bati.errors import BatiError
from bati.io import atomic_write_text
from bati.report.likelihood import read_likelihood_split
from bati.report.probes import Probe, read_probe
from bati.report.runs import ReportWarning, RunResult, rules_in

PLAN_FILE = "plan.json"
PLAN_FORMAT = 1


class PlanFileError(BatiError, ValueError):
    """A plan.json that cannot be read: the report that wrote it must be written again."""


@dataclass(frozen=True)
class PlannedCell:
    """One cell of a stored plan: a training run (family, method, seed, noise) and the probes of its checkpoint."""

    id: str
    label: str
    family: str
    method: str
    seed: int
    noise: float
    eval_context_length: int
    experts: str
    """Which experts collected its data: per-task or conditioned (`bati.experts.kinds`)."""
    run_dir: Path
    """The run's directory (once read: the report folder joined with the stored relative path)."""
    probes: tuple[Probe, ...] = ()
    host: str = ""
    """The method whose run evaluates this cell's method as a test-time rule (bati-r and bati-auto in a bati run:
    `run_dir` is that run's); "": the cell's own run."""

    def result(self) -> RunResult | None:
        """The cell's results in its run's eval.json (a test-time rule's where the run evaluated the cell's method as
        one: `rules`); None while it is missing (not finished) or holds no results of the method, or is damaged
        (said: ReportWarning)."""
        path = self.run_dir / "eval.json"
        if not path.is_file():
            return None
        try:
            raw = json.loads(path.read_text())
            if isinstance(raw, dict) and raw.get("method") != self.method and self.method not in rules_in(raw):
                return None  # the run did not evaluate this method
            return RunResult.from_dict(raw, path, self.method)
        except (OSError, ValueError, TypeError, AttributeError) as err:
            warnings.warn(f"skipping {path}: {err}", ReportWarning, stacklevel=2)
            return None

    def read(self) -> FinishedCell | None:
        """What the cell's run folder holds once the run finished (None before): the one reader of a plan's
        run folders, for the experiment report and `bati claims` alike."""
        run = self.result()
        if run is None:
            return None
        rule = self.method if self.host else None
        probes = tuple((probe, saved) for probe in self.probes
                       if (saved := read_probe(self.run_dir, probe, rule)) is not None)
        split = None if self.host else read_likelihood_split(self.run_dir)  # the run's own: its host's
        return FinishedCell(self, run, probes, split)


@dataclass(frozen=True)
class FinishedCell:
    """A finished cell's records: its run's eval.json, the probes saved so far and the likelihood split (if any)."""

    cell: PlannedCell
    run: RunResult
    probes: tuple[tuple[Probe, dict], ...]
    """(probe, its saved result) for each of the cell's probes on disk, in the plan's order."""
    likelihood_split: dict | None


@dataclass(frozen=True)
class StoredPlan:
    """An experiment planned at a scale for some seeds and settings (beyond the spec's own): its cells."""

    experiment: str
    scale: str
    seeds: tuple[int, ...]
    settings: tuple[str, ...]
    cells: tuple[PlannedCell, ...]
    """Every cell of the experiment in its folder: the report's tables cover their finished runs."""
    selection: tuple[str, ...] = ()
    """The ids of the cells the report's command runs (its --methods, --families; empty: all of them)."""

    def selected(self) -> tuple[PlannedCell, ...]:
        """The cells the report's command runs."""
        return tuple(c for c in self.cells if c.id in self.selection) if self.selection else self.cells

    def write(self, report_dir: Path) -> Path:
        """`report_dir`/plan.json, atomically; run directories relative to `report_dir`."""
        cells = [{**{k: v for k, v in asdict(cell).items() if k != "host" or v},  # a run of its own: no "host"
                  "run_dir": os.path.relpath(cell.run_dir, report_dir), "probes": [_settings(p) for p in cell.probes]}
                 for cell in self.cells]
        head = {"format": PLAN_FORMAT, "experiment": self.experiment, "scale": self.scale,
                "seeds": list(self.seeds), "settings": list(self.settings), "selection": list(self.selection)}
        text = json.dumps(head)[:-1] + ', "cells": [\n' + ",\n".join(map(json.dumps, cells)) + "\n]}\n"  # a cell a line
        path = Path(report_dir) / PLAN_FILE
        atomic_write_text(path, text)
        return path



def _settings(probe: Probe) -> dict:
    """A probe's settings other than the defaults (what tells it apart; `Probe(**...)` reads it back)."""
    default = asdict(Probe())
    return {key: value for key, value in asdict(probe).items() if value != default[key]}


def read_plan(report_dir: Path) -> StoredPlan | None:
    """The plan stored in `report_dir` (None where there is none); PlanFileError for a damaged one."""
    path = Path(report_dir) / PLAN_FILE
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as err:
        raise PlanFileError(f"{path} is unreadable ({err}): write the report again (`bati results --reports`)") from err
    try:
        if record.get("format") != PLAN_FORMAT:
            raise ValueError(f"format {record.get('format')!r}, this version reads {PLAN_FORMAT}")
        cells = tuple(PlannedCell(**{**cell, "run_dir": Path(os.path.normpath(Path(report_dir) / cell["run_dir"])),
                                     "probes": tuple(Probe(**p) for p in cell["probes"])})
                      for cell in record["cells"])
        return StoredPlan(record["experiment"], record["scale"], tuple(record["seeds"]), tuple(record["settings"]),
                          cells, tuple(record["selection"]))
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        raise PlanFileError(f"{path} is not a plan this version reads ({err}): write the report again "
                            "(`bati results --reports`)") from err
