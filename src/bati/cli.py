"""The `bati` command line: one subcommand per verb (tyro over dataclasses, rich output)."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Union

import tyro
from rich.console import Console
from rich.markdown import Markdown
from rich.markup import escape
from rich.table import Table

from bati.experiments.sweep import Grid

console = Console()
# Errors go to stderr on one line, whatever the terminal width (soft_wrap: no hard line breaks).
error_console = Console(stderr=True, soft_wrap=True)


class UserError(Exception):
    """An error caused by the user's input: printed without a traceback, exit code 2."""


class SweepFailed(Exception):
    """Some cells of a sweep failed (the others finished): exit code 1."""


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
        from bati.envs import FAMILY_NAMES, get_family

        names = [self.family] if self.family else list(FAMILY_NAMES)
        families = [get_family(name) for name in names]
        if self.noise is not None:
            for family in families:
                family.validate_noise(self.noise)
        table = Table(title="bati task families")
        table.add_column("family", no_wrap=True)
        table.add_column("gymnasium id", no_wrap=True)
        for column in ("tasks differ in", "task space", "default eps"):
            table.add_column(column)
        for f in families:
            table.add_row(f.name, f.env_id, f.kind, escape(f.task_space), f"{f.default_noise:g}")
        console.print(table)
        if self.task is None:
            return
        family = families[0]
        task = self.task[0] if len(self.task) == 1 else list(self.task)
        env = family.make_env(task, self.noise)
        env.reset(seed=0)
        start, total, steps = time.perf_counter(), 0.0, 0
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total, steps, done = total + reward, steps + 1, terminated or truncated
        console.print(
            f"{family.name} task={task} eps={env.unwrapped.noise:g}: random-action return {total:.1f} "
            f"over {steps} steps ({1e3 * (time.perf_counter() - start):.0f} ms)"
        )


@dataclass
class ExpertsTrain:
    """Train a family's task-conditioned SAC expert (checkpoints; re-running resumes)."""

    family: str
    total_steps: int | None = None
    """Environment transitions (default: the family's, see bati.experts.train.DEFAULT_STEPS)."""
    seed: int = 0
    updates_per_step: float = 0.5
    out_dir: Path | None = None
    """Run directory (default runs/experts/<family>)."""
    export_dir: Path | None = None
    """Where to export the finished expert (default: the package zoo)."""

    def run(self) -> None:
        from bati.experts.train import ExpertTrainConfig, train_expert

        config = ExpertTrainConfig(self.family, self.total_steps, seed=self.seed, out_dir=self.out_dir,
                                   updates_per_step=self.updates_per_step, export_dir=self.export_dir)
        out = train_expert(config)
        console.print(f"expert run in {out}; exported to {self.export_dir or 'the package zoo'}")


@dataclass
class ExpertsCard:
    """Evaluate a shipped expert on the 20 train / 20 test tasks and write its card."""

    family: str
    seed: int = 0
    """Seed of the train/test task split (the same as `bati data collect --seed`)."""
    zoo_dir: Path | None = None

    def run(self) -> None:
        from bati.experts.card import write_card

        card = write_card(self.family, self.seed, self.zoo_dir)
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

    def run(self) -> None:
        from bati.data.collect import collect

        result = collect(self.family, self.scale, self.seed, self.noise, self.root, zoo_dir=self.zoo_dir,
                         progress=console.is_terminal, workers=self.workers)
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

    def run(self) -> None:
        from bati.data import store
        from bati.envs import get_family

        family = get_family(self.family)
        noise = family.validate_noise(self.noise)
        path = store.collection_dir(self.root, self.family, self.scale, self.seed, noise)
        m = store.read_manifest(path, family, self.scale, self.seed, noise, self.root)
        table = Table(title=f"{path} (commit {m['commit']}, {m['transitions']:,} transitions)")
        for column in ("test task", "task", "p_test collector (most different)",
                       "p_train collector (most similar)"):
            table.add_column(column)
        for j, task in enumerate(m["test_tasks"]):
            d, s = m["p_test_most_different"][j], m["p_train_most_similar"][j]
            table.add_row(str(j), escape(str(task)), f"{d}: {escape(str(m['train_tasks'][d]))}",
                          f"{s}: {escape(str(m['train_tasks'][s]))}")
        console.print(table)


@dataclass
class Data:
    """Offline datasets and context data (Minari)."""

    command: group(collect=DataCollect, info=DataInfo)

    def run(self) -> None:
        self.command.run()


@dataclass
class Train:
    """Train one method on one family (offline, IQL core), evaluating on p_train / p_test contexts."""

    family: str = "PointGoal"
    method: str = "bati"
    """bati, bati-r, recon, unicorn, csro, focal, dpt, oracle or no-context."""
    seed: int = 0
    scale: Literal["quick", "paper"] = "quick"
    steps: int | None = None
    """Gradient steps (default: quick 3k, paper 100k)."""
    noise: float | None = None
    out_dir: Path | None = None
    """Run directory (default runs/<family>/<scale>/<method>-seed<seed>); re-running resumes. With --seeds:
    the parent of the runs' directories <method>-seed<s> (default runs/<family>/<scale>)."""
    data_root: Path = Path("data")
    seeds: tuple[int, ...] = ()
    """Train several seeds as one program vmapped over them (instead of --seed)."""

    def run(self) -> None:
        from bati.train import TrainConfig, train_seeds

        config = TrainConfig(family=self.family, method=self.method, seed=self.seed, scale=self.scale,
                             steps=self.steps, noise=self.noise, out_dir=None if self.seeds else self.out_dir,
                             data_root=self.data_root)
        runs_dir = (self.out_dir or Path("runs") / self.family / self.scale) if self.seeds else None
        for summary in train_seeds(config, self.seeds or (self.seed,), runs_dir=runs_dir):
            console.print(
                f"{self.method} on {self.family}, seed {summary['seed']}: return with p_train contexts "
                f"{summary['p_train_return']:.1f}, with p_test contexts {summary['p_test_return']:.1f} "
                f"(mean of the last {summary['evaluations_averaged']} evaluations)"
            )


@dataclass
class Run:
    """The main job: data with the shipped experts, train BATI, BATI-R and Recon, evaluate under context shift."""

    family: str = "PointGoal"
    methods: tuple[str, ...] = ("bati", "bati-r", "recon")
    """Any of bati, bati-r, recon, unicorn, csro, focal, dpt, oracle; or `all`."""
    seeds: tuple[int, ...] = (0,)
    scale: Literal["quick", "paper"] = "quick"
    steps: int | None = None
    noise: float | None = None
    out_dir: Path | None = None
    """Experiment directory (default runs/<family>/<scale>)."""
    data_root: Path = Path("data")

    def run(self) -> None:
        from bati.experiments.main_job import MainJobConfig, run_main_job

        results = run_main_job(MainJobConfig(self.family, self.methods, self.seeds, self.scale, self.steps,
                                             self.noise, self.data_root, self.out_dir))
        console.print(Markdown(results["markdown"]))
        console.print(f"wall time {results['wall_time_s'] / 60:.1f} min; results in {results['out_dir']}/"
                      "(results.json, results.md, learning_curves.png)")


@dataclass
class Likelihood:
    """For a BATI run: task-inference error of Eq. 8 with the full, reward-only and state-only NLL."""

    run_dir: Path
    context_length: int = 200

    def run(self) -> None:
        from bati.report.likelihood import likelihood_split, likelihood_split_markdown

        console.print(Markdown(likelihood_split_markdown(likelihood_split(self.run_dir, self.context_length))))


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
class Report:
    """Tables (Markdown + CSV) and learning curves (PNG) from the eval.json files under a directory."""

    results_dir: tyro.conf.Positional[Path]
    """Directory searched recursively for runs' eval.json files."""
    out_dir: Path | None = None
    """Where report.md, the CSVs and PNGs go (default: RESULTS_DIR/report)."""

    def run(self) -> None:
        import warnings

        from bati.report import ReportWarning, build_report

        caught: list[warnings.WarningMessage] = []
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", ReportWarning)
                report = build_report(self.results_dir, self.out_dir)
        finally:  # skipped files are named even when the report then fails
            for w in caught:
                if issubclass(w.category, ReportWarning):
                    error_console.print(f"[yellow]warning:[/] {escape(str(w.message))}")
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
        console.print(Markdown(report["markdown"]))
        console.print(f"{report['runs']} run(s), {len(report['tables'])} table(s); "
                      f"files in {report['out_dir']}/: " + ", ".join(p.name for p in report["files"]),
                      soft_wrap=True)


COMMANDS = {"envs": Envs, "experts": Experts, "data": Data, "train": Train, "run": Run, "sweep": Sweep,
            "likelihood": Likelihood, "report": Report}


def main(argv: list[str] | None = None) -> int:
    from bati.envs import TaskError
    from bati.errors import BatiError

    command = tyro.extras.subcommand_cli_from_dict(
        COMMANDS, args=argv, prog="bati", config=(tyro.conf.OmitSubcommandPrefixes,)
    )
    try:
        command.run()
    except SweepFailed as err:
        error_console.print(f"[bold red]error:[/] {escape(str(err))}")
        return 1
    except (UserError, BatiError, TaskError, FileNotFoundError, ValueError) as err:
        error_console.print(f"[bold red]error:[/] {escape(str(err))}")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
