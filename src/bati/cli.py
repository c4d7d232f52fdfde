"""The `bati` command line: one subcommand per verb (tyro over dataclasses, rich output)."""

from __future__ import annotations

import json
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Union

import tyro
from rich.console import Console
from rich.markup import escape

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
from bati.errors import BatiWarning, PartialFailure
from bati.experiments.claims import write_and_show_claims
from bati.experiments.experiment import ExperimentJob, run_and_show_experiment
from bati.experiments.index import update_results
from bati.experiments.main_job import MainJob, run_and_show_main_job
from bati.experiments.probes import show_likelihood_split
from bati.experiments.sweep import SweepJob, sweep_and_show
from bati.experts.card import write_card
from bati.experts.kinds import ExpertsKind
from bati.experts.per_task import merge_per_task_experts
from bati.experts.train import ExpertTrainConfig, train_and_export
from bati.experts.zoo import ZOO_DIR
from bati.inference import infer_context
from bati.io import git_commit
from bati.processes import TERMINATED_EXIT_CODE, Terminated, sigterm_as_interrupt
from bati.report.build import build_and_show_report
from bati.train_job import TrainJob, run_train_job
from bati.usage import parse

console = Console()
# Errors go to stderr on one line, whatever the terminal width (soft_wrap: no hard line breaks).
error_console = Console(stderr=True, soft_wrap=True)


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


@dataclass
class Report:
    """Tables (Markdown + CSV) and learning curves (PNG) from the eval.json files under a directory."""

    results_dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RESULTS_DIR")]
    """Directory searched recursively for runs' eval.json files."""
    out_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where report.md, the CSVs and PNGs go (default: RESULTS_DIR/report)."""

    def run(self) -> None:
        build_and_show_report(self.results_dir, self.out_dir, console=console)


@dataclass
class Claims:
    """Each of the paper's claims decided by rliable intervals over the committed runs, at every scale."""

    root: Path = Path(".")
    """The project directory whose results/ holds the experiments (quick, 12k, cpu, paper)."""
    out: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where the page goes (default: ROOT/docs/claims.md)."""

    def run(self) -> None:
        write_and_show_claims(self.root, self.out, console=console)


@dataclass
class Results:
    """The committed results indexed: results/README.md, docs/results.md and the README's headline table."""

    root: Path = Path(".")
    """The project directory whose results/ holds the studies."""
    reports: bool = False
    """First write every experiment study's report again from its cells (report-only)."""
    pack: bool = False
    """First pack every finished run's metrics.jsonl into metrics.jsonl.gz (floats to 4 significant digits):
    for a results folder kept in version control."""

    def run(self) -> None:
        update_results(self.root, self.reports, self.pack, console=console)


COMMANDS = {"envs": Envs, "experts": Experts, "data": Data, "train": Train, "run": Run, "sweep": Sweep,
            "experiment": Experiment, "likelihood": Likelihood, "infer": Infer, "report": Report,
            "claims": Claims, "results": Results}


def main(argv: list[str] | None = None) -> int:
    """Run one command. Every failure a user can cause or meet (bad input, a missing, damaged or locked
    file, an OS error such as a full disk) is one line on stderr, exit code 2; a sweep with failed cells
    or a damaged collection found by `bati data verify`: exit code 1; Ctrl-C 130 and SIGTERM 143, both after
    the same clean-up (a sweep's workers stopped, locks released), so the same command resumes."""
    from bati.envs import TaskError
    from bati.errors import BatiError, describe_os_error

    args = sys.argv[1:] if argv is None else [str(a) for a in argv]
    for option in NEEDS_A_VALUE:  # an empty list there would silently mean the default
        for i, arg in enumerate(args):
            if arg == option and (i + 1 == len(args) or args[i + 1].startswith("--")):
                return _error(f"{option} needs at least one value (e.g. {option} my_data/task-0)", 2)
    try:
        command = parse(COMMANDS, argv, lambda line: _error(line, 2))
    except SystemExit as exit_:
        return exit_.code if isinstance(exit_.code, int) else 2
    git_commit()  # the running code's commit is read now, whatever is committed while the command runs
    with warnings.catch_warnings(), sigterm_as_interrupt():
        warnings.simplefilter("always", BatiWarning)
        warnings.showwarning = _show_warning(warnings.showwarning)
        try:
            command.run()
        except PartialFailure as err:
            return _error(str(err), 1)
        except OSError as err:  # before ValueError: FileNotFoundError, PermissionError, disk full, ...
            return _error(describe_os_error(err), 2)
        except (BatiError, TaskError, ValueError) as err:
            return _error(str(err), 2)
        except Terminated:  # SIGTERM (kill, a scheduler): the same clean-up as Ctrl-C
            return _stopped(argv, _error("terminated; run the same command again to resume", TERMINATED_EXIT_CODE))
        except KeyboardInterrupt:
            return _stopped(argv, _error("interrupted; run the same command again to resume", 130))
    return 0


def _stopped(argv, code: int) -> int:
    """After an interrupt's clean-up the `bati` program (`argv` None) leaves at once: the interpreter's shutdown
    tore modules down under threads still busy (XLA compiling, an evaluator's workers): a segmentation fault
    when Ctrl-C came during the first compilation. A caller of main() gets the code and keeps its process."""
    if argv is not None:
        return code
    sys.stdout.flush(), sys.stderr.flush()
    os._exit(code)


NEEDS_A_VALUE = ("--datasets",)
"""List options whose empty value is their default (your own data: none, i.e. PointGoal): given without a
value they are a mistake, not a request for the default."""


def _error(message: str, code: int) -> int:
    error_console.print(f"[bold red]error:[/] {escape(message)}")
    return code


def _show_warning(default):
    """warnings.showwarning that prints bati's warnings (a torn log line dropped, ...) as one line."""

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, BatiWarning):
            error_console.print(f"[yellow]warning:[/] {escape(str(message))}")
        else:
            default(message, category, filename, lineno, file, line)

    return show


if __name__ == "__main__":
    sys.exit(main())
