"""The cells a claim reads: where each scale's results are (`SOURCES`) and the records of an experiment's
finished cells there (`gather`), from the plan its report stored (bati.report.stored_plan). No JAX."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from bati.experts.kinds import CONDITIONED_SETTING as CONDITIONED
from bati.experts.kinds import data_label
from bati.report.convergence import run_drift
from bati.report.stored_plan import PLAN_FILE, StoredPlan, read_plan

__all__ = ["CONDITIONED_DATA", "SOURCES", "Record", "Source", "gather", "source_plan"]


@dataclass(frozen=True)
class Source:
    """One scale's results: where its experiments ran and the settings they ran with."""

    label: str
    out_dir: Path
    scale: str
    settings: tuple[str, ...] = ()
    data: str = ""
    """Short name of data other than the default (the paper's: per-task experts where the family has them,
    docs/data.md): the task-conditioned expert's (`CONDITIONED_DATA`), which decides a claim only where the
    default data has no cells for it, or another setting, whose verdicts only stand beside (`every_scale`)."""
    reports: tuple[tuple[str, str], ...] = ()
    """(a claim's experiment, the experiment whose report holds its cells here) where they differ: a folder that
    ran the `experts` study holds `main`'s cells of its families."""
    experts: str = ""
    """Keep only the cells of this experts kind (a study of both kinds' data: `experts`)."""

    def heading(self, collectors: str = "") -> str:
        """The label; for a claim whose families have no SAC experts (`collectors`: the data of their own, e.g.
        Kuhn poker's "exact best responses' data"), the label with the SAC experts' data named after theirs."""
        if not collectors:
            return self.label
        return self.label.replace(PAPER_DATA, collectors).replace(CONDITIONED_DATA, collectors)


PAPER_DATA = "the paper's data: one SAC expert per training task, App. C.2"
CONDITIONED_DATA = data_label("conditioned")  # "one task-conditioned expert's data"
"""`Source.data` of the task-conditioned expert's cells: they decide a claim only where no cells of the default
data do (`overall`)."""

SOURCES = (
    Source(f"quick (3k steps, 20 episodes per task, {CONDITIONED_DATA})", Path("results/quick/experiments"),
           "quick", (CONDITIONED,), data=CONDITIONED_DATA),
    Source(f"12k (4x quick steps, quick sizes, {CONDITIONED_DATA})", Path("results/quick/locomotion-12k"), "quick",
           ("steps=12000", CONDITIONED), data=CONDITIONED_DATA),
    Source(f"cpu ({CONDITIONED_DATA} at the paper's sizes, 100k steps, batch 16 x 64, IQL 128x128)",
           Path("results/cpu/experiments"), "cpu", (CONDITIONED,), data=CONDITIONED_DATA),
    Source(f"paper ({CONDITIONED_DATA} at the paper's sizes, 100k steps, batch 16 x 256, IQL 256x256)",
           Path("results/paper/experiments"), "paper", (CONDITIONED,), data=CONDITIONED_DATA),
    # the default data, the paper's (App. C.2): one SAC expert per training task where the family has them
    Source(f"cpu ({PAPER_DATA}; 100k steps, batch 16 x 64, IQL 128x128)",
           Path("results/cpu/experiments"), "cpu"),
    Source(f"paper ({PAPER_DATA}; 100k steps, batch 16 x 256, IQL 256x256)",
           Path("results/paper/experiments"), "paper"),
    # HalfCheetahDir's per-task cells on its first experts (40k transitions each, a third of the paper's Oracle)
    Source("cpu, per-task experts of 40k transitions (HalfCheetahDir's first experts, since retrained)",
           Path("results/cpu/experts-40k"), "cpu", data="per-task experts, 40k", reports=(("main", "experts"),),
           experts="per-task"),
    Source("cpu, Table 3's dataset size read in total (50 episodes per training task), our expert's data",
           Path("results/cpu/total-data"), "cpu", ("episodes_per_task=50",), data="total size",
           reports=(("main", "experts"),), experts="conditioned"),
    Source("cpu, Table 3's dataset size read in total (50 episodes per training task), per-task experts' data "
           "(HalfCheetahDir's 40k experts)",
           Path("results/cpu/total-data"), "cpu", ("episodes_per_task=50",),
           data="total size, per-task experts, 40k", reports=(("main", "experts"),), experts="per-task"),
)


@dataclass
class Record:
    """One finished cell (or one probe of it): normalised scores where the run has references."""

    method: str
    family: str
    noise: float
    seed: int
    p_test: float
    p_train: float
    p_test_return: float
    context_length: int | None
    commit: str | None
    device: str | None
    wall_time_s: float
    job: str = ""
    """What shares its wall time: the seeds of one training job (one setting and method), or one probe."""
    drift: float = math.nan
    """The run's p_test drift over its scored window (bati.report.convergence): ~0 when converged."""
    normalised: bool = False
    """Whether its scores (and drift) are normalised: the run records reference returns."""

    @property
    def change(self) -> float:
        """p_test - p_train: how much the score falls when another policy collected the context."""
        return self.p_test - self.p_train


def source_plan(spec_name: str, source: Source, root: Path) -> StoredPlan | None:
    """The experiment's plan at a source's scale and data, as its report stored it (`bati.report.stored_plan`): of
    the report folders in the source's directory, the one whose plan has the source's settings, a method's own
    settings (`csro.club_negatives=...`) aside; of several, the one with the fewest of those (the experiment's
    report before a variant's, e.g. ER-TRL with an unbounded latent)."""
    experiment = dict(source.reports).get(spec_name, spec_name)
    found = []
    for path in sorted((root / source.out_dir).glob(f"*/{PLAN_FILE}")):
        plan = read_plan(path.parent)
        if plan.experiment == experiment and plan.scale == source.scale and \
                _data_settings(plan.settings) == _data_settings(source.settings):
            found.append(plan)
    return min(found, key=lambda plan: len(plan.settings), default=None)


def _raw(value):
    """A score where the run records no reference returns: its return as it is."""
    return value


def _data_settings(settings: tuple[str, ...]) -> tuple[str, ...]:
    """The settings that apply to every method (a method's own, `section.key=value`, aside), sorted."""
    return tuple(sorted(s.replace(" ", "") for s in settings if "." not in s.partition("=")[0]))


def gather(spec_name: str, source: Source, root: Path) -> list[Record]:
    """The records of the experiment's finished cells (and of their probes) at one scale and data."""
    plan = source_plan(spec_name, source, root)
    records = []
    for cell in plan.cells if plan is not None else ():
        if source.experts and cell.experts != source.experts:
            continue
        finished = cell.read()
        if finished is None:
            continue
        run = finished.run
        score = run.normalised if run.reference_returns else _raw
        training = (run.total_wall_time(), f"{cell.run_dir.parent}/{cell.method}")
        results = [(run.p_test_return, run.p_train_return, cell.eval_context_length, run.commit, *training)]
        if cell.probes:
            results = [(p["p_test_return"], p["p_train_return"], p["context_length"], p.get("commit"),
                        p.get("wall_time_s"), f"{cell.run_dir}/{p['context_length']}")
                       for _, p in finished.probes if "p_test_return" in p]
            if results:  # the first probe's record carries the run's training (its own seconds are ~1% of it)
                results[0] = (*results[0][:4], *training)
        drift = run_drift(run)  # a probe evaluates its cell's training run: the cell's drift
        for p_test, p_train, length, commit, wall, job in results:
            records.append(Record(cell.method, cell.family, cell.noise, cell.seed, score(p_test), score(p_train),
                                  p_test, length, commit, run.machine, wall or 0.0, job, drift,
                                  bool(run.reference_returns)))
    return records

