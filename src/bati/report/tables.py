"""Result tables: method x context distribution, mean +- std over seeds."""

from __future__ import annotations

import numpy as np


def return_digits(*values: float) -> int:
    """Decimals for returns: 3 when every |return| is below 5 (KuhnPoker's returns per hand), else 1."""
    finite = [abs(float(v)) for v in values if v is not None and np.isfinite(v)]
    return 3 if finite and max(finite) < 5 else 1


def mean_std(values: list[float], digits: int = 1) -> str:
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{np.mean(values):.{digits}f} ± {np.std(values):.{digits}f}"


# How a method is named in tables (its `--method` name otherwise).
METHOD_LABELS = {"oracle": "oracle (IQL, true task)"}


def results_markdown(rows: list[dict], oracle: float | None, title: str) -> str:
    """rows: one per method with lists over seeds: p_train_return, p_test_return, *_inference_error."""
    lines = [f"### {title}", "", "| method | p_train contexts | p_test contexts | task-inference error (p_train / p_test) |",
             "| --- | --- | --- | --- |"]
    d = return_digits(*([] if oracle is None else [oracle]),
                      *(v for row in rows for k in ("p_train_return", "p_test_return") for v in row[k]))
    if oracle is not None:
        lines.append(f"| Oracle (Pre-IQL, the experts) | {oracle:.{d}f} | {oracle:.{d}f} | – |")
    for row in rows:
        lines.append(
            f"| {METHOD_LABELS.get(row['method'], row['method'])} | {mean_std(row['p_train_return'], d)} | "
            f"{mean_std(row['p_test_return'], d)} | "
            f"{np.mean(row['p_train_inference_error']):.2f} / {np.mean(row['p_test_inference_error']):.2f} |"
        )
    return "\n".join(lines) + "\n"
