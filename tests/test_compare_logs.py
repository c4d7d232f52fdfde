"""scripts/compare_logs.py: two runs' training logs compared at the digits a packed log keeps."""

from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compare_logs.py"


def write_log(run_dir: Path, values: list[float], packed: bool = False) -> Path:
    run_dir.mkdir(parents=True)
    text = "".join(json.dumps({"step": 100 * (i + 1), "wall_time": float(i), "v": v}) + "\n"
                   for i, v in enumerate(values))
    if packed:
        (run_dir / "metrics.jsonl.gz").write_bytes(gzip.compress(text.encode()))
    else:
        (run_dir / "metrics.jsonl").write_text(text)
    return run_dir


def compare(a: Path, b: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(a), str(b)], capture_output=True, text=True)


def test_a_packed_log_matches_the_full_precision_log_it_was_packed_from(tmp_path):
    packed = write_log(tmp_path / "a", [16.54, 1.304], packed=True)
    full = write_log(tmp_path / "b", [16.544912, 1.3035561])
    result = compare(packed, full)
    assert result.returncode == 0 and result.stdout.strip() == "same: 2 steps, 2 values at 4 significant digits"


def test_the_first_step_that_differs_is_named(tmp_path):
    a = write_log(tmp_path / "a", [1.0, 16.54, 2.0], packed=True)
    b = write_log(tmp_path / "b", [1.0, 16.545387, 3.0])
    result = compare(a, b)
    assert result.returncode == 1 and result.stdout.startswith("differ: first at step 200, v: 16.54 vs 16.545387")


def test_a_run_directory_without_a_log_is_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    result = compare(tmp_path / "empty", tmp_path / "empty")
    assert result.returncode == 1 and "no metrics.jsonl or metrics.jsonl.gz" in result.stderr
