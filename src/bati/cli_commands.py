"""The `bati` commands that collect data, train and evaluate (they import JAX): `bati.cli` parses them.

Each command is a dataclass (tyro makes its options from the fields) with a `run` that does the work on the
rich consoles of `bati.cli`; the commands that read results (report, claims, results) are in `bati.cli` itself.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Union

import tyro

from bati.cli import console, error_console
from bati.cli_hints import DEFAULT_IN_DOC
from bati.data.show import (
    CollectOptions,
    InfoOptions,
    VerifyOptions,
    collect_and_show,
    show_collection,
    verify_and_show,
)
from bati.envs import get_family
from bati.envs.listing import show_families
from bati.experiments.experiment import ExperimentJob, run_and_show_experiment
from bati.experiments.main_job import MainJob, run_and_show_main_job
from bati.experiments.probes import show_likelihood_split
from bati.experiments.sweep import SweepJob, sweep_and_show
from bati.experts.card import write_card
from bati.experts.kinds import ExpertsKind
from bati.experts.per_task import merge_per_task_experts
from bati.experts.train import ExpertTrainConfig, train_and_export
from bati.experts.zoo import ZOO_DIR
from bati.inference import infer_context
from bati.train_job import TrainJob, run_train_job


@dataclass
class Envs:
    """List the task families with their task spaces; with --family and --task, try one episode."""

    family: str | None = None
    """Show only this family (and, with --task, run one random-action episode in it)."""
    task: tuple[float, ...] | None = None
    """A task of the family, e.g. `--task 1.5` or `--task 0.6 0.8` for PointGoal."""
    noise: Annotated[float | None, DEFAULT_IN_DOC] = None
    """Per-step noise eps (default: the family's)."""

    def run(self) -> None:
        show_families(self.family, self.task, self.noise, console=console)


@dataclass
class ExpertsTrain(ExpertTrainConfig):
    """Train a family's task-conditioned SAC expert, or with --per-task one SAC per training task (checkpoints;
    re-running resumes). The export goes into the run directory's zoo/ unless --export-dir or --into-package
    says otherwise."""

    def run(self) -> None:
        train_and_export(self, console=console)


@dataclass
class ExpertsCard:
    """Evaluate a shipped expert on the 20 train / 20 test tasks and write its card."""

    family: str
    seed: int = 0
    """Seed of the train/test task split (the same as `bati data collect --seed`)."""
    zoo_dir: Path | None = None
    experts: Annotated[ExpertsKind | None, DEFAULT_IN_DOC] = None
    """Per-task experts (card in <zoo>/<family>/per-task/; the default where the family has them) or conditioned."""

    def run(self) -> None:
        card = write_card(self.family, self.seed, self.zoo_dir, self.experts)
        console.print(card["summary"])


@dataclass
class ExpertsMerge:
    """Join per-task experts trained in parts (`bati experts train --per-task --tasks ...`) into one export:
    the experts one program training every part's tasks would give."""

    family: str
    parts: tuple[Path, ...]
    """The parts' zoo directories (each holds <family>/per-task/, e.g. runs/experts/F-per-task/zoo)."""
    export_dir: Path | None = None
    """Zoo directory to write the merged experts into, as <export_dir>/<family>/per-task/."""
    into_package: bool = False
    """Write them into the package's own zoo instead (what later per-task collections of the family use)."""

    def run(self) -> None:
        if self.into_package == (self.export_dir is not None):
            raise ValueError("give either --export-dir or --into-package (where the merged experts go)")
        zoo = ZOO_DIR if self.into_package else self.export_dir
        meta = merge_per_task_experts(get_family(self.family), list(self.parts), zoo, package=self.into_package)
        console.print(f"{len(meta['task_indices'])} per-task experts of {self.family} (tasks {meta['task_indices']}, "
                      f"{meta['parts']} parts) written to {zoo}", soft_wrap=True)


def group(**commands):
    """A dataclass type whose single field selects one of `commands` (nested subcommands)."""
    options = tuple(Annotated[cls, tyro.conf.subcommand(name)] for name, cls in commands.items())
    return Annotated[Union[options], tyro.conf.arg(name="")]  # noqa: UP007 (Union of a built tuple)


@dataclass
class Experts:
    """Expert (context-collection) policies."""

    command: group(train=ExpertsTrain, merge=ExpertsMerge, card=ExpertsCard)

    def run(self) -> None:
        self.command.run()


@dataclass
class DataCollect(CollectOptions):
    """Collect a family's offline datasets (Eq. 9) and test contexts (Eq. 10) as Minari datasets (cached)."""

    def run(self) -> None:
        collect_and_show(self, console=console)


@dataclass
class DataInfo(InfoOptions):
    """Summarise a collection on disk (its manifest): tasks and context collectors."""

    def run(self) -> None:
        show_collection(self, console=console)


@dataclass
class DataVerify(VerifyOptions):
    """Recompute the sha256 of every dataset file of the collections under --root; name edited, truncated or
    missing files (exit code 1 when a collection is damaged)."""

    def run(self) -> None:
        verify_and_show(self, console=console)


@dataclass
class Data:
    """Offline datasets and context data (Minari)."""

    command: group(collect=DataCollect, info=DataInfo, verify=DataVerify)

    def run(self) -> None:
        self.command.run()


@dataclass
class Train(TrainJob):
    """Train one method on one family (offline, IQL core), evaluating on p_train / p_test contexts.
    Every setting of the run is an option (each method's under --bati., --csro., ...; IQL's under --iql.);
    re-running resumes."""

    def run(self) -> None:
        run_train_job(self, console=console)


@dataclass
class Run(MainJob):
    """The main job: data with the shipped experts, train BATI, BATI-R and Recon (or --methods) as a sweep,
    evaluate under context shift, then the report (table with rliable intervals, CSVs, curves) and one line
    reading it. A rerun trains only what is missing."""

    def run(self) -> None:
        run_and_show_main_job(self, console=console)


@dataclass
class Likelihood:
    """For a BATI run: task-inference error of Eq. 8 with the full, reward-only and state-only NLL (also
    written to RUN_DIR/likelihood.json)."""

    run_dir: Path
    context_length: int = 200

    def run(self) -> None:
        show_likelihood_split(self.run_dir, self.context_length, console=console)


@dataclass
class Infer:
    """Infer the task of a context file with a trained bati / bati-r / bati-auto run, and say if it is unknown.

    The context file is an .npz of observations (C, obs_dim), actions (C, action_dim), rewards (C,) and
    next_observations (C, obs_dim). Prints one JSON object: the training task that best explains the
    context (Eq. 8 over the table), its score (mean NLL per transition) and `unknown`: the score is above
    the `quantile` of the training tasks' own contexts' scores."""

    run_dir: Path
    context: Path
    quantile: float = 0.95

    def run(self) -> None:
        print(json.dumps(infer_context(self.run_dir, self.context, self.quantile), indent=2))


@dataclass
class Sweep(SweepJob):
    """Run a grid of training runs (families x methods x seeds x noises x scales); reruns do only what is missing."""

    def run(self) -> None:
        sweep_and_show(self, console=console, error_console=error_console)


@dataclass
class Experiment(ExperimentJob):
    """Run one of the paper's experiments (`bati experiment list` shows them) and write its report."""

    name: tyro.conf.Positional[str]
    """The experiment (main, noise, context-length, ...), or `list`."""

    def run(self) -> None:
        run_and_show_experiment(self, console=console, error_console=error_console)


COMMANDS = {"envs": Envs, "experts": Experts, "data": Data, "train": Train, "run": Run, "sweep": Sweep,
            "experiment": Experiment, "likelihood": Likelihood, "infer": Infer}
"""The commands that collect data, train and evaluate, in the order `bati --help` lists them."""
