"""Training runs: run directories, resume, several seeds at once, evaluations and the run's summary.

The algorithm itself is bati.trainer (pure JAX, no files). This module is its edge: it resolves a config
once (family, data, expert), claims and checks the run directories, brings resumed seeds level, writes
metrics.jsonl, eval.jsonl, checkpoint.msgpack (bati.checkpoints) and eval.json, and opens a finished run
again (`open_run`) for inference and probes.

Methods that train exactly as another and differ only at test time (bati-r and bati-auto train as bati,
`TaskInference.trains_as`) can be evaluated alongside its run (`also`): at every evaluation, the same states
with the same keys are evaluated with their inference too, into their own run directories beside it
(`<method>-seed<s>`), which end up as those of a run trained alone: the same config.json, metrics.jsonl
(copied), eval.jsonl, checkpoint and eval.json (plus `trained_with`, the sibling that trained).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from bati.checkpoints import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
from bati.config import NOT_IDENTITY, TrainConfig, differing_settings, family_of
from bati.data import FamilyData, ensure_family_data, load_family_data
from bati.data.own import load_own_data
from bati.errors import BatiError
from bati.evaluate import Evaluator, OfflineEvaluator, reference_returns
from bati.experts import load as load_expert
from bati.io import (
    LOCK_NAME,
    append_jsonl,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    check_directory,
    check_run_config,
    code_record,
    hold_lock,
    read_jsonl,
    read_jsonl_lines,
    read_run_config,
)
from bati.sinks import open_sinks
from bati.trainer import Trainer, TrainState

__all__ = ["FinishedRun", "TrainingError", "open_run", "train", "train_seeds"]


class TrainingError(BatiError, RuntimeError):
    """Training cannot go on (e.g. a NaN loss); earlier checkpoints are left untouched."""


def train(config: TrainConfig, show_progress: bool = True) -> dict:
    """Train (or resume) one run; returns its final evaluation summary (also in eval.json)."""
    return train_seeds(config, (config.seed,), show_progress=show_progress)[0]


def train_seeds(config: TrainConfig, seeds: tuple[int, ...], show_progress: bool = True,
                runs_dir: Path | None = None, references: dict | None = None, also: tuple[str, ...] = ()) -> list[dict]:
    """Train (or resume) one run per seed of one config as one compiled program vmapped over seeds.

    Each seed has its own run directory (`runs_dir/<method>-seed<s>`, default: the config's default
    directory), metrics, evaluations and checkpoints, exactly as a run trained alone; seed s gives the
    numbers of the single-seed run s to float tolerance. Runs resumed from checkpoints of different
    steps are first brought level (the ones behind advance alone), then go on together.
    Returns the runs' summaries (also in each eval.json), in the order of `seeds`. `references`: the
    collection's random and expert returns when the caller has them (`bati run` computes them once for all
    its methods); by default they are computed here. `also`: methods that train exactly as this one, evaluated
    alongside each run into `<method>-seed<s>` beside it (see the module docstring); one that is finished, has
    a checkpoint of its own or has evaluations the run does not match is left alone (it trains on its own).
    """
    seeds = check_seeds(seeds)
    if len(seeds) > 1 and config.out_dir is not None and runs_dir is None:
        raise ValueError("several seeds need one directory each: give runs_dir (the parent), not out_dir")
    also = _check_also(config, also)
    configs = [replace(config, seed=s, out_dir=(runs_dir / f"{config.method}-seed{s}") if runs_dir else
                       config.out_dir).resolved() for s in seeds]
    alongside = [[_alongside_config(c, method) for method in also] for c in configs]
    _check_paths(configs + [a for group in alongside for a in group])
    with contextlib.ExitStack() as claimed:
        for c in configs + [a for group in alongside for a in group]:  # claim the run directories (or refuse them)
            claimed.enter_context(hold_lock(c.out_dir / LOCK_NAME, f"the run directory {c.out_dir}"))
            claimed.enter_context(_forgotten_unless_started(c.out_dir))
            _check_run_dir(c.out_dir, c)
        return _train_claimed(configs, show_progress, references, alongside)


def _check_also(config: TrainConfig, also) -> tuple[str, ...]:
    """The methods to evaluate alongside `config`'s runs, or ValueError (one line) for one that trains otherwise."""
    from bati.methods import METHODS, training_of

    also = tuple(dict.fromkeys(also))
    for method in also:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r} to evaluate alongside; choose from: {', '.join(METHODS)}")
        if method == config.method or training_of(method) != training_of(config.method):
            raise ValueError(f"{method!r} does not train exactly as {config.method!r}, so it cannot be evaluated "
                             "alongside it (methods that share a training: bati, bati-r, bati-auto)")
    if also and config.datasets:
        raise ValueError("evaluating methods alongside a run needs a family's p_train and p_test contexts, not your "
                         "own datasets: train each method on its own")
    return also


def _alongside_config(config: TrainConfig, method: str) -> TrainConfig:
    """The config of `method` evaluated alongside the run of `config`: its sibling run directory."""
    if config.out_dir.name != f"{config.method}-seed{config.seed}":
        raise ValueError(f"evaluating methods alongside a run needs the sweep's run directories, named "
                         f"<method>-seed<seed>, not {config.out_dir.name!r}")
    return replace(config, method=method, out_dir=config.out_dir.parent / f"{method}-seed{config.seed}").resolved()


def _follows(run: _SeedRun, companion: TrainConfig) -> bool:
    """Whether `companion` is evaluated alongside `run` from here: not finished, no checkpoint of its own, and
    exactly the run's evaluations so far (none for a fresh run); its records after the run's step are dropped."""
    out = companion.out_dir
    if (out / "eval.json").exists() or (out / CHECKPOINT_NAME).exists():
        return False

    def steps(directory: Path) -> list[int]:
        path = directory / "eval.jsonl"
        return [r["step"] for r in read_jsonl(path, require=("step",))] if path.exists() else []

    if [s for s in steps(out) if s <= run.step] != steps(run.out):
        return False
    _drop_records_after(out, run.step)
    return True


def _check_paths(configs: list[TrainConfig]) -> None:
    """Refuse run directories and a data root that are files (or unwritable where we must write) with
    one line, before anything is written anywhere."""
    from bati.data import store

    for c in configs:
        check_directory(c.out_dir, "the run directory")
    c = configs[0]
    if c.datasets:  # a user's own datasets: read, never written
        return
    collection = store.collection_dir(c.data_root, family_of(c.family), c.data_scale, c.data_seed, c.noise,
                                      c.task_split(), c.experts)
    check_directory(c.data_root, "the data root", writable=not (collection / store.MANIFEST).is_file())


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


DATASETS_RECORD = "datasets.json"


def _check_datasets_unchanged(out: Path, fingerprint: dict[str, str]) -> None:
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
    """What runs of one config train on, resolved once at the entry point and passed down: the family
    (an OwnFamily for your own datasets), the data and the family's expert (None on your own data)."""

    config: TrainConfig
    family: object
    data: FamilyData
    expert: object | None

    @classmethod
    def resolve(cls, config: TrainConfig, show_progress: bool = True, collect: bool = True) -> RunInputs:
        """The inputs of a resolved config: its data collected if missing (`collect`) or read as it is."""
        family = family_of(config.family, config.context_length)
        if config.datasets:
            data = load_own_data(config.datasets, config.task_key, config.context_length, config.held_out,
                                 seed=config.data_seed)
            if config.task_batch > len(data.train_tasks):
                raise ValueError(f"task_batch ({config.task_batch}) must be at most the {len(data.train_tasks)} tasks "
                                 "of your datasets: give --task-batch")
            return cls(config, family, data, None)
        from bati.methods import METHODS

        # training needs the expert (collection, reference returns): none is one line now, not after training;
        # a finished run is opened without it unless its method imitates it (DPT)
        needs_expert = collect or METHODS[config.method].needs_expert_actions
        expert = load_expert(config.family, config.zoo_dir, config.experts) if needs_expert else None
        if collect:
            data = ensure_family_data(family, config.data_scale, config.data_seed, config.noise,
                                      config.data_root, n_episodes=config.episodes_per_task,
                                      n_context_episodes=config.context_episodes, progress=show_progress,
                                      tasks=config.task_split(), zoo_dir=config.zoo_dir, experts=config.experts)
        else:
            data = load_family_data(family, config.data_scale, config.data_seed, config.noise,
                                    config.data_root, tasks=config.task_split(), experts=config.experts)
        return cls(config, family, data, expert)

    def trainer(self) -> Trainer:
        return Trainer(self.config, self.data, self.family, self.expert)


def _train_claimed(configs: list[TrainConfig], show_progress: bool, references: dict | None,
                   alongside: list[list[TrainConfig]]) -> list[dict]:
    """train_seeds once its run directories are checked, claimed and locked."""
    config, seeds = configs[0], [c.seed for c in configs]
    inputs = RunInputs.resolve(config, show_progress)
    data, trainer = inputs.data, inputs.trainer()
    if config.datasets:
        evaluator = OfflineEvaluator(trainer, data, config.eval_context_length, *own_env(config, data))
        for c in configs:  # the data a run started on is the data it resumes on
            _check_datasets_unchanged(Path(c.out_dir), data.manifest["fingerprint"])
    else:
        evaluator = Evaluator(trainer.method, trainer.iql, data, config.eval_context_length, family=inputs.family,
                              workers=config.eval_workers)
    runs = [_SeedRun.open(c, trainer) for c in configs]
    for run, group in zip(runs, alongside):
        run.alongside = [a for a in group if _follows(run, a)]
    companions = {a.method: Evaluator(replace(inputs, config=a).trainer().method, trainer.iql, data,
                                      config.eval_context_length, family=inputs.family, workers=config.eval_workers)
                  for run in runs for a in run.alongside}
    start = time.perf_counter()
    progress = Progress(
        TextColumn(f"[bold]{config.method} on {config.family}" + (f" x{len(seeds)} seeds" if len(seeds) > 1 else "")),
        BarColumn(), TextColumn("{task.completed:,}/{task.total:,}"), TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(), TimeRemainingColumn(), disable=not show_progress,
    )
    with progress:
        bar = progress.add_task("train", total=config.steps, completed=min(r.step for r in runs), status="")
        try:
            while (behind := min(r.step for r in runs)) < config.steps:
                group = [r for r in runs if r.step == behind]
                until = min([r.step for r in runs if r.step > behind] + [config.steps])
                _advance(trainer, evaluator, data, group, until, start, progress, bar, companions)
        finally:
            evaluator.close()
            for companion in companions.values():
                companion.close()
            for run in runs:
                for sink in run.sinks:
                    sink.close()
    if references is None and not config.datasets:
        references = reference_returns(data, family=inputs.family, expert=inputs.expert)
    session = {"device": describe_device(), "jax_version": jax.__version__, **code_record(),
               "wall_time_s": round(time.perf_counter() - start, 2)}
    recorded = {k: data.manifest[k] for k in ("n_episodes", "n_context_episodes", "transitions", "transitions_read",
                                              "tasks") if k in data.manifest}
    if not config.datasets:  # own data is fingerprinted by its files (data.manifest["fingerprint"])
        recorded["fingerprint"] = data.fingerprint()
    summaries = []
    for run in runs:
        summary = {**summarize_run(run.out), "reference_returns": references, **session, "data": recorded}
        atomic_write_json(run.out / "eval.json", summary)
        summaries.append(summary)
        for companion in run.alongside:  # the run's training is theirs: its logs and checkpoint, their evaluations
            out = companion.out_dir
            atomic_write_text(out / "metrics.jsonl", (run.out / "metrics.jsonl").read_text())
            atomic_write_bytes(out / CHECKPOINT_NAME, (run.out / CHECKPOINT_NAME).read_bytes())
            atomic_write_json(out / "eval.json", {
                **summarize_run(out), "reference_returns": references, **session, "data": recorded,
                "wall_time_s": round(run.alongside_seconds.get(companion.method, 0.0), 2),
                "trained_with": run.out.name})
    return summaries


def check_seeds(seeds) -> tuple[int, ...]:
    """The seeds as a tuple, or ValueError unless they are distinct integers >= 0, at least one."""
    seeds = tuple(seeds)
    if not seeds or len(set(seeds)) != len(seeds) or any(not isinstance(s, int) or s < 0 for s in seeds):
        raise ValueError(f"seeds must be distinct integers >= 0 (at least one), got {list(seeds)}")
    return seeds


@dataclass
class _SeedRun:
    """One seed's run directory and its state on the host side of the training loop."""

    config: TrainConfig
    state: TrainState
    base_key: jax.Array
    sinks: list = field(default_factory=list)
    """Optional mirrors of the JSONL logs (TensorBoard, W&B: `--log-to`)."""
    alongside: list[TrainConfig] = field(default_factory=list)
    """Runs of methods evaluated alongside this one (`train_seeds(..., also=...)`)."""
    alongside_seconds: dict[str, float] = field(default_factory=dict)
    """Wall time of each one's evaluations (its whole cost: the training is this run's)."""

    @property
    def out(self) -> Path:
        return self.config.out_dir

    @property
    def step(self) -> int:
        return int(self.state.step)

    @classmethod
    def open(cls, config: TrainConfig, trainer: Trainer) -> _SeedRun:
        """Start fresh or resume from the run directory's checkpoint (the directory is already claimed)."""
        base_key = jax.random.PRNGKey(config.seed)
        state = trainer.init(jax.random.fold_in(base_key, 0))
        if (config.out_dir / CHECKPOINT_NAME).exists():
            state = load_checkpoint(config.out_dir / CHECKPOINT_NAME, state)
        _drop_records_after(config.out_dir, int(state.step))
        sinks = open_sinks(config.log_to, config.out_dir, config.record()) if config.log_to else []
        return cls(config, state, base_key, sinks)


CHECKPOINT_SECONDS = 600.0
"""Besides every checkpoint_every steps, a run checkpoints at the first log boundary this long (wall time)
after its last checkpoint, so a kill loses at most about this much work. A run resumed from any log
boundary gives the same numbers (step t's key is fold_in(key, t)), so this changes no result."""


def _advance(trainer: Trainer, evaluator: Evaluator, data, runs: list[_SeedRun], until: int, start: float,
             progress, bar, companions: dict[str, Evaluator] | None = None) -> None:
    """Train `runs` (all at the same step) together up to step `until`: chunks of log_every steps,
    vmapped over the runs when there are several, with their logs, evaluations and checkpoints; `companions`:
    the evaluator of each method evaluated alongside some of the runs. With `eval_beside_training` an evaluation
    runs in a thread while the next chunks train, and the checkpoint of its step is saved once its records are
    written (so a resumed run never lacks an evaluation before its checkpoint); the numbers are the same."""
    c = runs[0].config
    step = runs[0].step
    last_checkpoint = time.monotonic()
    train_keys = jnp.stack([jax.random.fold_in(r.base_key, 1) for r in runs])
    alone = len(runs) == 1  # the plain program: a run trained alone gives exactly its own numbers
    # The states stay on the device, stacked over the runs, between chunks; each run's own state is cut out
    # only where it is needed (a checkpoint, the end): cutting ~125 leaves per run after every chunk cost
    # ~45 ms per 100 steps for 3 runs (measured on the CPU), the device idle meanwhile.
    state = runs[0].state if alone else None
    states = None if alone else jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[r.state for r in runs])

    def stacked():
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], state) if alone else states

    def sync_runs():
        for j, run in enumerate(runs):
            run.state = state if alone else jax.tree_util.tree_map(lambda x, j=j: x[j], states)

    def evaluation_inputs(at: int, members: list[int] | None = None):
        """The stacked states, keys and env seeds of an evaluation at step `at` (of the runs `members` only)."""
        keys = jnp.stack([jax.random.fold_in(r.base_key, 2 + at) for r in runs])
        seeds = [r.config.seed * 7919 + at for r in runs]
        if members is None or len(members) == len(runs):
            return stacked(), keys, seeds
        picked = jnp.asarray(members)
        return (jax.tree_util.tree_map(lambda x: x[picked], stacked()), keys[picked], [seeds[j] for j in members])

    def followers(method: str) -> list[int]:
        """The runs that `method` is evaluated alongside."""
        return [j for j, run in enumerate(runs) if any(a.method == method for a in run.alongside)]

    def evaluations(at: int) -> list[tuple]:
        """What the evaluation at step `at` evaluates, fixed now (the states move on): (method, evaluator,
        inputs, members) for the runs (method None) and for each method evaluated alongside some of them."""
        out = [(None, evaluator, evaluation_inputs(at), list(range(len(runs))))]
        for method, companion in (companions or {}).items():
            if members := followers(method):
                out.append((method, companion, evaluation_inputs(at, members), members))
        return out

    def evaluate(todo: list[tuple]) -> list[tuple]:
        """Run the evaluations (here or in the evaluation thread): (method, members, results, seconds) each."""
        done = []
        for method, each, inputs, members in todo:
            began = time.perf_counter()
            results = each.evaluate_runs(*inputs)
            done.append((method, members, results, time.perf_counter() - began))
        return done

    def write_evaluations(at: int, done: list[tuple]) -> None:
        for method, members, results, seconds in done:
            for j, result in zip(members, results):
                if method is None:
                    append_jsonl(runs[j].out / "eval.jsonl", {"step": at, **result.summary()})
                    for sink in runs[j].sinks:
                        sink.log(at, result.summary(), "eval")
                    continue
                out = next(a.out_dir for a in runs[j].alongside if a.method == method)
                append_jsonl(out / "eval.jsonl", {"step": at, **result.summary()})
                spent = runs[j].alongside_seconds
                spent[method] = spent.get(method, 0.0) + seconds / len(members)
        progress.update(bar, status=evaluator.status(done[0][2]))

    def save_checkpoints(snapshot) -> None:
        """Each run's checkpoint from the (stacked) state `snapshot`."""
        nonlocal last_checkpoint
        for j, run in enumerate(runs):
            own = snapshot if alone else jax.tree_util.tree_map(lambda x, j=j: x[j], snapshot)
            save_checkpoint(run.out / CHECKPOINT_NAME, own)
        last_checkpoint = time.monotonic()

    beside = ThreadPoolExecutor(1, thread_name_prefix="bati-eval") if c.eval_beside_training else None
    pending = None  # the evaluation running beside training: (step, future, the state to checkpoint or None)

    def land() -> None:
        """Wait for the evaluation running beside training, write its records, then its step's checkpoint."""
        nonlocal pending
        if pending is None:
            return
        at, future, snapshot = pending
        pending = None
        write_evaluations(at, future.result())
        if snapshot is not None:
            save_checkpoints(snapshot)

    if (step // c.eval_every + 1) * c.eval_every <= until or until == c.steps:  # an evaluation comes: prepare it
        evaluator.warm_up(*evaluation_inputs(step))
        for method, companion in (companions or {}).items():
            if members := followers(method):
                companion.warm_up(*evaluation_inputs(step, members))

    try:
        while step < until:
            length = min(c.log_every, until - step)
            if alone:
                state, metrics = trainer.run_chunk(state, train_keys[0], data.train, length=length)
                metrics = jax.tree_util.tree_map(lambda x: x[None], metrics)
            else:
                states, metrics = trainer.run_chunks(states, train_keys, data.train, length=length)
            step += length
            metrics = jax.device_get(metrics)
            for j, run in enumerate(runs):
                record = {k: float(v[j]) for k, v in metrics.items()}
                bad = [k for k, v in record.items() if not math.isfinite(v)]
                if bad:
                    raise TrainingError(f"{run.out}: non-finite {', '.join(bad)} at step {step}; the last good "
                                        f"checkpoint (if any) is untouched in {run.out / CHECKPOINT_NAME}")
                append_jsonl(run.out / "metrics.jsonl",
                             {"step": step, "wall_time": time.perf_counter() - start, **record})
                for sink in run.sinks:
                    sink.log(step, record, "train")
            checkpoint = (step % c.checkpoint_every == 0 or step == c.steps
                          or time.monotonic() - last_checkpoint >= CHECKPOINT_SECONDS)
            if step % c.eval_every == 0 or step == c.steps:
                land()  # the one before, in step order
                if beside is None:
                    write_evaluations(step, evaluate(evaluations(step)))
                else:
                    snapshot = (state if alone else states) if checkpoint else None
                    pending = (step, beside.submit(evaluate, evaluations(step)), snapshot)
                    checkpoint = False  # saved by land(), after this evaluation's records
            if checkpoint:
                land()  # never a checkpoint ahead of an evaluation not yet written
                save_checkpoints(state if alone else states)
            progress.update(bar, completed=step)  # the runs behind set the pace
        land()
    finally:
        if beside is not None:
            beside.shutdown(wait=True, cancel_futures=True)
    sync_runs()


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


def open_run(run_dir: Path, finished: bool = False) -> FinishedRun:
    """The run in `run_dir` at its last checkpoint, on the data it was trained on (read, never collected):
    the one way inference (bati infer, novelty) and probes open a run. ValueError naming the directory
    when it holds no run config or no checkpoint, or (with `finished`) when the run has not reached its
    last step."""
    run_dir = Path(run_dir)
    config = TrainConfig.from_record(read_run_config(run_dir)).resolved()
    checkpoint = run_dir / CHECKPOINT_NAME
    if not checkpoint.is_file():
        raise ValueError(f"{run_dir} has no checkpoint: train (or resume) the run first")
    inputs = RunInputs.resolve(config, show_progress=False, collect=False)
    trainer = inputs.trainer()
    state = load_checkpoint(checkpoint, trainer.init(jax.random.PRNGKey(0)))
    if finished and int(state.step) != config.steps:
        raise ValueError(f"{run_dir} is at step {int(state.step)} of {config.steps}: finish the run first")
    return FinishedRun(run_dir, inputs, trainer, state)


def describe_device() -> str:
    """The accelerator JAX runs on, as JAX reports it (e.g. "gpu: NVIDIA H100 80GB HBM3 x1"); on a CPU its
    model too (e.g. "cpu: 2-core AMD EPYC (x86_64) x1"): XLA's kernels, and with them the last bits of a float,
    differ between CPU models, which a chaotic MuJoCo rollout amplifies (docs/reliability.md)."""
    devices = jax.devices()
    first = devices[0]
    kind = first.device_kind if first.platform != "cpu" else f"{os.cpu_count()}-core {cpu_model()} ({platform.machine()})"
    return f"{first.platform}: {kind} x{len(devices)}"


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name from /proc/cpuinfo, with its widest vector instructions where the flags name them
    (e.g. "AMD EPYC, AVX-512"): XLA picks its CPU kernels by them, and two machines that both call themselves
    "AMD EPYC" gave different AntDir data for the same seed, one with AVX-512 and one without (docs/reliability.md).
    "CPU" where there is no model name (e.g. not on Linux)."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return "CPU"
    field = lambda key: next((line.split(":", 1)[1] for line in lines if line.startswith(key) and ":" in line), "")  # noqa: E731
    model, flags = " ".join(field("model name").split()) or "CPU", set(field("flags").split())
    vector = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "AVX" if "avx" in flags else ""
    return f"{model}, {vector}" if vector and model != "CPU" else model


def summarize_run(out: Path, last: int = 5) -> dict:
    """The paper's number: mean of the last `last` evaluations, per context distribution."""
    evals = read_jsonl(out / "eval.jsonl", require=("step",))
    if not evals:
        raise ValueError(f"{out / 'eval.jsonl'} holds no evaluation; resume the run to redo them")
    config = read_run_config(out)
    tail = evals[-last:]
    summary = {"family": config["family"], "method": config["method"], "seed": config["seed"],
               "scale": config["scale"], "steps": evals[-1]["step"], "evaluations_averaged": len(tail)}
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
    summary["config"] = {k: v for k, v in config.items() if k != "runtime"}
    return summary


def _check_run_dir(out: Path, config: TrainConfig) -> None:
    """A run directory belongs to one resolved config: refuse to resume a run that differs in any setting."""
    current = config.record()
    identity = tuple(k for k in current if k not in NOT_IDENTITY)
    runtime = {"device": describe_device(), "jax_version": jax.__version__, **code_record()}
    check_run_config(out / "config.json", {**current, "runtime": runtime}, identity, differing_settings)


def _drop_records_after(out: Path, step: int) -> None:
    """Forget log lines written after the checkpoint we resume from (they will be redone)."""
    for name in ("metrics.jsonl", "eval.jsonl"):
        path = out / name
        if path.exists():  # a torn last line (a kill mid-append) is dropped with a warning
            text = "".join(line + "\n" for line, record in read_jsonl_lines(path, require=("step",))
                           if record["step"] <= step)
            if text.encode() != path.read_bytes():
                atomic_write_text(path, text)


