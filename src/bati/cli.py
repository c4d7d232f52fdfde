"""The `bati` command line: one subcommand per verb (tyro over dataclasses, rich output)."""

from __future__ import annotations

import contextlib
import io
import json
import sys
import warnings
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Annotated, Literal, Union

import tyro
from rich.console import Console
from rich.markdown import Markdown
from rich.markup import escape
from rich.table import Table

from bati.config import TrainConfig, rerun_config
from bati.envs.base import TaskSplit
from bati.errors import BatiWarning
from bati.experiments.experiment import ExperimentJob
from bati.experiments.main_job import MainJob, MainJobFailed
from bati.experiments.sweep import Grid
from bati.experts.train import ExpertTrainConfig
from bati.io import git_commit
from bati.processes import TERMINATED_EXIT_CODE, Terminated, sigterm_as_interrupt

console = Console()
# Errors go to stderr on one line, whatever the terminal width (soft_wrap: no hard line breaks).
error_console = Console(stderr=True, soft_wrap=True)


class UserError(Exception):
    """An error caused by the user's input: printed without a traceback, exit code 2."""


class SweepFailed(Exception):
    """Some cells of a sweep failed (the others finished): exit code 1."""


class CollectionDamaged(Exception):
    """`bati data verify` found a damaged collection: exit code 1."""


@dataclass
class Envs:
    """List the task families with their task spaces; with --family and --task, try one episode."""

    family: str | None = None
    """Show only this family (and, with --task, run one random-action episode in it)."""
    task: tuple[float, ...] | None = None
    """A task of the family, e.g. `--task 1.5` or `--task 0.6 0.8` for PointGoal."""
    noise: float | None = None
    """Per-step noise eps (default: the family's)."""

    def run(self) -> None:
        from bati.envs import families_with_extras, get_family, random_episode

        if self.task is not None and not self.family:
            raise UserError("--task needs --family: a task is a parameter of one family "
                            "(e.g. --family PointGoal --task 0.6 0.8)")
        if self.family:  # one family: its missing extra is the error
            families, unavailable = [get_family(self.family)], []
        else:
            families, unavailable = families_with_extras()
        if self.noise is not None:
            for family in families:
                family.validate_noise(self.noise)
        wide = console.width >= 120  # else each task space goes below the table, not into a column of a word
        table = Table(title="bati task families")
        for column in ("family", "gymnasium id", "tasks differ in", "default eps"):
            table.add_column(column, no_wrap=True)
        if wide:
            table.add_column("task space", ratio=1)
        for f in families:
            table.add_row(f.name, f.env_id, f.kind, f"{f.default_noise:g}", *([escape(f.task_space)] if wide else []))
        for name, _ in unavailable:
            table.add_row(name, f"bati/{name}-v0", "-", "-", *(["not installed (below)"] if wide else []))
        console.print(table)
        if not wide:
            for f in families:
                console.print(f"[bold]{f.name}[/]: {escape(f.task_space)}", soft_wrap=True)
        for _, why in unavailable:
            console.print(escape(why), soft_wrap=True)
        if self.task is not None:
            task = self.task[0] if len(self.task) == 1 else list(self.task)
            episode = random_episode(families[0], task, self.noise)
            console.print(f"{families[0].name} task={task} eps={episode['noise']:g}: random-action return "
                          f"{episode['return']:.1f} over {episode['steps']} steps ({episode['ms']:.0f} ms)")


@dataclass
class ExpertsTrain(ExpertTrainConfig):
    """Train a family's task-conditioned SAC expert, or with --per-task one SAC per training task (checkpoints;
    re-running resumes). The export goes into the run directory's zoo/ unless --export-dir or --into-package
    says otherwise."""

    def run(self) -> None:
        from bati.experts.train import train_expert

        config = self.resolved()  # bad values: one line before any work
        out = train_expert(config)
        where = "the package zoo (every later collection of it uses this expert)" if config.into_package else \
            f"{config.export_dir} (collect with --zoo-dir {config.export_dir})"
        if config.per_task:
            where += " as per-task experts (collect with --experts per-task)"
        console.print(f"expert run in {out}; exported to {where}", soft_wrap=True)


@dataclass
class ExpertsCard:
    """Evaluate a shipped expert on the 20 train / 20 test tasks and write its card."""

    family: str
    seed: int = 0
    """Seed of the train/test task split (the same as `bati data collect --seed`)."""
    zoo_dir: Path | None = None
    experts: Literal["conditioned", "per-task"] = "conditioned"
    """The family's task-conditioned expert, or its per-task experts (card in <zoo>/<family>/per-task/)."""

    def run(self) -> None:
        from bati.experts.card import write_card

        card = write_card(self.family, self.seed, self.zoo_dir, self.experts)
        console.print(card["summary"])


def group(**commands):
    """A dataclass type whose single field selects one of `commands` (nested subcommands)."""
    options = tuple(Annotated[cls, tyro.conf.subcommand(name)] for name, cls in commands.items())
    return Annotated[Union[options], tyro.conf.arg(name="")]  # noqa: UP007 (Union of a built tuple)


@dataclass
class Experts:
    """Expert (context-collection) policies."""

    command: group(train=ExpertsTrain, card=ExpertsCard)

    def run(self) -> None:
        self.command.run()


@dataclass
class DataCollect:
    """Collect a family's offline datasets (Eq. 9) and test contexts (Eq. 10) as Minari datasets (cached)."""

    family: str
    scale: Literal["quick", "paper"] = "quick"
    """quick: 20 episodes per training task, 5 per context dataset; paper: App. C Table 3 sizes per task."""
    seed: int = 0
    """Seed of the train/test task split, the collector draws, the env resets and the expert's actions."""
    noise: float | None = None
    """Per-step noise eps of the envs (default: the family's)."""
    root: Path = Path("data")
    """Datasets root: the collection goes to <root>/<family>/<scale>-seed<seed>-eps<eps>/."""
    zoo_dir: Path | None = None
    """Where the family's expert is loaded from (default: the package zoo)."""
    workers: int | None = None
    """Worker processes (default: all cores)"""
    tasks: Annotated[TaskSplit, tyro.conf.OmitArgPrefixes] = TaskSplit()
    """Which tasks train and test: counts (--n-train, --n-test) or parameter ranges (--train-range LOW HIGH)."""
    experts: Literal["conditioned", "per-task"] = "conditioned"
    """Who collects: the family's task-conditioned SAC, or one SAC per training task (App. C.2; its own collection)."""

    def run(self) -> None:
        from bati.data.collect import collect

        result = collect(self.family, self.scale, self.seed, self.noise, self.root, zoo_dir=self.zoo_dir,
                         progress=console.is_terminal, workers=self.workers, tasks=self.tasks, experts=self.experts)
        m = result.manifest
        how = "already collected" if result.cached else f"collected in {result.wall_time_s:.1f} s"
        console.print(
            f"{m['family']} {m['scale']} seed={m['seed']} eps={m['noise']:g}: {how}: "
            f"{m['transitions']:,} transitions ({m['n_episodes']} episodes per training task, "
            f"{m['n_context_episodes']} per context dataset) "
            f"in {result.path}",
            soft_wrap=True,
        )


@dataclass
class DataInfo:
    """Summarise a collection on disk (its manifest): tasks and context collectors."""

    family: str
    scale: Literal["quick", "paper"] = "quick"
    seed: int = 0
    noise: float | None = None
    root: Path = Path("data")
    tasks: Annotated[TaskSplit, tyro.conf.OmitArgPrefixes] = TaskSplit()
    """The collection's task split (as given to `bati data collect`)."""
    experts: Literal["conditioned", "per-task"] = "conditioned"
    """Which experts collected it (as given to `bati data collect`)."""

    def run(self) -> None:
        from bati.data import store
        from bati.envs import get_family

        path, m = store.inspect_collection(self.root, get_family(self.family), self.scale, self.seed, self.noise,
                                           self.tasks, self.experts)
        table = Table(title=f"{path} (commit {m['commit']}, {m['transitions']:,} transitions)")
        for column in ("test task", "task", "p_test collector (most different)",
                       "p_train collector (most similar)"):
            table.add_column(column)
        for j, task in enumerate(m["test_tasks"]):
            d, s = m["p_test_most_different"][j], m["p_train_most_similar"][j]
            table.add_row(str(j), escape(str(task)), f"{d}: {escape(str(m['train_tasks'][d]))}",
                          f"{s}: {escape(str(m['train_tasks'][s]))}")
        console.print(table)
        if store.has_checksums(m):
            console.print(f"{len(m['files'])} dataset files, each of its recorded size; `bati data verify` "
                          "compares their sha256", soft_wrap=True)
        else:
            console.print(f"no checksums (collected before format {store.CHECKSUM_FORMAT}): files not checked",
                          soft_wrap=True)


@dataclass
class DataVerify:
    """Recompute the sha256 of every dataset file of the collections under --root; name edited, truncated or
    missing files (exit code 1 when a collection is damaged)."""

    family: str | None = None
    """Only this family's collections (default: every collection under --root)."""
    scale: Literal["quick", "paper"] | None = None
    """Only collections of this scale (default: any)."""
    seed: int | None = None
    """Only collections of this seed (default: any)."""
    noise: float | None = None
    """Only collections of this eps (default: any)."""
    root: Path = Path("data")

    def run(self) -> None:
        from bati.data import store
        from bati.envs import get_family

        family = get_family(self.family) if self.family else None  # an unknown one is an error, not "none found"
        results = store.verify_collections(self.root, family, self.scale, self.seed, self.noise)
        damaged, checked = [], 0
        for path, status, details in results:
            checked += 1
            console.print(f"{status}: {escape(str(path))}" + (f": {escape('; '.join(details))}" if details else ""),
                          soft_wrap=True)
            if status == "damaged":
                damaged.append(path)
        if damaged:
            raise CollectionDamaged(f"{len(damaged)} of {checked} collection(s) damaged ("
                                    + ", ".join(map(str, damaged)) + "); delete them and re-run `bati data collect`")


@dataclass
class Data:
    """Offline datasets and context data (Minari)."""

    command: group(collect=DataCollect, info=DataInfo, verify=DataVerify)

    def run(self) -> None:
        self.command.run()


@dataclass
class Train(TrainConfig):
    """Train one method on one family (offline, IQL core), evaluating on p_train / p_test contexts.
    Every setting of the run is an option (each method's under --bati., --csro., ...; IQL's under --iql.);
    re-running resumes."""

    seeds: tuple[int, ...] | None = None
    """Train several seeds as one program vmapped over them (instead of --seed); --out-dir is then the parent
    of the runs' directories <method>-seed<s> (default runs/<family>/<scale>)."""
    config: Path | None = None
    """Rerun the config a run directory recorded (its directory or config.json), exactly; only --out-dir,
    --data-root and --seeds may be given with it."""

    def run(self) -> None:
        from bati.train import train_seeds

        if self.seeds is not None and not self.seeds:
            raise UserError("--seeds needs at least one seed (e.g. --seeds 0 1 2), or leave it out for --seed")
        config = TrainConfig(**{f.name: getattr(self, f.name) for f in fields(TrainConfig)})
        if self.config is not None:
            config = rerun_config(self.config, config)
        family = config.resolved().family  # checks every setting before any work
        runs_dir = (config.out_dir or Path("runs") / family / config.scale) if self.seeds else None
        if self.seeds:
            config = replace(config, out_dir=None)
        # progress bars only on a terminal: a log file (or a test) gets the result lines, not bar redraws
        for summary in train_seeds(config, self.seeds or (config.seed,), runs_dir=runs_dir,
                                   show_progress=console.is_terminal):
            if "p_test_return" in summary:
                result = (f"return with p_train contexts {summary['p_train_return']:.1f}, with p_test contexts "
                          f"{summary['p_test_return']:.1f}")
            else:  # own data: no env
                result = (f"held-out task-inference accuracy {summary['held_out_inference_accuracy']:.2f}, held-out "
                          f"representation loss {summary['held_out_representation_loss']:.3f}")
                if "held_out_return" in summary:
                    result += f", return in your env {summary['held_out_return']:.2f}"
            console.print(f"{config.method} on {family}, seed {summary['seed']}: {result} "
                          f"(mean of the last {summary['evaluations_averaged']} evaluations)")


@dataclass
class Run(MainJob):
    """The main job: data with the shipped experts, train BATI, BATI-R and Recon (or --methods) as a sweep,
    evaluate under context shift, then the report (table with rliable intervals, CSVs, curves) and one line
    reading it. A rerun trains only what is missing."""

    def run(self) -> None:
        from bati.experiments.main_job import run_main_job

        results = run_main_job(self, show_progress=console.is_terminal)
        console.print(Markdown(results["markdown"]))
        console.print(f"wall time {results['wall_time_s'] / 60:.1f} min; results in {results['out_dir']}/ "
                      f"(results.md, results.json; the report with CSVs and curves in {results['report_dir']}/)",
                      soft_wrap=True)


@dataclass
class Likelihood:
    """For a BATI run: task-inference error of Eq. 8 with the full, reward-only and state-only NLL (also
    written to RUN_DIR/likelihood.json)."""

    run_dir: Path
    context_length: int = 200

    def run(self) -> None:
        from bati.report.likelihood import LIKELIHOOD_FILE, likelihood_split_markdown, save_likelihood_split

        console.print(Markdown(likelihood_split_markdown(save_likelihood_split(self.run_dir, self.context_length))))
        console.print(f"saved in {self.run_dir / LIKELIHOOD_FILE}", soft_wrap=True)


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
        from bati.inference import infer_context

        print(json.dumps(infer_context(self.run_dir, self.context, self.quantile), indent=2))


@dataclass
class Sweep:
    """Run a grid of training runs (families x methods x seeds x noises x scales); reruns do only what is missing."""

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

    def run(self) -> None:
        from bati.experiments.sweep import sweep

        result = sweep(self.grid, self.out_dir, data_root=self.data_root, workers=self.workers, backend=self.backend,
                       address=self.address, show_progress=console.is_terminal)
        counts = {s: result.count(s) for s in ("done", "skipped", "failed")}
        console.print(f"sweep {result.out_dir}: {counts['done']} cell(s) run, {counts['skipped']} already done, "
                      f"{counts['failed']} failed, in {result.wall_time_s / 60:.1f} min", soft_wrap=True)
        for cell_id, error in result.errors.items():
            error_console.print(f"[red]failed[/] {cell_id}: {escape(error)}", soft_wrap=True)
        if self.report and counts["done"] + counts["skipped"]:
            Report(self.out_dir).run()
        if counts["failed"]:
            raise SweepFailed(f"{counts['failed']} cell(s) failed; their errors are in {result.out_dir}/sweep.json; "
                              "rerun the same command to retry them")


@dataclass
class Experiment(ExperimentJob):
    """Run one of the paper's experiments (`bati experiment list` shows them) and write its report."""

    name: tyro.conf.Positional[str]
    """The experiment (main, noise, context-length, ...), or `list`."""

    def run(self) -> None:
        from bati.experiments.experiment import experiment_list, run_experiment_job

        if self.name == "list":
            table = Table(title="bati experiments (cells: runs at the quick / cpu / paper scale; probes: quick)")
            table.add_column("name", no_wrap=True)
            table.add_column("paper", no_wrap=True)
            for column in ("quick", "cpu", "paper", "probes"):
                table.add_column(column, justify="right", no_wrap=True)
            rows = experiment_list()
            wide = console.width >= 120  # else the titles go below the table: a column of 8 characters reads badly
            if wide:
                table.add_column("what", ratio=1)
            for row in rows:
                table.add_row(row["name"], row["paper"], *(str(row["cells"][k]) for k in ("quick", "cpu", "paper")),
                              str(row["probes"]), *([escape(row["title"])] if wide else []))
            console.print(table)
            if not wide:
                for row in rows:
                    console.print(f"[bold]{row['name']}[/]: {escape(row['title'])}", soft_wrap=True)
            return
        outcome = run_experiment_job(self, show_progress=console.is_terminal,
                                     on_probe=lambda label: console.print(f"probe {label}") if console.is_terminal
                                     else None)
        console.print(Markdown(outcome.report["markdown"]))
        if outcome.run is None:
            console.print(f"experiment {self.name}: report in {outcome.report_dir}/ (nothing trained)", soft_wrap=True)
            return
        sweep, run = outcome.run.sweep, outcome.run
        counts = {s: sweep.count(s) for s in ("done", "skipped", "failed")}
        console.print(f"experiment {self.name}: {counts['done']} cell(s) run, {counts['skipped']} already done, "
                      f"{counts['failed']} failed, {run.probes_done} probe(s), in {run.wall_time_s / 60:.1f} min; "
                      f"report in {outcome.report_dir}/", soft_wrap=True)
        for label, error in outcome.failures.items():
            error_console.print(f"[red]failed[/] {label}: {escape(error)}", soft_wrap=True)
        if outcome.failures:
            raise SweepFailed(f"{counts['failed']} cell(s) and {len(run.probe_errors)} probe(s) failed; rerun the "
                              "same command to retry them")


@dataclass
class Report:
    """Tables (Markdown + CSV) and learning curves (PNG) from the eval.json files under a directory."""

    results_dir: tyro.conf.Positional[Path]
    """Directory searched recursively for runs' eval.json files."""
    out_dir: Path | None = None
    """Where report.md, the CSVs and PNGs go (default: RESULTS_DIR/report)."""

    def run(self) -> None:
        from bati.report import build_report

        report = build_report(self.results_dir, self.out_dir)  # skipped files: warnings, printed as they happen
        console.print(Markdown(report["markdown"]))
        console.print(f"{report['runs']} run(s), {len(report['tables'])} table(s); "
                      f"files in {report['out_dir']}/: " + ", ".join(p.name for p in report["files"]),
                      soft_wrap=True)


@dataclass
class Claims:
    """Each of the paper's claims decided by rliable intervals over the committed runs, at every scale."""

    root: Path = Path(".")
    """The project directory whose results/ holds the experiments (quick, 12k, cpu, paper)."""
    out: Path | None = None
    """Where the page goes (default: ROOT/docs/claims.md)."""

    def run(self) -> None:
        from bati.experiments.claims import write_claims

        out, verdicts = write_claims(self.root, self.out)
        for claim, verdict, scale in verdicts:
            console.print(f"{claim.name} {verdict} (at {scale}): {claim.text}", soft_wrap=True)
        console.print(f"claims page: {out}")


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
        from bati.experiments.index import pack_results, regenerate_reports, write_results

        if not (self.root / "results").is_dir():
            raise UserError(f"{self.root / 'results'} is not a directory: --root names the project directory")
        if self.pack:
            files, saved = pack_results(self.root)
            console.print(f"packed {files} metrics.jsonl file(s), {saved / 2**20:.1f} MiB saved")
        if self.reports:
            for folder in regenerate_reports(self.root):
                console.print(f"report: {folder}/report.md")
        for path in write_results(self.root):
            console.print(f"written: {path}")


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
        command = _parse(argv)
    except SystemExit as exit_:
        return exit_.code if isinstance(exit_.code, int) else 2
    git_commit()  # the running code's commit is read now, whatever is committed while the command runs
    with warnings.catch_warnings(), sigterm_as_interrupt():
        warnings.simplefilter("always", BatiWarning)
        warnings.showwarning = _show_warning(warnings.showwarning)
        try:
            command.run()
        except (SweepFailed, CollectionDamaged, MainJobFailed) as err:
            return _error(str(err), 1)
        except OSError as err:  # before ValueError: FileNotFoundError, PermissionError, disk full, ...
            return _error(describe_os_error(err), 2)
        except (UserError, BatiError, TaskError, ValueError) as err:
            return _error(str(err), 2)
        except Terminated:  # SIGTERM (kill, a scheduler): the same clean-up as Ctrl-C
            _ignore_further_interrupts(argv)
            return _error("terminated; run the same command again to resume", TERMINATED_EXIT_CODE)
        except KeyboardInterrupt:
            _ignore_further_interrupts(argv)
            return _error("interrupted; run the same command again to resume", 130)
    return 0


def _ignore_further_interrupts(argv) -> None:
    """The command has stopped and cleaned up: a second Ctrl-C while the interpreter exits (its atexit
    callbacks) would only print a traceback, so it is ignored (the `bati` program only, `argv` None: a
    caller of main() keeps its own Ctrl-C)."""
    import signal

    if argv is not None:
        return
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread (main() called from a thread): nothing to protect
        pass


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


def _parse(argv: list[str] | None):
    """The command tyro parses from `argv`; a usage error (unknown option, a value of the wrong type,
    a missing value) is printed as one line instead of tyro's panel, then SystemExit(2) as tyro does."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            command = tyro.extras.subcommand_cli_from_dict(
                COMMANDS, args=argv, prog="bati", config=(tyro.conf.OmitSubcommandPrefixes,)
            )
    except SystemExit as exit_:
        if exit_.code not in (0, None):
            _error(usage_error_line(captured.getvalue()), 2)
            raise SystemExit(2) from None
        sys.stderr.write(captured.getvalue())
        raise
    sys.stderr.write(captured.getvalue())  # whatever else tyro printed (warnings)
    return command


def usage_error_line(panel: str) -> str:
    """tyro's usage-error panel in one line: its message, its first suggestion, where the help is."""
    rows = [row.strip().strip("\u2502\u256d\u256e\u2570\u256f").strip() for row in panel.splitlines()]
    sections: list[list[str]] = [[]]
    for row in rows[1:]:  # after the title, rules (----) separate the message and the hints
        if row and set(row) <= set("-\u2500\u256d\u256e\u2570\u256f "):
            sections.append([])
        else:
            sections[-1].append(row)
    body = next((section for section in sections if any(section)), rows)
    message = " ".join(_first_paragraph(body))
    if not message:
        return "invalid arguments (see `bati --help`)"
    suggestion = _row_after(rows, "Perhaps you meant")
    if suggestion:
        message += f"; perhaps you meant {suggestion.split()[0]}"
    helps = [row.split(" run ", 1)[-1].split(" see ", 1)[-1] for row in rows if row.startswith("For full helptext")]
    return message + (f" (see `{helps[0]}`)" if helps else "")


def _row_after(rows: list[str], prefix: str) -> str:
    """The first non-empty row after the row that starts with `prefix` ("" if none)."""
    starts = [i for i, row in enumerate(rows) if row.startswith(prefix)]
    return next((row for row in rows[starts[0] + 1:] if row), "") if starts else ""


def _first_paragraph(rows: list[str]) -> list[str]:
    out = []
    for row in rows:
        if not row and out:
            break
        if row:
            out.append(row)
    return out


if __name__ == "__main__":
    sys.exit(main())
