"""`bati sweep`: a grid of training runs (cells) on a local process pool or on Ray, resumable.

A cell is one fully resolved `TrainConfig`; its identity is that whole config (where it lives
aside). Cells that differ only in their seed form one job, trained as one program vmapped over
the seeds (`train_seeds`). `sweep` runs cells (an experiment's plan hands its own down); `sweep_grid` expands a
grid into them once (`bati sweep`, `bati run`). Layout of a sweep directory:

    <out>/sweep.json                               the cells and their status (rewritten atomically)
    <out>/.sweep.json.lock                         held while a sweep writes that record
    <out>/<Family>/<scale>-eps<eps>-<hash>/<method>-seed<s>/   one run directory per cell

`<hash>` digests the cell's config without method and seed, so the runs of one setting sit side by
side (what `bati report` tabulates together). A finished cell (its eval.json holds the same config)
is skipped; a failed job is recorded with its error and the others go on; a rerun after a kill runs
only what is missing. One sweep at a time owns a status record: a second process on the same record is
refused at once (LockedError), as it would overwrite the first one's statuses with its own.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import sys
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import tyro

from bati.errors import BatiError, PartialFailure
from bati.experts.kinds import experts_label
from bati.io import atomic_write_json, hold_lock, rules_evaluated
from bati.config import (NOT_IDENTITY, ScaleName, TrainConfig, apply_settings, differing_settings, digest_view,
                         method_config_key, method_sections, section_readers, settable_names)

if TYPE_CHECKING:
    from bati.envs import TaskFamily

AXES = ("family", "method", "seed", "scale", "noise")
"""Grid axes; every other TrainConfig field can be set for all cells with `overrides`."""
NOT_OVERRIDABLE = AXES + ("out_dir", "data_root")


class SweepError(BatiError, ValueError):
    """A sweep that cannot start (bad grid, backend, directory): nothing was written."""


class SweepFailed(PartialFailure):
    """Some cells of a sweep (or probes of an experiment) failed; the others finished."""


@dataclass
class Grid:
    """families x methods x seeds x noises x scales, plus TrainConfig settings common to every cell."""

    families: tuple[str, ...] = ("PointGoal",)
    methods: tuple[str, ...] = ("bati", "bati-r", "recon")
    """Method names, or `all` for every method."""
    seeds: tuple[int, ...] = (0,)
    noises: tuple[float, ...] = ()
    """Per-step noise levels eps (empty: each family's default)."""
    scales: tuple[ScaleName, ...] = ("quick",)
    settings: tuple[str, ...] = ()
    """KEY=VALUE TrainConfig settings for every cell, e.g. `steps=12000 context_length=50
    iql.hidden_dims=[64,64] csro.club_weight=3` (values as JSON)."""

    def overrides(self) -> dict[str, Any]:
        """The settings as {TrainConfig field or `section.field`: value} (SweepError for a malformed or
        unknown one)."""
        names = settable_names()
        out: dict[str, Any] = {}
        for item in self.settings:
            key, sep, text = item.partition("=")
            key = key.strip().replace("-", "_")
            if not sep or not key:
                raise SweepError(f"setting {item!r} is not KEY=VALUE")
            if key not in names:
                plain = sorted(n for n in names if "." not in n and n not in NOT_OVERRIDABLE)
                raise SweepError(f"unknown setting {key!r}; settable: {', '.join(plain)}, and SECTION.FIELD of "
                                 f"{', '.join(dict.fromkeys(n.partition('.')[0] for n in sorted(names) if '.' in n))}")
            if key.partition(".")[0] in NOT_OVERRIDABLE:
                raise SweepError(f"{key} cannot be set per cell: use the grid's axes (families, methods, seeds, "
                                 "noises, scales), --out-dir and --data-root")
            if key in out:
                raise SweepError(f"setting {key} is given twice ({item!r} after {key}={json.dumps(out[key])}): "
                                 "give it once (several values are several sweeps)")
            try:
                value = json.loads(text)
            except ValueError:
                value = text
            out[key] = tuple(value) if isinstance(value, list) else value
        return out


@dataclass(frozen=True)
class Cell:
    config: TrainConfig  # resolved, out_dir set
    family: TaskFamily  # the config's family object, looked up once by the grid's expansion
    host: str = ""
    """The method whose run evaluates this cell's method as a test-time rule (bati-r and bati-auto in a bati run of
    the grid: config.out_dir is that run's); "": the cell is a run of its own."""

    @cached_property  # (a digest costs a config's record; plans and reports ask for it many times)
    def id(self) -> str:
        return config_digest(self.config, exclude=NOT_IDENTITY, family=self.family)

    @cached_property
    def job_key(self) -> str:
        return config_digest(self.config, exclude=NOT_IDENTITY + ("seed",), family=self.family)

    @property
    def label(self) -> str:
        c = self.config
        return f"{c.family}/{c.method}/seed{c.seed}"


def config_digest(config: TrainConfig, exclude: Iterable[str] = (), family: TaskFamily | None = None) -> str:
    """A short stable digest of a config's settings (JSON with sorted keys). Settings added later count
    only when they differ from their old value, renamed ones under their old names (`digest_view`), so
    older digests stay valid. `family`: the config's family object, where the caller has it."""
    settings = {k: v for k, v in digest_view(config.record(family)).items() if k not in set(exclude)}
    return hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:10]


def expand(grid: Grid, out_dir: Path, data_root: Path = Path("data")) -> list[Cell]:
    """The grid's cells, each a resolved config with its run directory; bad values raise SweepError."""
    from bati.envs import get_family
    from bati.methods import method_names

    for axis in ("families", "methods", "seeds", "scales"):
        if not getattr(grid, axis):
            raise SweepError(f"the grid's {axis} are empty: give at least one")
    overrides = grid.overrides()
    try:
        methods = method_names(grid.methods)
        # A method's hyperparameter (`focal.distance=...`) goes to the cells of the methods that read its section.
        sections = {key: key.partition(".")[0] for key in overrides if key.partition(".")[0] in method_sections()}
        for key, section in sections.items():
            if section not in {method_config_key(m) for m in methods}:
                raise SweepError(f"{key} is read by {', '.join(section_readers(section))} only; "
                                 f"none of the grid's methods ({', '.join(methods)}) reads it")
        families = {family.name: family for family in map(get_family, dict.fromkeys(grid.families))}
        cells = []
        for family in families.values():
            noises = list(dict.fromkeys(grid.noises)) or [None]
            for scale in dict.fromkeys(grid.scales):
                for noise in noises:
                    for method in methods:
                        for seed in dict.fromkeys(grid.seeds):
                            own = {k: v for k, v in overrides.items()
                                   if k not in sections or sections[k] == method_config_key(method)}
                            config = apply_settings(TrainConfig(family=family.name, method=method, seed=seed,
                                                                scale=scale, noise=noise, data_root=data_root),
                                                    own).resolve(family).config
                            cells.append(Cell(replace(config, out_dir=run_dir(out_dir, config, family)), family))
    except (ValueError, TypeError) as err:  # TaskError is a ValueError
        raise SweepError(str(err)) from err
    return hosted(cells)


def hosted(cells: list[Cell]) -> list[Cell]:
    """The cells with each test-time rule's (bati-r, bati-auto) evaluated in the run of a grid cell it trains as
    (same setting and seed; bati's run first, else the first of them that can): its run directory is that run's,
    `host` its method. A run can evaluate a rule from its start only: one that has evaluations without the rule does
    not host it, and a rule's cell whose own directory holds a run already (trained alone, or a folder of the layout
    before) stays that run."""
    from bati.methods import training_of

    groups: dict[tuple, list[Cell]] = {}  # one setting, seed and training: the training's own method first
    for cell in cells:
        c = cell.config
        if not c.datasets:
            groups.setdefault((c.out_dir.parent, c.seed, training_of(c.method)), []).append(cell)
    hosts: dict[int, Cell] = {}
    for group in groups.values():
        runs: list[Cell] = []
        for cell in sorted(group, key=lambda cell: cell.config.method != training_of(cell.config.method)):
            host = next((run for run in runs if _can_host(run.config, cell.config)), None)
            if host is None:
                runs.append(cell)
            else:
                hosts[id(cell)] = host
    return [Cell(replace(cell.config, out_dir=hosts[id(cell)].config.out_dir), cell.family,
                 hosts[id(cell)].config.method) if id(cell) in hosts else cell for cell in cells]


def _can_host(run: TrainConfig, rule: TrainConfig) -> bool:
    """Whether the run of `run` can evaluate `rule`'s method as a test-time rule: the same config but the method, no
    run in the rule's own directory, and no evaluations of the run without it."""
    return (replace(rule, method=run.method, out_dir=run.out_dir) == run and not (rule.out_dir / "config.json").exists()
            and not _evaluated_without(run.out_dir, rule.method))


def _rules_evaluated(run_dir: Path) -> frozenset[str] | None:
    """`bati.io.rules_evaluated` of the run in `run_dir`; None also for a log that cannot be read (the run's resume
    says what is wrong with it, not the plan)."""
    try:
        return rules_evaluated(run_dir)
    except (OSError, ValueError):
        return None


def _evaluated_without(run_dir: Path, rule: str) -> bool:
    """Whether the run in `run_dir` has evaluations without the test-time rule `rule`."""
    held = _rules_evaluated(run_dir)
    return held is not None and rule not in held


def run_dir(out_dir: Path, config: TrainConfig, family: TaskFamily | None = None) -> Path:
    setting = config_digest(config, exclude=NOT_IDENTITY + ("method", "seed"), family=family)[:8]
    return Path(out_dir) / config.family / f"{config.scale}-eps{config.noise:g}-{setting}" / \
        f"{config.method}-seed{config.seed}"


def finished(cell: Cell) -> bool:
    """Whether the cell's run has an eval.json (a test-time rule's cell: holding the rule's evaluations), whatever its
    config: what a queue asks before it starts a job (`is_done` also checks the config)."""
    try:
        raw = json.loads((cell.config.out_dir / "eval.json").read_text())
    except (OSError, ValueError):
        return False
    return not cell.host or cell.config.method in ((raw.get("rules") if isinstance(raw, dict) else None) or {})


def is_done(cell: Cell) -> bool:
    """The cell's run finished with this very config (its eval.json says so; a test-time rule's cell: and holds the
    rule's evaluations)."""
    path = cell.config.out_dir / "eval.json"
    try:
        raw = json.loads(path.read_text())
        saved = raw.get("config", {})
    except (OSError, ValueError, AttributeError):
        return False
    if cell.host and cell.config.method not in (raw.get("rules") or {}):
        return False
    current = replace(cell.config, method=cell.host or cell.config.method).record(cell.family)
    return isinstance(saved, dict) and not differing_settings(saved, current, [k for k in current if k not in NOT_IDENTITY])


# --- jobs ------------------------------------------------------------------------------------
@dataclass
class Job:
    """The cells of one setting and method, differing only in their seeds: one vmapped program; `rules`: the cells of
    test-time rules evaluated in its runs (`Cell.host`), done when the runs are."""

    cells: list[Cell]
    rules: list[Cell] = field(default_factory=list)

    @property
    def config(self) -> TrainConfig:
        return self.cells[0].config

    @property
    def seeds(self) -> tuple[int, ...]:
        return tuple(c.config.seed for c in self.cells)

    @property
    def rule_methods(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(c.config.method for c in self.rules))

    @property
    def label(self) -> str:
        c = self.config
        return f"{c.family} {c.scale} eps={c.noise:g} {c.method} seeds {list(self.seeds)}"


def make_jobs(cells: list[Cell], share_training: bool = True) -> list[Job]:
    """The cells grouped into jobs (one per setting and method); with `share_training`, a test-time rule's cells
    (`Cell.host`) join the job of their host's run, which trains (its cells made here where the plan's selection
    left them out: asking for bati-r trains the bati run that evaluates it)."""
    jobs: dict[str, Job] = {}
    for cell in cells:
        if cell.host and share_training:
            host = Cell(replace(cell.config, method=cell.host), cell.family)
            jobs.setdefault(host.job_key, Job([])).rules.append(cell)
        else:
            jobs.setdefault(cell.job_key, Job([])).cells.append(cell)
    for job in jobs.values():
        seeds = {c.config.seed for c in job.cells}
        for rule in job.rules:
            if rule.config.seed not in seeds:
                seeds.add(rule.config.seed)
                job.cells.append(Cell(replace(rule.config, method=rule.host), rule.family))
    return list(jobs.values())


def run_job(config: TrainConfig, seeds: tuple[int, ...], runs_dir: Path, references: dict | None = None,
            rules: tuple[str, ...] = ()) -> list[dict]:
    """What a worker runs: the job's seeds in one program (no progress bars: the sweep shows its table).
    `references`: the collection's random and expert returns when an earlier job computed them; `rules`: the
    test-time rules evaluated in its runs (Job.rules)."""
    from bati.train import train_seeds

    summaries = train_seeds(replace(config, out_dir=None), seeds, show_progress=False, runs_dir=runs_dir,
                            references=references, rules=rules)
    return [{k: s[k] for k in ("seed", "p_train_return", "p_test_return", "reference_returns") if k in s}
            for s in summaries]


def collection_key(cell: Cell) -> str:
    """What a run's reference returns depend on: its collection (family, sizes, seed, eps, tasks, root) and
    the expert (zoo); jobs with the same key share them (computed by the first, passed to the others)."""
    config = cell.config
    return json.dumps([config.family, config.data_scale, config.data_seed, config.noise, str(config.data_root),
                       config.episodes_per_task, config.context_episodes, str(config.task_split()),
                       str(config.zoo_dir), config.record(cell.family).get("family_version"), bool(config.datasets)]
                      + ([config.experts] if config.experts != "conditioned" else []))


def check_experts(cells: list[Cell]) -> None:
    """Every run needs its family's expert (reference returns, the collection, DPT's labels): a missing one
    is the zoo's one-line error before anything is written."""
    from bati.data.collect import load_expert

    families = {c.config.family: c.family for c in cells}
    for family, zoo_dir, experts in sorted({(c.config.family, c.config.zoo_dir, c.config.experts)
                                            for c in cells if not c.config.datasets}, key=str):
        load_expert(families[family], zoo_dir, experts)


def prepare_data(cells: list[Cell], progress: bool, check_only: bool = False) -> None:
    """Collect every collection the cells need once, up front (in parallel over tasks), so that
    workers only read data and never collect the same collection twice. `check_only`: collect nothing,
    raise what collecting would raise before any work (e.g. a collection of other sizes in the data root)."""
    needed = {(cell.config.resolve(cell.family).collection,
               None if cell.config.zoo_dir is None else str(cell.config.zoo_dir))
              for cell in cells if not cell.config.datasets}
    for collection, zoo_dir in sorted(needed, key=lambda n: (n[0].family.name, str(n))):
        collection.collect(progress, zoo_dir, check_only=check_only)


# --- the sweep -------------------------------------------------------------------------------
@dataclass
class SweepResult:
    out_dir: Path
    status: dict[str, str]  # cell id -> done | failed | skipped (done before)
    errors: dict[str, str]
    wall_time_s: float

    def count(self, status: str) -> int:
        return sum(s == status for s in self.status.values())


@dataclass
class SweepJob:
    """`bati sweep`'s settings (the CLI is this dataclass): the grid and how and where to run it."""

    grid: Annotated[Grid, tyro.conf.OmitArgPrefixes]
    out_dir: Path = Path("runs/sweep")
    """Sweep directory: sweep.json (cells and status) and one run directory per cell."""
    data_root: Path = Path("data")
    workers: int = 1
    """Jobs at a time (local: processes; several may share one GPU). A job trains one setting's seeds together."""
    backend: Literal["local", "ray"] = "local"
    address: str | None = None
    """Ray cluster address (backend ray; default: a local Ray)."""
    report: bool = True
    """Finish with `bati report OUT_DIR`."""

def record_lock(out_dir: Path, status_file: str = "sweep.json"):
    """The lock a sweep holds on its status record (a context manager; LockedError if another process
    holds it). Callers that do more under the same record, such as an experiment's probes, take it
    themselves and pass `locked=True` to `sweep`."""
    out_dir = Path(out_dir)
    check_out_dir(out_dir)
    return hold_lock(out_dir / f".{status_file}.lock", f"the sweep record {out_dir / status_file}")


def sweep_grid(grid: Grid | list[Grid], out_dir: Path, *, data_root: Path = Path("data"), **options) -> SweepResult:
    """`sweep` over the cells of `grid` (or of several grids), expanded once here; the status record keeps the
    grid. `options`: those of `sweep`."""
    grids = [grid] if isinstance(grid, Grid) else list(grid)
    if not grids:
        raise SweepError("no grid to sweep")
    cells = list({c.id: c for g in grids for c in expand(g, out_dir, data_root)}.values())
    return sweep(cells, out_dir, data_root=data_root, record=grids_record(grids), **options)


def grids_record(grids: list[Grid]) -> dict:
    """The grids a sweep's cells come from, as its status record keeps them."""
    return {"grid": asdict(grids[0])} if len(grids) == 1 else {"grids": [asdict(g) for g in grids]}


def sweep(cells: list[Cell], out_dir: Path, *, data_root: Path = Path("data"), workers: int = 1,
          backend: Literal["local", "ray"] = "local", address: str | None = None,
          show_progress: bool = True, status_file: str = "sweep.json", locked: bool = False,
          on_job_done: Callable[[list[Cell]], None] | None = None, record: dict | None = None) -> SweepResult:
    """Run every one of `cells` (a grid's: `sweep_grid`; an experiment plan's) that is not finished yet; see the
    module docstring. `status_file` names the status record in `out_dir` (experiments sharing one directory, and
    so their common cells, keep one each); `locked`: the caller already holds its `record_lock`; `on_job_done`:
    called with a finished job's done cells (its rules' too) once they are recorded, before the next
    job starts (an experiment's per-run work, kept when a session ends before the sweep does); `record`: what the
    status record says the cells come from (their grids)."""
    out_dir = Path(out_dir)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise SweepError(f"workers must be an integer >= 1, got {workers!r}")
    if backend not in ("local", "ray"):
        raise SweepError(f"unknown backend {backend!r}; choose local or ray")
    check_out_dir(out_dir)
    if not cells:
        raise SweepError("no cell to sweep")
    if not locked:
        with record_lock(out_dir, status_file):
            return sweep(cells, out_dir, data_root=data_root, workers=workers, backend=backend, address=address,
                         show_progress=show_progress, status_file=status_file, locked=True, on_job_done=on_job_done,
                         record=record)
    start = time.perf_counter()
    ray = connect_ray(address) if backend == "ray" else None
    header = {**(record or {}), "data_root": str(data_root), "backend": backend, "workers": workers}
    progress = _SweepStatus(cells, out_dir / status_file, header, on_job_done)
    pending = [c for c in cells if progress.status[c.id] == "pending"]
    jobs = make_jobs(pending)
    check_experts(pending)
    prepare_data(pending, progress=False, check_only=True)  # before the status file is written
    progress.record()
    if jobs:
        prepare_data(pending, progress=show_progress)
    progress.table = LiveTable(cells, progress.status, show_progress)
    with progress.table:
        if ray is not None:
            _run_on_ray(ray, jobs, workers, progress.arguments, progress.running, progress.finished)
        else:
            _run_locally(jobs, workers, progress.arguments, progress.running, progress.finished)
    return SweepResult(out_dir, dict(progress.status), progress.errors, time.perf_counter() - start)


class _SweepStatus:
    """A sweep's cells as its jobs run: each cell's status and error, the status file (rewritten at each change),
    the live table, and the reference returns each collection's first job computes for the others."""

    def __init__(self, cells: list[Cell], path: Path, header: dict,
                 on_job_done: Callable[[list[Cell]], None] | None):
        self.cells, self.path, self.header, self.on_job_done = cells, path, header, on_job_done
        self.status = {c.id: ("skipped" if is_done(c) else "pending") for c in cells}
        self.errors: dict[str, str] = {}
        self.references: dict[str, dict] = {}  # collection -> its random and expert returns, computed once
        self.table: LiveTable | None = None

    def record(self) -> None:
        atomic_write_json(self.path, {**self.header, "cells": {
            c.id: {"label": c.label, "run_dir": str(c.config.out_dir), "status": self.status[c.id],
                   **({"error": self.errors[c.id]} if c.id in self.errors else {})} for c in self.cells}})

    def arguments(self, job: Job) -> tuple:
        """run_job's arguments: the job's rules, and those its runs evaluated so far (a run resumed without
        them would go on without them, and they could not be evaluated in it any more)."""
        rules = job.rule_methods + tuple(r for c in job.cells for r in sorted(_rules_evaluated(c.config.out_dir) or ())
                                         if r not in job.rule_methods)
        return (job.config, job.seeds, job.config.out_dir.parent, self.references.get(collection_key(job.cells[0])),
                tuple(dict.fromkeys(rules)))

    def running(self, job: Job) -> None:
        for cell in job.cells + job.rules:
            if cell.id in self.status:  # (a host's cell made for a rule of the selection is not the plan's)
                self.status[cell.id] = "running"
        self.table.refresh()
        self.table.log(job, "running")

    def finished(self, job: Job, error: str | None, summaries: list[dict] | None = None) -> None:
        for cell in (c for c in job.cells + job.rules if c.id in self.status):
            self.status[cell.id] = "failed" if error else "done"
            if error:
                self.errors[cell.id] = error
        if summaries and summaries[0].get("reference_returns"):
            self.references.setdefault(collection_key(job.cells[0]), summaries[0]["reference_returns"])
        self.record()
        self.table.refresh()
        self.table.log(job, f"failed ({error})" if error else "done")
        if self.on_job_done is not None and not error:
            self.on_job_done([cell for cell in job.cells + job.rules if self.status.get(cell.id) == "done"])


def sweep_and_show(job: SweepJob, *, console, error_console) -> None:
    """`bati sweep`: the sweep (its live table only on a terminal), one line counting its cells, each failed
    cell's error on `error_console`, then `bati report` over it unless `job.report` is False or nothing
    finished; SweepFailed if a cell failed."""
    from rich.markup import escape

    from bati.report.build import build_and_show_report

    result = sweep_grid(job.grid, job.out_dir, data_root=job.data_root, workers=job.workers, backend=job.backend,
                        address=job.address, show_progress=console.is_terminal)
    counts = {s: result.count(s) for s in ("done", "skipped", "failed")}
    console.print(f"sweep {result.out_dir}: {counts['done']} cell(s) run, {counts['skipped']} already done, "
                  f"{counts['failed']} failed, in {result.wall_time_s / 60:.1f} min", soft_wrap=True)
    for cell_id, error in result.errors.items():
        error_console.print(f"[red]failed[/] {cell_id}: {escape(error)}", soft_wrap=True)
    if job.report and counts["done"] + counts["skipped"]:
        build_and_show_report(job.out_dir, console=console)
    if counts["failed"]:
        raise SweepFailed(f"{counts['failed']} cell(s) failed; their errors are in {result.out_dir}/sweep.json; "
                          "rerun the same command to retry them")

def _describe(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"


def _run_locally(jobs: list[Job], workers: int, arguments: Callable, running: Callable, finished: Callable) -> None:
    if workers == 1:  # in this process, one job after the other
        for job in jobs:
            running(job)
            try:
                summaries = run_job(*arguments(job))
            except Exception as err:  # a failed job is recorded; the sweep goes on
                traceback.print_exc()
                finished(job, _describe(err))
            else:
                finished(job, None, summaries)
        return
    from concurrent.futures import FIRST_COMPLETED, wait

    from bati.processes import spawned_pool

    with spawned_pool(workers) as pool:  # several jobs may share one GPU
        queue, futures = list(jobs), {}
        while queue or futures:
            while queue and len(futures) < workers:
                job = queue.pop(0)
                futures[pool.submit(run_job, *arguments(job))] = job
                running(job)
            done, _ = wait(futures, return_when=FIRST_COMPLETED)
            for future in done:
                err = future.exception()
                finished(futures.pop(future), _describe(err) if err else None, None if err else future.result())


def connect_ray(address: str | None):
    """Ray, connected (a local cluster when `address` is None); SweepError when it cannot be."""
    try:
        import ray
    except ImportError as err:
        raise SweepError('the Ray backend needs Ray: pip install -e ".[ray]"') from err
    if address and address != "auto":
        host, _, port = address.rpartition(":")
        try:
            with socket.create_connection((host or "127.0.0.1", int(port)), timeout=3):
                pass
        except (OSError, ValueError) as err:
            raise SweepError(f"cannot reach a Ray cluster at {address!r} ({err}); start one with `ray start --head` "
                             "or leave --address out for a local one") from err
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    ray.init(address=address, include_dashboard=False, ignore_reinit_error=True, log_to_driver=False,
             runtime_env={"env_vars": {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}})
    return ray


def _run_on_ray(ray, jobs: list[Job], workers: int, arguments: Callable, running: Callable,
                finished: Callable) -> None:
    remote = ray.remote(num_cpus=1, max_retries=0)(run_job)
    futures = {}
    for job in jobs:  # Ray schedules them on the cluster's CPUs; at most `workers` run from this sweep
        while len(futures) >= workers:
            _ray_collect(ray, futures, finished)
        futures[remote.remote(*arguments(job))] = job
        running(job)
    while futures:
        _ray_collect(ray, futures, finished)


def _ray_collect(ray, futures: dict, finished: Callable) -> None:
    (ref,), _ = ray.wait(list(futures), num_returns=1)
    job = futures.pop(ref)
    try:
        summaries = ray.get(ref)
    except Exception as err:  # RayTaskError wraps the job's own exception
        cause = getattr(err, "cause", None) or err
        finished(job, _describe(cause))
    else:
        finished(job, None, summaries)


def check_out_dir(out_dir: Path) -> None:
    """The sweep directory must be a directory we can write, outside the bati package (SweepError otherwise,
    nothing written)."""
    from bati.io import PathError, check_outside_package

    try:
        check_outside_package(out_dir, "the sweep directory")
    except PathError as err:
        raise SweepError(str(err)) from err
    existing = next((p for p in (out_dir, *out_dir.parents) if p.exists()), None)
    if out_dir.exists() and not out_dir.is_dir():
        raise SweepError(f"the sweep directory {out_dir} is a file")
    if existing is not None and existing != out_dir and not existing.is_dir():
        raise SweepError(f"cannot create the sweep directory {out_dir}: {existing} is a file")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise SweepError(f"the sweep directory {out_dir} is not writable ({existing} is not)")


def cell_data(config) -> str:
    """Which data a cell trains on, as the live table and log lines show it: the experts, and the episodes per
    training task where a setting changes them."""
    size = f", {config.episodes_per_task} episodes per task" if config.episodes_per_task is not None else ""
    return experts_label(config.experts, config.family) + size


class LiveTable:
    """A live table of the cells per job while the sweep runs (pending / running / done / failed)."""

    def __init__(self, cells: list[Cell], status: dict[str, str], enabled: bool):
        self.cells, self.status, self.enabled = cells, status, enabled
        self.live = None
        self.started: dict[int, float] = {}  # a job's start (perf_counter), for the plain log lines

    def render(self):
        from rich.table import Table

        counts = {s: sum(v == s for v in self.status.values()) for s in ("pending", "running", "done", "failed",
                                                                          "skipped")}
        table = Table(title="bati sweep: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n))
        for column in ("family", "scale", "eps", "data", "method", "seeds", "steps", "status"):
            table.add_column(column)
        style = {"done": "green", "failed": "red", "running": "yellow", "skipped": "dim"}
        for job in make_jobs(self.cells, share_training=False):
            states = sorted({self.status[c.id] for c in job.cells})
            text = "/".join(states)
            c = job.config
            table.add_row(c.family, c.scale, f"{c.noise:g}", cell_data(c), c.method, " ".join(map(str, job.seeds)),
                          self.progress(job) if text == "running" else f"{c.steps:,}",
                          f"[{style.get(text, '')}]{text}" if text in style else text)
        return table

    def __rich__(self):  # rich's Live draws the table afresh at each refresh: a running job's steps move
        return self.render()

    def progress(self, job: Job) -> str:
        """A running job's logged steps of its total and the time left at its rate since this sweep started it
        ("12,300 / 100,000, ~41 min left"); its total alone before its first log line."""
        total, started = job.config.steps, self.started.get(id(job))
        step, log = 0, job.cells[0].config.out_dir / "metrics.jsonl"
        try:
            with open(log, "rb") as file:
                file.seek(max(0, log.stat().st_size - 4096))
                lines = file.read().decode(errors="replace").splitlines()
        except OSError:  # no log yet: the total alone
            lines = []
        for line in reversed(lines):  # the last whole line (the newest may be half written)
            try:
                step = int(json.loads(line)["step"])
                break
            except (ValueError, KeyError, TypeError):
                continue
        done = f"{step:,} / {total:,}"
        if not step or started is None or step >= total:
            return done
        left = (time.perf_counter() - started) * (total - step) / step
        return f"{done}, ~{left / 60:.0f} min left"

    def refresh(self) -> None:
        if self.live is not None:
            self.live.refresh()

    def log(self, job: Job, state: str) -> None:
        """Without the live table (output to a file or a pipe, e.g. a background run's log): one line on stderr
        per job as it starts and as it ends, with its wall time, so a log shows where a sweep stands."""
        now = time.perf_counter()
        started = self.started.setdefault(id(job), now)
        if self.enabled:
            return
        c = job.config
        rules = ", ".join(job.rule_methods)
        seeds = " ".join(map(str, job.seeds))
        took = "" if state == "running" else f" after {(now - started) / 60:.1f} min"
        print(f"[{time.strftime('%H:%M:%S')}] sweep: {c.family} {c.scale} eps {c.noise:g} ({cell_data(c)}) {c.method} "
              f"seeds {seeds}"
              f"{f' (evaluating {rules} too)' if rules else ''}: {state}{took}", file=sys.stderr, flush=True)

    def __enter__(self):
        if self.enabled:
            from rich.live import Live

            self.live = Live(self, refresh_per_second=1)
            self.live.__enter__()
        return self

    def __exit__(self, *exc):
        if self.live is not None:
            self.live.__exit__(*exc)
        return False
