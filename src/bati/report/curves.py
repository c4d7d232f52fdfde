"""Learning curves: evaluation return against gradient steps, p_test and p_train contexts."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bati.io import read_jsonl
from bati.report.tables import METHOD_LABELS


def plot_learning_curves(run_dirs: dict[str, list[Path]], path: Path, title: str, oracle: float | None = None) -> None:
    """run_dirs: method -> its seeds' run directories (each with eval.jsonl)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, source in zip(axes, ("p_test", "p_train")):
        for method, dirs in run_dirs.items():
            curves = [read_jsonl(d / "eval.jsonl", require=("step",)) for d in dirs]  # torn last line: dropped
            n = min(len(c) for c in curves)
            steps = [e["step"] for e in curves[0][:n]]
            values = np.array([[e[f"{source}_return"] for e in c[:n]] for c in curves])
            mean = values.mean(0)
            (line,) = ax.plot(steps, mean, label=METHOD_LABELS.get(method, method))
            if len(dirs) > 1:
                ax.fill_between(steps, mean - values.std(0), mean + values.std(0), color=line.get_color(), alpha=0.2)
        if oracle is not None:
            ax.axhline(oracle, color="gray", linestyle="--", label="Oracle (experts)")
        ax.set_title(f"{source} contexts")
        ax.set_xlabel("gradient steps")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("episodic return")
    axes[1].legend(loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def save_figure(fig, path: Path, dpi: int) -> None:
    """Write a figure atomically (a temporary file, then a rename) and close it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(path)
