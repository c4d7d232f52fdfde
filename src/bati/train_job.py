"""`bati train`: one setting's runs from the command's options, or the config a run recorded, trained again.

`TrainJob` is the command's settings (the CLI is this dataclass): every `TrainConfig` setting, the seeds to
train together as one program and a recorded config to rerun; `run_train_job` trains them (`train_seeds`)
and prints one result line per seed.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Annotated

from bati.cli_hints import DEFAULT_IN_DOC
from bati.config import TrainConfig, rerun_config


@dataclass
class TrainJob(TrainConfig):
    seeds: Annotated[tuple[int, ...] | None, DEFAULT_IN_DOC] = None
    """Train several seeds as one program vmapped over them (instead of --seed); --out-dir is then the parent
    of the runs' directories <method>-seed<s> (default runs/<family>/<scale>)."""
    config: Path | None = None
    """Rerun the config a run directory recorded (its directory or config.json), exactly; only --out-dir,
    --data-root and --seeds may be given with it."""

    def train_config(self) -> TrainConfig:
        """The runs' config: the job's own settings, or the recorded one with the job's directories."""
        if self.seeds is not None and not self.seeds:
            raise ValueError("--seeds needs at least one seed (e.g. --seeds 0 1 2), or leave it out for --seed")
        config = TrainConfig(**{f.name: getattr(self, f.name) for f in fields(TrainConfig)})
        return config if self.config is None else rerun_config(self.config, config)


def run_train_job(job: TrainJob, *, console) -> None:
    """Train (or resume) the job's runs, every setting checked first; one line per seed on the rich `console`
    (progress bars only on a terminal: a log file, or a test, gets the result lines, not bar redraws)."""
    from bati.train import train_seeds

    config = job.train_config()
    run = config.resolve()  # checks every setting before any work
    family = run.config.family
    runs_dir = (config.out_dir or Path("runs") / family / config.scale) if job.seeds else None
    if job.seeds:
        config = replace(config, out_dir=None)
    seeds = job.seeds or (config.seed,)
    where = runs_dir if job.seeds else run.config.out_dir
    console.print(f"run director{'ies' if job.seeds else 'y'}: {where}"
                  + (f"/{config.method}-seed{{{','.join(map(str, seeds))}}}" if job.seeds else ""), soft_wrap=True)
    for summary in train_seeds(config, seeds, runs_dir=runs_dir, show_progress=console.is_terminal, family=run.family):
        console.print(f"{config.method} on {family}, seed {summary['seed']}: {result_line(summary)} "
                      f"(mean of the last {summary['evaluations_averaged']} evaluations)")


def result_line(summary: dict) -> str:
    """A run's final numbers in words: its returns, or on one's own data (no env) its held-out inference."""
    if "p_test_return" in summary:
        return (f"return with p_train contexts {summary['p_train_return']:.1f}, with p_test contexts "
                f"{summary['p_test_return']:.1f}")
    line = (f"held-out task-inference accuracy {summary['held_out_inference_accuracy']:.2f}, held-out "
            f"representation loss {summary['held_out_representation_loss']:.3f}")
    if "held_out_return" in summary:
        line += f", return in your env {summary['held_out_return']:.2f}"
    return line
