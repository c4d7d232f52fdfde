"""Whether two runs trained the same numbers: their training logs compared at the digits a packed log keeps.

    python scripts/compare_logs.py RUN_DIR_A RUN_DIR_B [--digits 4]

Each run directory's metrics.jsonl (or the packed metrics.jsonl.gz of `bati results --pack`) is read; at
every step both logs hold, each metric (wall time aside) is rounded to `--digits` significant digits. Prints
the steps and values compared and the first step and metric where the two differ, or "same"; exit 1 if they
differ.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
from pathlib import Path


def read_log(run_dir: Path) -> dict[int, dict]:
    """{step: record} from a run's metrics.jsonl, or its packed metrics.jsonl.gz."""
    plain, packed = run_dir / "metrics.jsonl", run_dir / "metrics.jsonl.gz"
    if plain.exists():
        text = plain.read_text()
    elif packed.exists():
        text = gzip.decompress(packed.read_bytes()).decode()
    else:
        raise SystemExit(f"{run_dir}: no metrics.jsonl or metrics.jsonl.gz")
    records = (json.loads(line) for line in text.splitlines() if line.strip())
    return {record["step"]: record for record in records}


def first_difference(a: dict[int, dict], b: dict[int, dict], digits: int) -> tuple[int, int, tuple | None]:
    """(steps compared, values compared, the first difference as (step, metric, a's, b's value) or None)."""
    def rounded(value: float) -> float:
        return float(f"{value:.{digits}g}")

    steps = sorted(set(a) & set(b))
    values = 0
    for step in steps:
        for key in sorted(set(a[step]) & set(b[step]) - {"step", "wall_time"}):
            values += 1
            if rounded(a[step][key]) != rounded(b[step][key]):
                return len(steps), values, (step, key, a[step][key], b[step][key])
    return len(steps), values, None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_a", type=Path)
    parser.add_argument("run_b", type=Path)
    parser.add_argument("--digits", type=int, default=4,
                        help="significant digits compared (a packed log keeps 4)")
    args = parser.parse_args()
    steps, values, difference = first_difference(read_log(args.run_a), read_log(args.run_b), args.digits)
    if difference is None:
        print(f"same: {steps} steps, {values} values at {args.digits} significant digits")
        return 0
    step, key, value_a, value_b = difference
    print(f"differ: first at step {step}, {key}: {value_a} vs {value_b} ({steps} common steps)")
    return 1


if __name__ == "__main__":
    sys.exit(main())
