"""Result tables: method x context distribution, mean +- std over seeds."""

from __future__ import annotations

import numpy as np


def mean_std(values: list[float]) -> str:
    if len(values) == 1:
        return f"{values[0]:.1f}"
    return f"{np.mean(values):.1f} ± {np.std(values):.1f}"


# How a method is named in tables (its `--method` name otherwise).
METHOD_LABELS = {"oracle": "oracle (IQL, true task)"}


def results_markdown(rows: list[dict], oracle: float | None, title: str) -> str:
    """rows: one per method with lists over seeds: p_train_return, p_test_return, *_inference_error."""
    lines = [f"### {title}", "", "| method | p_train contexts | p_test contexts | task-inference error (p_train / p_test) |",
             "| --- | --- | --- | --- |"]
    if oracle is not None:
        lines.append(f"| Oracle (Pre-IQL, the experts) | {oracle:.1f} | {oracle:.1f} | – |")
    for row in rows:
        lines.append(
            f"| {METHOD_LABELS.get(row['method'], row['method'])} | {mean_std(row['p_train_return'])} | {mean_std(row['p_test_return'])} | "
            f"{np.mean(row['p_train_inference_error']):.2f} / {np.mean(row['p_test_inference_error']):.2f} |"
        )
    return "\n".join(lines) + "\n"
