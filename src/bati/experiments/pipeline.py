"""An experiment's pipeline: its plan (the spec made concrete: cells and their probes), then the stages that run
it (the sweep of its cells; each BATI run's likelihood split as its job ends; the probes of the finished cells).

`plan_experiment` expands a spec (`bati.experiments.specs`) at a scale; `run_experiment` runs what is not finished
(a sweep of the plan's cells: resumable, idempotent); the report is `bati.experiments.report`, which stores
the plan beside it (`Plan.stored`) for the readers that must not plan again (`bati claims`, `bati results`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from bati.envs import family_names, get_family
from bati.experiments.probes import has_task_table, likelihood_split_due, run_probe, save_likelihood_split
from bati.experiments.specs import SPECS, ExperimentError, Spec, default_seeds, status_file
from bati.experiments.sweep import Cell, Grid, SweepResult, expand, grids_record, record_lock, sweep
from bati.methods import training_of
from bati.report.probes import Probe
from bati.report.stored_plan import PlannedCell, StoredPlan
from bati.run_dir import check_seeds


@dataclass
class Part:
    """One part of a spec made concrete: its grid, the grid's cells and the probes run on them."""

    grid: Grid
    cells: list[Cell]
    probes: tuple[Probe, ...] = ()


@dataclass
class Plan:
    """A spec made concrete for a scale, seeds and overrides: its parts (grids and their cells) and its cells,
    each once (a cell of two parts gets both parts' probes)."""

    spec: Spec
    scale: str
    seeds: tuple[int, ...]
    parts: list[Part]
    settings: tuple[str, ...] = ()
    """The KEY=VALUE settings given beyond the spec's own."""
    cells: list[Cell] = field(init=False)
    probes: dict[str, tuple[Probe, ...]] = field(init=False)
    """Cell id -> its probes."""

    def __post_init__(self) -> None:
        self.cells, self.probes = [], {}
        for part in self.parts:
            for cell in part.cells:
                if cell.id not in self.probes:
                    self.cells.append(cell)
                self.probes[cell.id] = tuple(dict.fromkeys(self.probes.get(cell.id, ()) + part.probes))

    @property
    def grids(self) -> list[Grid]:
        return [part.grid for part in self.parts]

    def select(self, methods: tuple[str, ...] = (), families: tuple[str, ...] = ()) -> Plan:
        """The plan's cells of `methods` and `families` (default: all), in the order chosen (a short GPU session
        runs the methods it names first): the plan `plan_experiment` makes with them, without planning again
        (a family the plan lacks that the spec would take is an ExperimentError, as any the spec would not)."""
        spec_parts(self.spec, methods, families)  # a method or family the experiment lacks: one line
        missing = [f for f in families if f not in {f for part in self.parts for f in part.grid.families}]
        if missing:
            raise ExperimentError(f"the plan of {self.spec.name!r} has no cells of {', '.join(missing)}: plan with it")
        parts = []
        for part in self.parts:
            grid = part.grid
            keep_methods = tuple(m for m in dict.fromkeys(methods or grid.methods) if m in grid.methods)
            keep_families = tuple(f for f in dict.fromkeys(families or grid.families) if f in grid.families)
            if not keep_methods or not keep_families:
                continue
            noise_rank = {}  # a family's eps in the grid's order, then the methods in the order chosen
            for cell in part.cells:
                noise_rank.setdefault((cell.config.family, cell.config.noise), len(noise_rank))
            kept = [(i, cell) for i, cell in enumerate(part.cells)
                    if cell.config.method in keep_methods and cell.config.family in keep_families]
            kept.sort(key=lambda item: (keep_families.index(item[1].config.family),
                                        noise_rank[item[1].config.family, item[1].config.noise],
                                        keep_methods.index(item[1].config.method), item[0]))
            parts.append(Part(replace(grid, families=keep_families, methods=keep_methods),
                              [cell for _, cell in kept], part.probes))
        return Plan(self.spec, self.scale, self.seeds, parts, self.settings)

    def stored(self, selection: Plan | None = None) -> StoredPlan:
        """The plan as its report stores it (`bati.report.stored_plan`): what claims and results read;
        `selection`: the cells of it the report's command runs (default: all)."""
        cells = tuple(PlannedCell(cell.id, cell.label, c.family, c.method, c.seed, c.noise, c.eval_context_length,
                                  c.experts, c.out_dir, self.probes.get(cell.id, ()), cell.host)
                      for cell in self.cells for c in (cell.config,))
        chosen = tuple(cell.id for cell in (selection.cells if selection is not None else ()))
        chosen = () if set(chosen) == {cell.id for cell in self.cells} else chosen  # () is every cell
        return StoredPlan(self.spec.name, self.scale, self.seeds, self.settings, cells, chosen)


def plan_experiment(spec: Spec, scale: str, out_dir: Path, *, seeds: tuple[int, ...] | None = None,
                    settings: tuple[str, ...] = (), methods: tuple[str, ...] = (), families: tuple[str, ...] = (),
                    data_root: Path = Path("data")) -> Plan:
    """Expand `spec` at `scale`. `settings` (KEY=VALUE) apply to every cell but may not change what the
    spec itself sets; `methods` / `families` keep a subset of the spec's, in their order (the cells', hence the
    jobs' order). ExperimentError otherwise."""
    if scale not in spec.scales:
        raise ExperimentError(f"experiment {spec.name!r} has no {scale!r} scale; choose one of: {', '.join(spec.scales)}")
    try:
        seeds = check_seeds(default_seeds(spec, scale) if seeds is None else seeds)
    except ValueError as err:
        raise ExperimentError(str(err)) from err
    own = {s.partition("=")[0].strip().replace("-", "_") for part in spec.parts for s in part.settings}
    clash = sorted(own & {s.partition("=")[0].strip().replace("-", "_") for s in settings})
    if clash:
        raise ExperimentError(f"experiment {spec.name!r} sets {', '.join(clash)} itself; leave it out of --settings")
    parts = spec_parts(spec, methods, families)
    planned = []
    for part in parts:
        # a chosen subset runs in the order chosen (a short GPU session runs the methods it names first)
        keep_methods = tuple(m for m in dict.fromkeys(methods or part.methods) if m in part.methods)
        keep_families = tuple(f for f in dict.fromkeys(families or part.families) if f in part.families)
        if not keep_methods or not keep_families:
            continue
        grid = Grid(families=keep_families, methods=keep_methods, seeds=seeds, noises=part.noises, scales=(scale,),
                    settings=part.settings + tuple(settings))
        planned.append(Part(grid, expand(grid, out_dir, data_root), part.probes))
    return Plan(spec, scale, seeds, planned, tuple(settings))


def spec_parts(spec: Spec, methods: tuple[str, ...] = (), families: tuple[str, ...] = ()) -> tuple:
    """The spec's parts, with those it makes for a family of its own among `families` (`Spec.for_family`);
    ExperimentError (one line) for a method or family the experiment does not have."""
    own = [f for f in families if f not in {f for p in spec.parts for f in p.families} and f in family_names()]
    parts = spec.parts + (tuple(p for f in own for p in spec.for_family(get_family(f))) if spec.for_family else ())
    spec_methods = {m for p in spec.parts for m in p.methods}
    spec_families = {f for p in parts for f in p.families}
    for kind, chosen, allowed in (("method", methods, spec_methods), ("family", families, spec_families)):
        extra = [x for x in chosen if x not in allowed]
        if extra:
            hint = "" if kind == "method" else (
                " or any other family (`bati envs`: PointGoal, or one registered with register_family)" if spec.for_family else
                f" (a family of your own runs in: {', '.join(n for n, s in SPECS.items() if s.for_family)})")
            raise ExperimentError(f"experiment {spec.name!r} has no {kind} {', '.join(map(repr, extra))}; "
                                  f"its {kind} choices: {', '.join(sorted(allowed))}{hint}")
    return parts


@dataclass
class ExperimentResult:
    plan: Plan
    sweep: SweepResult
    probes_done: int
    probe_errors: dict[str, str]
    wall_time_s: float


def run_experiment(plan: Plan, out_dir: Path, *, data_root: Path = Path("data"), workers: int = 1,
                   backend: str = "local", address: str | None = None, show_progress: bool = True,
                   on_probe: Callable[[str], None] | None = None, locked: bool = False) -> ExperimentResult:
    """Run the plan's cells that are not finished (one sweep; where the spec keeps it, each BATI run's likelihood
    split as its job ends), then the probes of the finished ones, holding the experiment's sweep record all along
    (a second process on it is refused at once;
    `locked`: the caller holds `record_lock(out_dir, status_file(plan.spec))` already)."""
    if not locked:
        with record_lock(out_dir, status_file(plan.spec)):
            return run_experiment(plan, out_dir, data_root=data_root, workers=workers, backend=backend,
                                  address=address, show_progress=show_progress, on_probe=on_probe, locked=True)
    start = time.perf_counter()
    done, errors = 0, {}

    def split(cells) -> None:
        """The likelihood split of the cells' BATI runs where the spec keeps it and it is due. The split is
        the trained model's: bati-r and bati-auto share bati's training, so bati's run has it."""
        nonlocal done
        for cell in cells:
            c = cell.config
            if not (plan.spec.likelihood_split and has_task_table(c.method) and training_of(c.method) == c.method
                    and likelihood_split_due(c.out_dir, c.steps, c.eval_context_length)):
                continue
            label = f"{cell.label} likelihood"
            if on_probe is not None:
                on_probe(label)
            try:
                save_likelihood_split(c.out_dir, c.eval_context_length)
                done += 1
            except Exception as err:  # reported like a failed probe
                errors[label] = f"{type(err).__name__}: {err}"

    # each job's split right after it (its checkpoint is at hand; a session cut later keeps it), the probes after all
    result = sweep(plan.cells, out_dir, data_root=data_root, workers=workers, backend=backend, address=address,
                   show_progress=show_progress, status_file=status_file(plan.spec), locked=True, on_job_done=split,
                   record=grids_record(plan.grids))
    for cell in plan.cells:
        if result.status.get(cell.id) not in ("done", "skipped"):
            continue
        for probe in plan.probes.get(cell.id, ()):
            label = f"{cell.label} {probe.name}"
            if on_probe is not None:
                on_probe(label)
            try:
                run_probe(cell.config.out_dir, probe, cell.config.method if cell.host else None)
                done += 1
            except Exception as err:  # a failed probe is reported; the others go on
                errors[label] = f"{type(err).__name__}: {err}"
        split([cell])  # a skipped cell's split, where its checkpoint is at hand and none is saved
    return ExperimentResult(plan, result, done, errors, time.perf_counter() - start)
