"""Optional logging sinks beside a run's JSONL files: TensorBoard and Weights & Biases.

The JSONL files (metrics.jsonl, eval.jsonl) stay the record every report is built from; a sink only
mirrors them while training (`bati train --log-to tensorboard wandb`). Each is an extra:
`pip install 'bati[tensorboard]'` (tensorboardX, events under <run>/tensorboard/) or
`pip install 'bati[wandb]'` (a W&B run named after the run directory, resumed with it; set
WANDB_MODE=offline to keep it local). A resumed run logs again the steps after its last checkpoint.
"""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

from bati.errors import BatiError

SINKS = {"tensorboard": ("tensorboardX", "tensorboard"), "wandb": ("wandb", "wandb")}
"""name -> (module it needs, the bati extra that installs it)."""


class SinkUnavailable(BatiError, ImportError):
    """A sink whose package is not installed (the message says how to install it)."""


def check_sinks(names) -> tuple[str, ...]:
    """The sink names as a tuple; ValueError for an unknown one, SinkUnavailable for a missing package."""
    names = tuple(dict.fromkeys(names))
    for name in names:
        if name not in SINKS:
            raise ValueError(f"unknown logging sink {name!r}; choose from: {', '.join(SINKS)}")
        module, extra = SINKS[name]
        if importlib.util.find_spec(module) is None:
            raise SinkUnavailable(f"--log-to {name} needs {module}, which is not installed; install it with "
                                  f"`pip install 'bati[{extra}]'`")
    return names


class TensorBoardSink:
    def __init__(self, out: Path, config: dict):
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(str(Path(out) / "tensorboard"))
        self.writer.add_text("config", f"```\n{config}\n```")

    def log(self, step: int, values: dict, prefix: str) -> None:
        for key, value in values.items():
            if isinstance(value, (int, float)):
                self.writer.add_scalar(f"{prefix}/{key}", value, step)

    def close(self) -> None:
        self.writer.close()


class WandbSink:
    def __init__(self, out: Path, config: dict):
        import wandb

        out = Path(out).resolve()
        run_id = hashlib.sha1(str(out).encode()).hexdigest()[:16]  # the same run directory resumes one W&B run
        self.run = wandb.init(project="bati", name=out.name, id=run_id, resume="allow", dir=str(out), config=config)

    def log(self, step: int, values: dict, prefix: str) -> None:
        self.run.log({f"{prefix}/{k}": v for k, v in values.items() if isinstance(v, (int, float))}, step=step)

    def close(self) -> None:
        self.run.finish()


def open_sinks(names, out: Path, config: dict) -> list:
    """The sinks `names` for the run directory `out` (config: the run's config.json record)."""
    makers = {"tensorboard": TensorBoardSink, "wandb": WandbSink}
    return [makers[name](out, config) for name in check_sinks(names)]
