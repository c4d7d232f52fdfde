"""Test-time task inference with a trained likelihood method, and knowing when a context fits no known task.

For a finished run of a method with a task table and an Eq. 8 objective (bati, bati-r, bati-auto):

- `load_run(run_dir)`: the run's config, data, method and final parameters (BATI-auto calibrated first,
  as the evaluator does).
- `table_scores(run, contexts)`: for each context, its Eq. 8 objective (mean NLL per transition, with the
  method's own weighting of the reward and state terms) under every table entry.
- Unknown-task score of a context: the best (lowest) of these, i.e. how well the best known task
  explains it. Calibrated on contexts of the training tasks (windows of their own data): the threshold
  is the `quantile` (0.95) of those scores, and a context above it is flagged "unknown".
- `novelty(run)` (the `novelty` probe): over `repeats` draws of one context per task, the AUROC of telling the test tasks'
  p_train and p_test contexts from the training tasks' contexts, and the share of each flagged. On the
  `ood-tasks` data the test tasks lie outside the training range (high AUROC wanted); on the default
  data they lie inside it (a low AUROC means new tasks of the training range are not called unknown).
  The training windows come from data the model was fit on, which lowers their scores: a detector
  that only tells seen from unseen data shows a high AUROC on both.
- `infer_context(run_dir, context)`: `bati infer`, for a user's context file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bati.config import TrainConfig
from bati.data import FamilyData, sample_contexts
from bati.data.batch import TRANSITION_FIELDS
from bati.errors import BatiError
from bati.evaluate import calibrate as calibrate_method
from bati.io import read_run_config
from bati.run_dir import FinishedRun, open_run

QUANTILE = 0.95


class InferenceError(BatiError, ValueError):
    """A run or context that cannot be scored (no table, no checkpoint, bad context file)."""


@dataclass
class LoadedRun:
    run_dir: Path
    config: TrainConfig
    data: FamilyData
    method: object
    params: dict
    step: int
    family: object
    """The run's TaskFamily (OwnFamily on your own data)."""


def load_run(run_dir: Path, calibrate: bool = True, rule: str | None = None) -> LoadedRun:
    """A run of a likelihood method at its last checkpoint (BATI-auto calibrated unless `calibrate` is False);
    `rule`: with one of its test-time rules' inference (`open_run`)."""
    run_dir = Path(run_dir)
    from bati.methods import METHODS

    try:  # the recorded method first: a method without a table is one line before anything is loaded
        recorded = rule or read_run_config(run_dir).get("method")
    except (OSError, ValueError):
        recorded = None  # open_run says what is wrong with the directory
    cls = METHODS.get(recorded) if isinstance(recorded, str) else None
    if cls is not None and not (hasattr(cls, "task_latents") and hasattr(cls, "score")):
        raise InferenceError(f"{run_dir}: method {recorded!r} has no task table and likelihood to score")
    try:
        run = open_run(run_dir, rule=rule)
    except ValueError as err:
        raise InferenceError(str(err)) from err
    return scorable(run, calibrate)


def scorable(run: FinishedRun, calibrate: bool = True) -> LoadedRun:
    """An opened run (`open_run`) ready to score contexts: its method's final parameters, BATI-auto's calibrated
    unless `calibrate` is False. InferenceError for a method without a task table."""
    config, data, method = run.config, run.data, run.trainer.method
    if not hasattr(method, "task_latents") or not hasattr(method, "score"):
        raise InferenceError(f"{run.run_dir}: method {config.method!r} has no task table and likelihood to score")
    params = run.state.method.params
    if calibrate and method.calibrates:
        distances = jnp.asarray(run.inputs.family.distance_matrix(data.train_tasks, data.train_tasks), jnp.float32)
        params, _ = calibrate_method(method, params, data, config.eval_context_length, jax.random.PRNGKey(0xCA1),
                                     distances)
    return LoadedRun(run.run_dir, config, data, method, params, run.step, run.inputs.family)


def table_scores(run: LoadedRun, contexts: dict) -> np.ndarray:
    """(K, n_train): Eq. 8's objective of each of K contexts under each table entry (its mean)."""
    table = run.method.task_latents(run.params)
    contexts = {name: contexts[name] for name in TRANSITION_FIELDS}
    scores = jax.jit(jax.vmap(lambda ctx: jax.vmap(lambda z: run.method.score(run.params, ctx, z))(table)))
    return np.asarray(scores(contexts))


def auroc(positives: np.ndarray, negatives: np.ndarray) -> float:
    """P(a positive scores above a negative), ties 1/2: the area under the ROC curve."""
    p, n = np.ravel(positives)[:, None], np.ravel(negatives)[None, :]
    return float(((p > n) + 0.5 * (p == n)).mean())


def training_scores(run: LoadedRun, repeats: int, length: int, seed: int = 0) -> np.ndarray:
    """Unknown-task scores of `repeats` contexts of every training task from its own data (the calibration set)."""
    train = run.data.train
    keys = jax.random.split(jax.random.PRNGKey(seed), repeats)
    ids = jnp.arange(train.n_tasks)
    return np.concatenate([table_scores(run, sample_contexts(train, k, ids, length)).min(1) for k in keys])


def novelty(run: LoadedRun, repeats: int = 5, quantile: float = QUANTILE, seed: int = 0) -> dict:
    """AUROC and flagged shares of the test tasks' p_train / p_test contexts against the training tasks'
    (the `novelty` probe of `bati experiment unknown-tasks` saves it)."""
    length = run.config.eval_context_length
    known = training_scores(run, repeats, length, seed)
    threshold = float(np.quantile(known, quantile))
    out = {"run_dir": str(run.run_dir), "family": run.config.family, "method": run.config.method,
           "seed": run.config.seed, "step": run.step, "context_length": length, "repeats": repeats,
           "quantile": quantile, "threshold": threshold, "train_score_mean": float(known.mean())}
    scores = {}
    for source in ("p_train", "p_test"):
        task_data = getattr(run.data, source)
        ids = jnp.arange(task_data.n_tasks)
        keys = jax.random.split(jax.random.PRNGKey(seed + 1), repeats)
        scores[source] = np.concatenate([table_scores(run, sample_contexts(task_data, k, ids, length)).min(1)
                                         for k in keys])
        out[f"{source}_auroc"] = auroc(scores[source], known)
        out[f"{source}_flagged"] = float(np.mean(scores[source] > threshold))
        out[f"{source}_score_mean"] = float(scores[source].mean())
    out["p_test_vs_p_train_auroc"] = auroc(scores["p_test"], scores["p_train"])
    return out


def read_context(path: Path, obs_dim: int | None = None, action_dim: int | None = None) -> dict:
    """A context file: an .npz with observations (C, obs_dim), actions (C, action_dim), rewards (C,),
    next_observations (C, obs_dim) of real numbers, C >= 1. One-line errors naming the file and the array.
    Without the dims (before a run is loaded), every array's rows are checked against the rewards' C only."""
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as err:
        raise InferenceError(f"{path}: cannot read the context file ({err.strerror or err})") from err
    if magic[:2] != b"PK" and magic[:4] != b"\x93NUM":
        raise InferenceError(f"{path}: not an .npz file (an .npz is a zip of .npy arrays, as numpy.savez writes: "
                             f"{', '.join(TRANSITION_FIELDS)})")
    try:
        saved = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise InferenceError(f"{path}: not a readable .npz context file ({err or 'empty file'})") from err
    if not isinstance(saved, np.lib.npyio.NpzFile):
        raise InferenceError(f"{path}: one array (.npy), not an .npz context file of {', '.join(TRANSITION_FIELDS)}")
    with saved:
        raw = {}
        for name in (n for n in TRANSITION_FIELDS if n in saved.files):
            try:
                raw[name] = saved[name]
            except (ValueError, OSError, EOFError) as err:  # an object array (pickled), a damaged member
                raise InferenceError(f"{path}: {name} cannot be read as an array of numbers ({err})") from err
    missing = [name for name in TRANSITION_FIELDS if name not in raw]
    if missing:
        raise InferenceError(f"{path} lacks {', '.join(missing)}; a context file holds {', '.join(TRANSITION_FIELDS)}")
    for name, array in raw.items():
        if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
            raise InferenceError(f"{path}: {name} holds {array.dtype} values; a context holds real numbers")
    rewards = raw["rewards"]
    if rewards.ndim != 1:
        raise InferenceError(f"{path}: rewards has shape {rewards.shape}; expected (C,), one reward per transition")
    length = rewards.shape[0]
    if length < 1:
        raise InferenceError(f"{path}: the context is empty (0 transitions); give C >= 1 transitions")
    expected = {"observations": (length, obs_dim), "actions": (length, action_dim),
                "next_observations": (length, obs_dim)}
    for name, shape in expected.items():
        if shape[1] is None:  # dims not known yet: two-dimensional, C rows
            if raw[name].ndim != 2 or raw[name].shape[0] != length:
                raise InferenceError(f"{path}: {name} has shape {raw[name].shape}; expected (C, dim) with C = "
                                     f"{length} transitions (from rewards)")
            continue
        if raw[name].shape != shape:
            raise InferenceError(f"{path}: {name} has shape {raw[name].shape}; expected {shape} (C = {length} "
                                 "transitions, from rewards)")
    arrays = {name: np.asarray(raw[name], np.float32) for name in TRANSITION_FIELDS}
    for name, array in arrays.items():
        if not np.all(np.isfinite(array)):
            raise InferenceError(f"{path}: {name} holds NaN or infinite values (or values beyond float32's range)")
    return {name: jnp.asarray(a)[None] for name, a in arrays.items()}


def infer_context(run_dir: Path, context_file: Path, quantile: float = QUANTILE, repeats: int = 5) -> dict:
    """The training task that best explains a user's context, its score, and whether it is unknown."""
    if not 0.0 < quantile < 1.0:
        raise InferenceError(f"quantile must be in (0, 1), got {quantile!r}")
    read_context(Path(context_file))  # a bad file: one line now, not after the run has loaded
    run = load_run(run_dir)
    family = run.family
    spec = run.method.spec
    context = read_context(Path(context_file), spec.obs_dim, spec.action_dim)
    scores = table_scores(run, context)[0]
    best = int(np.argmin(scores))
    known = training_scores(run, repeats, min(int(context["rewards"].shape[1]), run.data.train.n_transitions))
    threshold = float(np.quantile(known, quantile))
    if not np.isfinite(scores[best]):
        raise InferenceError(f"{context_file}: its likelihood is zero under every training task (a score of "
                             f"{scores[best]}): values far outside what the run was trained on")
    return {"run_dir": str(run.run_dir), "family": family.name, "method": run.config.method,
            "context_length": int(context["rewards"].shape[1]), "task_index": best,
            "task": run.data.train_tasks[best], "score": float(scores[best]), "threshold": threshold,
            "unknown": bool(scores[best] > threshold), "quantile": quantile}
