"""The `bati` command line: one subcommand per verb (tyro over dataclasses, rich output).

The commands that read results (report, claims, results) are here and import no JAX: a command line naming one of
them parses them alone. The commands that collect data, train and evaluate are `bati.cli_commands`.
"""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from rich.markup import escape

from bati.cli_hints import DEFAULT_IN_DOC
from bati.errors import BatiWarning, PartialFailure
from bati.report.claims import write_and_show_claims
from bati.experiments.index import update_results
from bati.io import git_commit
from bati.processes import TERMINATED_EXIT_CODE, Terminated, sigterm_as_interrupt
from bati.report.build import build_and_show_report
from bati.usage import parse

console = Console()
# Errors go to stderr on one line, whatever the terminal width (soft_wrap: no hard line breaks).
error_console = Console(stderr=True, soft_wrap=True)


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


READING = {"report": Report, "claims": Claims, "results": Results}
"""The commands that read results: parsed alone when the command line names one of them, so they import no JAX."""


def commands(args: list[str]) -> dict[str, type]:
    """The commands tyro chooses from: the reading ones where `args` starts with one of them, else every command
    (those that collect data, train and evaluate are `bati.cli_commands`)."""
    if args and args[0] in READING:
        return READING
    from bati.cli_commands import COMMANDS

    return {**COMMANDS, **READING}


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
        command = parse(commands(args), argv, lambda line: _error(line, 2))
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
