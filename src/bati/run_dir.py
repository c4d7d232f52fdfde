"""Run directories: what runs of a config train on, claiming and checking their directories, resuming their
records, their summaries (eval.json), and opening a finished run again.

A run directory holds config.json (the resolved config; a directory belongs to one), metrics.jsonl and
eval.jsonl (one line per log / evaluation step), checkpoint.msgpack, eval.json (the summary) and, on your own
datasets, datasets.json (their sha256). A run's test-time rules (bati-r, bati-auto in a bati run:
`TaskInference.trains_as`) are evaluated into its own eval.jsonl and eval.json, under "rules".
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import jax
import numpy as np

from bati.checkpoints import CHECKPOINT_NAME, load_checkpoint
from bati.config import NOT_IDENTITY, ResolvedRun, TrainConfig, differing_settings
from bati.data import FamilyData
from bati.data.own import load_own_data
from bati.device import machine_record
from bati.errors import BatiError
from bati.experts.zoo import load_for as load_expert
from bati.io import (
    LOCK_NAME,
    atomic_write_json,
    atomic_write_text,
    check_directory,
    check_run_config,
    code_record,
    hold_lock,
    read_jsonl,
    read_jsonl_lines,
    read_run_config,
    rules_evaluated,
)
from bati.methods import check_rules
from bati.trainer import Trainer, TrainState

__all__ = ["FinishedRun", "RunInputs", "TrainingError", "check_rules_evaluated", "check_seeds",
           "claim_run_dirs", "drop_records_after", "open_run", "own_env", "summarize_evaluations", "summarize_run"]

DATASETS_RECORD = "datasets.json"


class TrainingError(BatiError, RuntimeError):
    """Training cannot go on (e.g. a NaN loss); earlier checkpoints are left untouched."""


def check_seeds(seeds) -> tuple[int, ...]:
    """The seeds as a tuple, or ValueError unless they are distinct integers >= 0, at least one."""
    seeds = tuple(seeds)
    if not seeds or len(set(seeds)) != len(seeds) or any(not isinstance(s, int) or s < 0 for s in seeds):
        raise ValueError(f"seeds must be distinct integers >= 0 (at least one), got {list(seeds)}")
    return seeds


def check_rules_evaluated(out: Path, rules: tuple[str, ...]) -> None:
    """ValueError (one line) unless every evaluation in `out`'s eval.jsonl holds every rule of `rules`: a rule
    asked for after its run began cannot be evaluated at the steps already past."""
    held = rules_evaluated(out) if rules else None
    missing = [rule for rule in rules if held is not None and rule not in held]
    if missing:
        raise ValueError(f"{out} has evaluations without {', '.join(missing)} (the run began without it): train "
                         f"{missing[0]} on its own, in a run directory of its own")


@contextlib.contextmanager
def claim_run_dirs(runs: list[ResolvedRun]):
    """Hold the run directories of `runs` (locks) while training: each is checked before anything is written (a
    file in its place, an unwritable data root, a directory of another config: one line), and one this call
    creates is forgotten again if it fails before its first record."""
    _check_paths(runs)
    with contextlib.ExitStack() as claimed:
        for run in runs:
            out = run.config.out_dir
            claimed.enter_context(hold_lock(out / LOCK_NAME, f"the run directory {out}"))
            claimed.enter_context(_forgotten_unless_started(out))
            _check_run_dir(out, run)
        yield


def _check_paths(runs: list[ResolvedRun]) -> None:
    """Refuse run directories and a data root that are files (or unwritable where we must write) with
    one line, before anything is written anywhere."""
    from bati.data import store

    for run in runs:
        check_directory(run.config.out_dir, "the run directory")
    c = runs[0].collection
    if c is None:  # a user's own datasets: read, never written
        return
    collection = store.collection_dir(c.root, c.family, c.scale, c.seed, c.noise, c.tasks, c.experts)
    check_directory(c.root, "the data root", writable=not (collection / store.MANIFEST).is_file())


@contextlib.contextmanager
def _forgotten_unless_started(out: Path):
    """A run directory this call creates is removed again if it fails before its first record (e.g. no
    data, Ctrl-C while collecting): the next attempt may then use other settings without being refused."""
    fresh = not (out / "config.json").exists()
    try:
        yield
    except BaseException:
        left = {p.name for p in out.iterdir()} if out.is_dir() else set()
        if fresh and left <= {"config.json", DATASETS_RECORD, LOCK_NAME}:
            (out / "config.json").unlink(missing_ok=True)
            (out / DATASETS_RECORD).unlink(missing_ok=True)
        raise


def own_env(config: TrainConfig, data) -> tuple:
    """(family, episode length) of the user's --eval-env for a run on own data, or () without one; EnvError
    (one line) if its spaces do not match the data's."""
    if config.eval_env is None:
        return ()
    from bati.data.own import EnvError, OwnFamily, check_eval_env

    length = check_eval_env(config.eval_env, config.task_key)
    family = OwnFamily(config.context_length, config.eval_env, config.task_key)
    probe = family.make_env(data.train_tasks[0])
    try:
        shapes = (probe.observation_space.shape, probe.action_space.shape)
        if shapes != ((data.obs_dim,), (data.action_dim,)):
            raise EnvError(f"--eval-env {config.eval_env!r} has observations {shapes[0]} and actions {shapes[1]}, "
                           f"but your datasets have ({data.obs_dim},) and ({data.action_dim},)")
        try:  # once before any work: an env that cannot reset fails now, not at the first evaluation
            probe.reset(seed=0)
        except Exception as err:  # the user's env's own error
            raise EnvError(f"--eval-env {config.eval_env!r} failed to reset to your first task "
                           f"({type(err).__name__}: {err})") from err
    finally:
        probe.close()
    return family, length


def check_datasets_unchanged(out: Path, fingerprint: dict[str, str]) -> None:
    """Record your datasets' sha256 with the run (datasets.json) or, when it has them, refuse to go on if
    they changed since: a resumed run would train on two versions of its data."""
    path = out / DATASETS_RECORD
    if path.is_file():
        recorded = json.loads(path.read_text())
        changed = sorted(d for d in set(recorded) | set(fingerprint) if recorded.get(d) != fingerprint.get(d))
        if changed:
            raise TrainingError(f"{out}: your dataset(s) {', '.join(changed)} changed since this run started "
                                f"(sha256 in {path}); restore them or train into another --out-dir")
        return
    atomic_write_json(path, fingerprint)


@dataclass
class RunInputs:
    """What runs of one config train on, read once at the entry point and passed down: the resolved run,
    its data and the family's expert (None on your own data)."""

    run: ResolvedRun
    data: FamilyData
    expert: object | None

    @property
    def config(self) -> TrainConfig:
        return self.run.config

    @property
    def family(self):
        """The family object (an OwnFamily for your own datasets)."""
        return self.run.family

    @classmethod
    def read(cls, run: ResolvedRun, show_progress: bool = True, collect: bool = True) -> RunInputs:
        """The inputs of a resolved run: its data collected if missing (`collect`) or read as it is."""
        config, family = run.config, run.family
        if config.datasets:
            data = load_own_data(config.datasets, config.task_key, config.context_length, config.held_out,
                                 seed=config.data_seed)
            if config.task_batch > len(data.train_tasks):
                raise ValueError(f"task_batch ({config.task_batch}) must be at most the {len(data.train_tasks)} tasks "
                                 "of your datasets: give --task-batch")
            return cls(run, data, None)
        from bati.methods import METHODS

        # training needs the expert (collection, reference returns): none is one line now, not after training;
        # a finished run is opened without it unless its method imitates it (DPT)
        needs_expert = collect or METHODS[config.method].needs_expert_actions
        expert = load_expert(family, config.zoo_dir, config.experts) if needs_expert else None
        data = run.collection.ensure(show_progress, config.zoo_dir) if collect else run.collection.load()
        return cls(run, data, expert)

    def trainer(self) -> Trainer:
        return Trainer(self.config, self.data, self.family, self.expert)

    def with_method(self, method: str) -> RunInputs:
        """The same run, data and expert with `method`, a test-time rule of this run (it trains exactly as it)."""
        return replace(self, run=replace(self.run, config=replace(self.config, method=method)))


@dataclass
class FinishedRun:
    """A run opened again from its directory (`open_run`): its resolved config, inputs, trainer (the method
    and IQL) and the state of its last checkpoint."""

    run_dir: Path
    inputs: RunInputs
    trainer: Trainer
    state: TrainState

    @property
    def config(self) -> TrainConfig:
        return self.inputs.config

    @property
    def data(self) -> FamilyData:
        return self.inputs.data

    @property
    def step(self) -> int:
        return int(self.state.step)


def open_run(run_dir: Path, finished: bool = False, rule: str | None = None) -> FinishedRun:
    """The run in `run_dir` at its last checkpoint, on the data it was trained on (read, never collected):
    the one way inference (bati infer, novelty) and probes open a run. `rule`: with the inference of one of its
    test-time rules (bati-r, bati-auto in a bati run). ValueError naming the directory when it holds no run
    config or no checkpoint, or (with `finished`) when the run has not reached its last step."""
    run_dir = Path(run_dir)
    config = TrainConfig.from_record(read_run_config(run_dir))
    if rule is not None and rule != config.method:
        config = replace(config, method=check_rules(config.method, (rule,), bool(config.datasets))[0])
    run = config.resolve()
    config = run.config
    checkpoint = run_dir / CHECKPOINT_NAME
    if not checkpoint.is_file():
        raise ValueError(f"{run_dir} has no checkpoint: train (or resume) the run first")
    inputs = RunInputs.read(run, show_progress=False, collect=False)
    trainer = inputs.trainer()
    state = load_checkpoint(checkpoint, trainer.init(jax.random.PRNGKey(0)))
    if finished and int(state.step) != config.steps:
        raise ValueError(f"{run_dir} is at step {int(state.step)} of {config.steps}: finish the run first")
    return FinishedRun(run_dir, inputs, trainer, state)


def summarize_run(out: Path, last: int = 5) -> dict:
    """The run's eval.json without its session's records: who it is, the summary of its own evaluations
    (`summarize_evaluations`) and its config."""
    config = read_run_config(out)
    evaluations = summarize_evaluations(out, last=last)
    summary = {"family": config["family"], "method": config["method"], "seed": config["seed"],
               "scale": config["scale"], "steps": evaluations["curve"][-1]["step"], **evaluations}
    summary["config"] = {k: v for k, v in config.items() if k != "runtime"}
    return summary


def summarize_evaluations(out: Path, rule: str | None = None, last: int = 5) -> dict:
    """The paper's number: mean of the last `last` evaluations in `out`'s eval.jsonl, per context distribution; with
    the curve and a method's own numbers. `rule`: those of one of the run's test-time rules."""
    evals = read_jsonl(out / "eval.jsonl", require=("step",))
    if not evals:
        raise ValueError(f"{out / 'eval.jsonl'} holds no evaluation; resume the run to redo them")
    if rule is not None:
        evals = [{"step": e["step"], **e["rules"][rule]} for e in evals]
    tail = evals[-last:]
    summary = {"evaluations_averaged": len(tail)}
    for source in ("p_test", "p_train") if "p_test_return" in evals[-1] else ():  # own data: no env, no returns
        summary[f"{source}_return"] = float(np.mean([e[f"{source}_return"] for e in tail]))
        summary[f"{source}_inference_error"] = float(np.mean([e[f"{source}_inference_error"] for e in tail]))
        summary[f"{source}_task_returns"] = evals[-1][f"{source}_task_returns"]
    for name in ("held_out_inference_accuracy", "held_out_representation_loss", "held_out_return"):  # own data's
        if name in evals[-1]:
            summary[name] = float(np.mean([e[name] for e in tail]))
    if "held_out_task_returns" in evals[-1]:
        summary["held_out_task_returns"] = evals[-1]["held_out_task_returns"]
    curve_keys = ("step", "p_test_return", "p_train_return", "p_test_inference_error", "p_train_inference_error",
                  "held_out_inference_accuracy", "held_out_representation_loss", "held_out_return")
    summary["curve"] = [{k: e[k] for k in curve_keys if k in e} for e in evals]
    # a method's own numbers (e.g. BATI-auto's calibrated state weight), averaged like the returns
    extra = [k for k, v in evals[-1].items() if k not in curve_keys and isinstance(v, (int, float))
             and all(isinstance(e.get(k), (int, float)) for e in tail)]
    if extra:
        summary["diagnostics"] = {k: float(np.mean([e[k] for e in tail])) for k in extra}
    return summary


def _check_run_dir(out: Path, run: ResolvedRun) -> None:
    """A run directory belongs to one resolved config: refuse to resume a run that differs in any setting."""
    current = run.record()
    identity = tuple(k for k in current if k not in NOT_IDENTITY)
    runtime = {**machine_record(), **code_record()}
    check_run_config(out / "config.json", {**current, "runtime": runtime}, identity, differing_settings)


def drop_records_after(out: Path, step: int) -> None:
    """Forget log lines written after the checkpoint we resume from (they will be redone)."""
    for name in ("metrics.jsonl", "eval.jsonl"):
        path = out / name
        if path.exists():  # a torn last line (a kill mid-append) is dropped with a warning
            text = "".join(line + "\n" for line, record in read_jsonl_lines(path, require=("step",))
                           if record["step"] <= step)
            if text.encode() != path.read_bytes():
                atomic_write_text(path, text)
