"""Fold the run folders of test-time rules evaluated alongside a bati run (the layout before one run per training)
into that run: each `<rule>-seed<s>/` whose eval.json records `trained_with` becomes the `"rules"` entry of its
host's eval.jsonl lines and eval.json, its probes move to `<host>/probes/<rule>/`, and the folder (config, copied
training log, evaluations) goes. The numbers do not change: `bati results --reports` then reads each rule from its
host's files (docs/methods.md).

    python scripts/fold_rule_folders.py results            # what it would do
    python scripts/fold_rule_folders.py results --apply    # do it

A folder whose host is missing, or whose evaluation steps differ from its host's, is named and left as it is.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from bati.io import atomic_write_json, atomic_write_text
from bati.report.runs import RULE_KEYS


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def fold(rule_dir: Path, apply: bool) -> str:
    """Fold one rule folder into its host; returns what was (or would be) done, or why not."""
    summary = json.loads((rule_dir / "eval.json").read_text())
    rule, host = summary["method"], rule_dir.parent / summary["trained_with"]
    if not (host / "eval.json").is_file() or not (host / "eval.jsonl").is_file():
        return f"left: {rule_dir} (its run {host.name} has no eval.json / eval.jsonl)"
    host_lines, rule_lines = _lines(host / "eval.jsonl"), _lines(rule_dir / "eval.jsonl")
    if [r["step"] for r in host_lines] != [r["step"] for r in rule_lines]:
        return f"left: {rule_dir} (its evaluation steps differ from {host.name}'s)"
    if not apply:
        return f"would fold: {rule_dir} -> {host.name} (rules: {rule})"
    for line, of_rule in zip(host_lines, rule_lines):
        line.setdefault("rules", {})[rule] = {k: v for k, v in of_rule.items() if k != "step"}
    atomic_write_text(host / "eval.jsonl", "".join(json.dumps(line) + "\n" for line in host_lines))
    host_summary = json.loads((host / "eval.json").read_text())
    host_summary.setdefault("rules", {})[rule] = {k: summary[k] for k in RULE_KEYS if k in summary}
    atomic_write_json(host / "eval.json", host_summary)
    if (rule_dir / "probes").is_dir():
        target = host / "probes" / rule
        target.mkdir(parents=True, exist_ok=True)
        for file in (rule_dir / "probes").iterdir():
            shutil.move(str(file), target / file.name)
    shutil.rmtree(rule_dir)
    return f"folded: {rule_dir} -> {host.name} (rules: {rule})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="directory searched for rule folders (eval.json with trained_with)")
    parser.add_argument("--apply", action="store_true", help="fold them (default: say what would be done)")
    args = parser.parse_args(argv)
    if not args.root.is_dir():
        print(f"error: {args.root} is not a directory", file=sys.stderr)
        return 2
    folders = sorted(p.parent for p in args.root.rglob("eval.json")
                     if "trained_with" in json.loads(p.read_text()))
    done = [fold(folder, args.apply) for folder in folders]
    print("\n".join(done) or "no rule folders")
    return 0


if __name__ == "__main__":
    sys.exit(main())
