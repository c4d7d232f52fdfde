"""Do the committed experiment reports regenerate, at this checkout, from the committed runs?

    python scripts/check_reports.py                       # every results/**/report.md written by `bati experiment`
    python scripts/check_reports.py results/cpu/experiments/main-conditioned/report.md ...

Each report names the command that wrote it (`- command: bati experiment NAME ... --out-dir OUT ...`). The
check copies OUT's committed files into a scratch directory, reruns that command there with `--report-only`
(nothing is trained; nothing under results/ is touched) and compares the new report.md and table.csv with the
committed ones, the command line aside (a one-seed job's report names its `--seeds`; the rerun covers every
seed, which is what the committed report should hold too). A report of some methods or families (a job with
`--methods` / `--families`, or a folder renamed after one: reports once covered the job's cells only, now every
cell of the experiment) passes when each of its table rows is among the regenerated ones, number for number.
A folder's RERUN file gives, on its first line, the settings its cells ran with where they are no longer the
defaults (e.g. `--settings csro.club_negatives=any-task`), added to the rerun; rows are checked then too (the rerun
splits such cells into setting tables of their own). A report of `bati report DIR` (also `bati run`'s), which says so in its first lines, is rebuilt from a copy of DIR
and compared whole. One line per report: `same`, `differs` (with the first differing lines), `frozen` (the
folder's FROZEN file says why today's plans cannot reproduce it, e.g. a family version since replaced) or
`skipped` (a report that names no command); exit 1 when any differs. About 1-2 minutes per report on a
2-core CPU (rliable's bootstrap and the figures).
"""

from __future__ import annotations

import argparse
import difflib
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMPARED = ("report.md", "table.csv")


def command_of(report: Path) -> list[str] | None:
    """The `bati experiment ...` arguments the report names (without `bati`), or None."""
    for line in report.read_text().splitlines():
        if line.startswith("- command: `bati experiment "):
            return shlex.split(line.removeprefix("- command: `bati ").rstrip("`"))
    return None


def values_end(args: list[str], name: str) -> int:
    """The index after the values of the option `name` (in args): the next option's, or the end."""
    return next((i for i in range(args.index(name) + 1, len(args)) if args[i].startswith("--")), len(args))


def without(args: list[str], name: str) -> list[str]:
    """args without the option `name` and its values (up to the next option)."""
    return args[:args.index(name)] + args[values_end(args, name):] if name in args else args


def with_settings(args: list[str], more: list[str]) -> list[str]:
    """args with the options `more`; the values of a second `--settings` join the first's (argparse would keep the
    last option's values alone)."""
    if more[:1] != ["--settings"] or "--settings" not in args:
        return args + more
    end = values_end(args, "--settings")
    return args[:end] + more[1:] + args[end:]


def compared_lines(path: Path) -> list[str]:
    """A report's lines but its command (the rerun's names its own out dir and every seed) and the wording of its
    wall-time line (older reports word the same number differently)."""
    lines = []
    for line in path.read_text().splitlines():
        if line.startswith("- command:"):
            continue
        if line.startswith("- summed wall time"):
            line = line.split(" (")[0]
        lines.append(line)
    return lines


def differences(committed: Path, regenerated: Path) -> list[str]:
    """The first lines of the diff between a committed report file and its regenerated twin (compared_lines)."""
    diff = difflib.unified_diff(compared_lines(committed), compared_lines(regenerated), "committed", "regenerated",
                                n=0, lineterm="")
    return [f"{committed.name}: {line}" for line in list(diff)[2:8]]


def rerun_in(scratch: Path, root: Path, source: Path, args: list[str]) -> list[str] | None:
    """Copies root/source (its result files) to scratch/source and runs `bati ARGS` in scratch; None when it
    succeeded, else the last lines it printed."""
    shutil.copytree(root / source, scratch / source, ignore=shutil.ignore_patterns("*.png", "checkpoint*", "*.lock"))
    done = subprocess.run([sys.executable, "-m", "bati.cli", *args], cwd=scratch, capture_output=True, text=True)
    return None if done.returncode == 0 else (done.stderr or done.stdout).strip().splitlines()[-3:]


def rows(path: Path) -> list[str]:
    """A table.csv's rows, header aside."""
    return path.read_text().splitlines()[1:] if path.exists() else []


def check(report: Path, scratch: Path, root: Path = ROOT) -> tuple[str, list[str]]:
    """The verdict on one committed report (under `root`, the project) and the lines that say why."""
    folder = report.parent
    if (folder / "FROZEN").exists():  # a snapshot that today's plans cannot reproduce, and why
        return "frozen", (folder / "FROZEN").read_text().strip().splitlines()
    args = command_of(report)
    if args is None:
        return check_bati_report(report, scratch, root)
    experiment = args[1]
    relative = folder.parent.relative_to(root)  # the report lies in OUT/<experiment>/ (or a renamed copy of it)
    # every seed (a one-seed job's report is its seed's only); the out dir relative to the scratch root, as the
    # committed command is run from the project root
    rerun = without(without(args, "--seeds"), "--out-dir") + ["--out-dir", str(relative), "--report-only"]
    # RERUN: the settings its cells ran with where they are no longer the defaults (its first line; the others say
    # why): the rerun's report then splits those cells into setting tables of their own, so rows are checked
    extra = (folder / "RERUN").read_text().splitlines() if (folder / "RERUN").exists() else []
    rerun = with_settings(rerun, shlex.split(extra[0])) if extra else rerun
    failure = rerun_in(scratch, root, relative, rerun)
    if failure is not None:
        return "failed", failure
    regenerated = scratch / relative / experiment
    # A job of some methods or families (or a renamed copy of one's report) once reported those alone; a report
    # now covers every cell of the experiment: its rows must be among the regenerated ones, number for number.
    subset = folder.name != experiment or "--methods" in args or "--families" in args or bool(extra)
    committed_rows, new_rows = rows(folder / "table.csv"), set(rows(regenerated / "table.csv"))
    lost = [f"table.csv: committed row not regenerated: {row}" for row in committed_rows if row not in new_rows]
    if subset:
        note = (f"(rows checked, rerun with RERUN's `{extra[0]}`)" if extra else "(rows checked: a report of some "
                f"methods or families, or a renamed copy of `{experiment}`'s folder)")
        return ("differs" if lost else "same"), [note] + lost[:6]
    found = [line for file in COMPARED if (folder / file).exists()
             for line in differences(folder / file, regenerated / file)]
    return ("differs" if found else "same"), found


def check_bati_report(report: Path, scratch: Path, root: Path) -> tuple[str, list[str]]:
    """A report of `bati report DIR` (also `bati run`'s): rerun into a copy of DIR, compare report.md whole."""
    match = re.search(r"Generated by `bati report` from .* under `([^`]+)`", report.read_text())
    if match is None:
        return "skipped", ["names no command (neither `bati experiment` nor `bati report`)"]
    out = scratch / "regenerated"
    failure = rerun_in(scratch, root, Path(match[1]), ["report", match[1], "--out-dir", str(out)])
    if failure is not None:
        return "failed", failure
    found = differences(report, out / "report.md")
    return ("differs" if found else "same"), found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("reports", nargs="*", type=Path, help="report.md files (default: every one under results/)")
    parser.add_argument("--root", type=Path, default=ROOT, help="the project (default: this script's)")
    options = parser.parse_args()
    root = options.root.resolve()
    reports = options.reports or sorted((root / "results").rglob("report.md"))
    bad = False
    for report in reports:
        if not report.exists():
            sys.exit(f"check_reports: no such report: {report}")
        with tempfile.TemporaryDirectory(prefix="bati-check-") as scratch:
            verdict, lines = check(report.resolve(), Path(scratch), root)
        bad |= verdict in ("differs", "failed")
        print(f"{verdict:8s} {report.resolve().relative_to(root)}", *(f"    {line}" for line in lines), sep="\n",
              flush=True)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
