"""Do the committed experiment reports regenerate, at this checkout, from the committed runs?

    python scripts/check_reports.py                       # every results/**/report.md written by `bati experiment`
    python scripts/check_reports.py results/cpu/experiments/main/report.md ...

Each report names the command that wrote it (`- command: bati experiment NAME ... --out-dir OUT ...`). The
check copies OUT's committed files into a scratch directory, reruns that command there with `--report-only`
(nothing is trained; nothing under results/ is touched) and compares the new report.md and table.csv with the
committed ones, the command line aside (a one-seed job's report names its `--seeds`; the rerun covers every
seed, which is what the committed report should hold too). One line per report: `same`, `differs` (with the
first differing lines) or `skipped` (a report of `bati report` / `bati run`, which names no command); exit 1 when
any differs. About 2 minutes per report on a 2-core CPU (rliable's bootstrap and the figures).
"""

from __future__ import annotations

import argparse
import difflib
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


def without(args: list[str], name: str) -> list[str]:
    """args without the option `name` and its values (up to the next option)."""
    if name not in args:
        return args
    start = args.index(name)
    end = next((i for i in range(start + 1, len(args)) if args[i].startswith("--")), len(args))
    return args[:start] + args[end:]


def compared_lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("- command:")]


def check(report: Path, scratch: Path, root: Path = ROOT) -> tuple[str, list[str]]:
    """The verdict on one committed report (under `root`, the project) and the lines that say why."""
    args = command_of(report)
    if args is None:
        return "skipped", ["names no `bati experiment` command (a `bati report` or `bati run` report)"]
    out_dir = report.parent.parent  # the report lies in OUT/<experiment>/ (or a renamed copy of that folder)
    relative = out_dir.relative_to(root)
    copy = scratch / relative
    shutil.copytree(out_dir, copy, ignore=shutil.ignore_patterns("*.png", "checkpoint*", "*.lock"))
    # every seed (a one-seed job's report is its seed's only); the out dir relative to the scratch root, as the
    # committed command is run from the project root
    rerun = without(without(args, "--seeds"), "--out-dir") + ["--out-dir", str(relative), "--report-only"]
    done = subprocess.run([sys.executable, "-m", "bati.cli", *rerun], cwd=scratch, capture_output=True, text=True)
    if done.returncode != 0:
        return "failed", (done.stderr or done.stdout).strip().splitlines()[-3:]
    differences = []
    for file in COMPARED:
        committed, regenerated = report.parent / file, copy / args[1] / file
        if not committed.exists():
            continue
        diff = list(difflib.unified_diff(compared_lines(committed), compared_lines(regenerated), "committed",
                                         "regenerated", n=0, lineterm=""))
        differences += [f"{file}: {line}" for line in diff[2:8]]
    renamed = [] if report.parent.name == args[1] else [f"(a renamed copy of `{args[1]}`'s report folder)"]
    return ("differs" if differences else "same"), renamed + differences


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
