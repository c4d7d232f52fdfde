"""How tables write methods, returns and CSV files (shared by `bati report` and the experiment reports)."""

from __future__ import annotations

import csv
import io
import math

import numpy as np

# How a method is named in tables (its `--method` name otherwise).
METHOD_LABELS = {"oracle": "oracle (IQL, true task)"}


def return_digits(*values: float) -> int:
    """Decimals for returns: 3 when every |return| is below 5 (KuhnPoker's returns per hand), else 1."""
    finite = [abs(float(v)) for v in values if v is not None and np.isfinite(v)]
    return 3 if finite and max(finite) < 5 else 1


def _csv_value(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return "" if not math.isfinite(value) else repr(value)
    if isinstance(value, list):
        return " ".join(map(str, value))
    return str(value)


def csv_text(columns, records: list[dict]) -> str:
    """The records as CSV text under `columns` (a missing or non-finite value is empty; a list, space-separated)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for record in records:
        writer.writerow([_csv_value(record.get(c)) for c in columns])
    return buffer.getvalue()
