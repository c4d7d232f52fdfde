"""The `bati data` commands on a rich console: a collection made or found (collect), a collection's manifest
(info), and the sha256 of every dataset file of the collections under a root (verify). Each command's
options are a dataclass here (the CLI is these dataclasses)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bati.cli_hints import DEFAULT_IN_DOC
from bati.data import store
from bati.envs import TaskSplit, get_family
from bati.errors import PartialFailure
from bati.experts.kinds import ExpertsKind


class CollectionDamaged(PartialFailure):
    """`bati data verify` found a damaged collection (the others are sound)."""


@dataclass
class CollectOptions:
    family: str
    scale: Literal["quick", "paper"] = "quick"
    """quick: 20 episodes per training task, 5 per context dataset; paper: App. C Table 3 sizes per task."""
    seed: int = 0
    """Seed of the train/test task split, the collector draws, the env resets and the expert's actions."""
    noise: Annotated[float | None, DEFAULT_IN_DOC] = None
    """Per-step noise eps of the envs (default: the family's)."""
    root: Path = Path("data")
    """Datasets root: the collection goes to <root>/<family>/<scale>-seed<seed>-eps<eps>/."""
    zoo_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where the family's expert is loaded from (default: the package zoo)."""
    workers: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Worker processes (default: all cores)"""
    tasks: Annotated[TaskSplit, tyro.conf.OmitArgPrefixes] = TaskSplit()
    """Which tasks train and test: counts (--n-train, --n-test) or parameter ranges (--train-range LOW HIGH)."""
    experts: Annotated[ExpertsKind | None, DEFAULT_IN_DOC] = None
    """Who collects: one SAC per training task (App. C.2), or the family's one task-conditioned SAC; each is its
    own collection (default: per-task where the family has per-task experts, else its one expert)."""


@dataclass
class InfoOptions:
    family: str
    scale: Literal["quick", "paper"] = "quick"
    seed: int = 0
    noise: float | None = None
    root: Path = Path("data")
    tasks: Annotated[TaskSplit, tyro.conf.OmitArgPrefixes] = TaskSplit()
    """The collection's task split (as given to `bati data collect`)."""
    experts: ExpertsKind | None = None
    """Which experts collected it (as given to `bati data collect`; default: the family's, as there)."""


@dataclass
class VerifyOptions:
    family: Annotated[str | None, DEFAULT_IN_DOC] = None
    """Only this family's collections (default: every collection under --root)."""
    scale: Annotated[Literal["quick", "paper"] | None, DEFAULT_IN_DOC] = None
    """Only collections of this scale (default: any)."""
    seed: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Only collections of this seed (default: any)."""
    noise: Annotated[float | None, DEFAULT_IN_DOC] = None
    """Only collections of this eps (default: any)."""
    root: Path = Path("data")


def collect_and_show(o: CollectOptions, *, console: Console) -> None:
    """Collect the datasets (progress bars on a terminal only) or find them collected; one line saying which."""
    from bati.data.collect import collect  # loads MuJoCo, which info and verify do without

    result = collect(o.family, o.scale, o.seed, o.noise, o.root, zoo_dir=o.zoo_dir, progress=console.is_terminal,
                     workers=o.workers, tasks=o.tasks, experts=o.experts)
    m = result.manifest
    how = "already collected" if result.cached else f"collected in {result.wall_time_s:.1f} s"
    console.print(
        f"{m['family']} {m['scale']} seed={m['seed']} eps={m['noise']:g}: {how}: "
        f"{m['transitions']:,} transitions ({m['n_episodes']} episodes per training task, "
        f"{m['n_context_episodes']} per context dataset) "
        f"in {result.path}",
        soft_wrap=True,
    )


def show_collection(o: InfoOptions, *, console: Console) -> None:
    """The collection's test tasks with their context collectors, and whether its files carry checksums."""
    path, m = store.inspect_collection(o.root, get_family(o.family), o.scale, o.seed, o.noise, o.tasks, o.experts)
    console.print(collectors_table(path, m))
    if store.has_checksums(m):
        console.print(f"{len(m['files'])} dataset files, each of its recorded size; `bati data verify` "
                      "compares their sha256", soft_wrap=True)
    else:
        console.print(f"no checksums (collected before format {store.CHECKSUM_FORMAT}): files not checked",
                      soft_wrap=True)


def collectors_table(path: Path, manifest: dict) -> Table:
    """One row per test task: its parameters and the training tasks whose experts collected its contexts."""
    m = manifest
    table = Table(title=f"{path} (commit {m['commit']}, {m['transitions']:,} transitions)")
    for column in ("test task", "task", "p_test collector (most different)", "p_train collector (most similar)"):
        table.add_column(column)
    for j, task in enumerate(m["test_tasks"]):
        d, s = m["p_test_most_different"][j], m["p_train_most_similar"][j]
        table.add_row(str(j), escape(str(task)), f"{d}: {escape(str(m['train_tasks'][d]))}",
                      f"{s}: {escape(str(m['train_tasks'][s]))}")
    return table


def verify_and_show(o: VerifyOptions, *, console: Console) -> None:
    """One line per collection found (ok, damaged with what is wrong, ...); CollectionDamaged if any is."""
    family = get_family(o.family) if o.family else None  # an unknown one is an error, not "none found"
    damaged, checked = [], 0
    for path, status, details in store.verify_collections(o.root, family, o.scale, o.seed, o.noise):
        checked += 1
        console.print(f"{status}: {escape(str(path))}" + (f": {escape('; '.join(details))}" if details else ""),
                      soft_wrap=True)
        if status == "damaged":
            damaged.append(path)
    if damaged:
        raise CollectionDamaged(f"{len(damaged)} of {checked} collection(s) damaged ("
                                + ", ".join(map(str, damaged)) + "); delete them and re-run `bati data collect`")
