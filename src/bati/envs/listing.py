"""`bati envs`: the task families as a table, and one random-action episode in a task of one of them."""

from __future__ import annotations

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bati.envs import families_with_extras, get_family, random_episode
from bati.envs.base import Task, TaskError, TaskFamily

WIDE = 120
"""Console columns from which the task spaces fit in the table (narrower: each below it, not in a column of a word)."""


def show_families(family: str | None = None, task: tuple[float, ...] | None = None, noise: float | None = None,
                  *, console: Console) -> None:
    """The families (or `family` only) with their task spaces; with `task`, one random-action episode in it."""
    if task is not None and not family:
        raise TaskError("--task needs --family: a task is a parameter of one family "
                        "(e.g. --family PointGoal --task 0.6 0.8)")
    if family:  # one family: its missing extra is the error
        families, unavailable = [get_family(family)], []
    else:
        families, unavailable = families_with_extras()
    if noise is not None:
        for f in families:
            f.validate_noise(noise)
    wide = console.width >= WIDE
    console.print(family_table(families, [name for name, _ in unavailable], wide))
    if not wide:
        for f in families:
            console.print(f"[bold]{f.name}[/]: {escape(f.task_space)}", soft_wrap=True)
    for _, why in unavailable:
        console.print(escape(why), soft_wrap=True)
    if task is not None:
        show_random_episode(families[0], task[0] if len(task) == 1 else list(task), noise, console=console)


def family_table(families: list[TaskFamily], unavailable: list[str], wide: bool) -> Table:
    """One row per family (and per family whose extra is missing); the task spaces in a column when `wide`."""
    table = Table(title="bati task families")
    for column in ("family", "gymnasium id", "tasks differ in", "default eps"):
        table.add_column(column, no_wrap=True)
    if wide:
        table.add_column("task space", ratio=1)
    for f in families:
        table.add_row(f.name, f.env_id, f.kind, f"{f.default_noise:g}", *([escape(f.task_space)] if wide else []))
    for name in unavailable:
        table.add_row(name, f"bati/{name}-v0", "-", "-", *(["not installed (below)"] if wide else []))
    return table


def show_random_episode(family: TaskFamily, task: Task, noise: float | None, *, console: Console) -> None:
    episode = random_episode(family, task, noise)
    console.print(f"{family.name} task={task} eps={episode['noise']:g}: random-action return "
                  f"{episode['return']:.1f} over {episode['steps']} steps ({episode['ms']:.0f} ms)")
