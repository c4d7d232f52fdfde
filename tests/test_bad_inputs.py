"""A catalogue of bad inputs and faults a user meets, each through the CLI (in-process, `bati.cli.main`).

Every case asserts its exit code, that stderr holds exactly one line (an `error:` naming what is wrong, or
a `warning:` for what was repaired), and that no file under the test's directory was written, lost or
changed beyond what the case allows (byte for byte, directories included). The world every case starts
from: a tiny PointGoal collection (2 episodes per training task, 1 per context dataset) and a finished
`bati train --steps 5` run on it, both copied into the case's own directory. docs/reliability.md holds
the same catalogue as a table.

Below the catalogue: locks across processes, and kill -9 at random points of a training run and of a
collection (slow) followed by a resume, which must give what an uninterrupted run gives.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import flax
import numpy as np
import pytest

from bati.cli import main
from bati.data import collect as collect_mod
from bati.data import store
from bati.data.batch import load_family_data
from bati.io import LOCK_NAME, hold_lock

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("bad_inputs")

FAMILY = "PointGoal"
TINY = {"n_episodes": 2, "n_context_episodes": 1}
COLLECTION = "PointGoal/quick-seed0-eps1-per-task-experts"  # the default collectors: per-task experts


@pytest.fixture(autouse=True)
def tiny_scale(monkeypatch):
    """`--scale quick` means the tiny sizes here (the CLI has no size options)."""
    monkeypatch.setitem(collect_mod.SCALES, "quick", dict(TINY))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The tiny collection (with its array cache) and a finished 5-step run on it, made once."""
    root = tmp_path_factory.mktemp("world")
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(collect_mod.SCALES, "quick", dict(TINY))
        assert main(["data", "collect", "--family", FAMILY, "--root", str(root / "data"), "--workers", "1"]) == 0
        load_family_data(FAMILY, root=root / "data")  # writes arrays.npz
        assert main(["train", "--steps", "5", "--data-root", str(root / "data"), "--out-dir", str(root / "run")]) == 0
    return root


@dataclass
class Env:
    """One case's directory: copies of the world's collection and run, and where new things may go."""

    tmp: Path

    @property
    def data(self) -> Path:
        return self.tmp / "data"

    @property
    def run(self) -> Path:
        return self.tmp / "run"

    @property
    def collection(self) -> Path:
        return self.data / COLLECTION

    @property
    def fresh(self) -> Path:
        """An empty data root (its family directory exists) for cases that collect."""
        return self.tmp / "fresh"

    def train(self, *extra) -> list:
        """`bati train` resuming the finished run (the same config: it only re-summarises)."""
        return ["train", "--steps", "5", "--data-root", self.data, "--out-dir", self.run, *extra]

    def file(self, name: str) -> Path:
        """A dataset file of the collection, e.g. "train-03-v0/data/main_data.hdf5"."""
        return self.collection / name


@pytest.fixture
def env(world, tmp_path) -> Env:
    shutil.copytree(world / "data", tmp_path / "data")
    shutil.copytree(world / "run", tmp_path / "run")
    (tmp_path / "fresh" / FAMILY).mkdir(parents=True)
    (tmp_path / "a_file").write_text("a file, not a directory\n")
    return Env(tmp_path)


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and directory (None) under `root`."""
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() else None) for p in root.rglob("*")}


def call(capsys, argv: list) -> tuple[int, str, list[str]]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, [line for line in err.splitlines() if line.strip()]


# --- faults the cases inject ---------------------------------------------------------------------
def remove_from_run(relative: str) -> Callable:
    """The run's file gone (a finished run whose eval.json was never written: killed after its last checkpoint)."""
    def setup(env: Env, patch, stack) -> None:
        (env.run / relative).unlink()

    return setup


def both(*setups: Callable) -> Callable:
    def setup(env: Env, patch, stack) -> None:
        for one in setups:
            one(env, patch, stack)

    return setup


def enospc_on_fsync_of(name: str):
    """A setup that makes the atomic write of the file `name` fail with ENOSPC (disk full) at its fsync."""

    def setup(env: Env, patch: pytest.MonkeyPatch, stack: contextlib.ExitStack) -> None:
        if not Path("/proc/self/fd").is_dir():
            pytest.skip("needs /proc to tell which file is written")
        real = os.fsync

        def fsync(fd: int) -> None:
            if f"/.{name}." in os.readlink(f"/proc/self/fd/{fd}"):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real(fd)

        patch.setattr(os, "fsync", fsync)

    return setup


def enospc_in_collection(env: Env, patch: pytest.MonkeyPatch, stack) -> None:
    """Minari's writes fail with ENOSPC after three datasets (a write() error names no file)."""
    real, calls = store.write_dataset, []

    def write(*args, **kwargs):
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        calls.append(args[1])
        return real(*args, **kwargs)

    patch.setattr(store, "write_dataset", write)


def unwritable(env: Env, patch: pytest.MonkeyPatch, stack) -> None:
    """Every directory reads as not writable (what a chmod 555 or a read-only mount does; works as root)."""
    real = os.access
    patch.setattr(os, "access", lambda path, mode, **kw: False if mode & os.W_OK else real(path, mode, **kw))


def write(relative: str, content: bytes | str, *, where: str = "run") -> Callable:
    def setup(env: Env, patch, stack) -> None:
        path = getattr(env, where) / relative
        path.write_bytes(content.encode() if isinstance(content, str) else content)

    return setup


def edit_manifest(key: str) -> Callable:
    """The collection's manifest with one field changed by hand (the sizes, or the first training task)."""
    def setup(env: Env, patch, stack) -> None:
        path = env.collection / "manifest.json"
        manifest = json.loads(path.read_text())
        if key == "train_tasks":
            manifest[key][0] = [0.0, 1.0]
        else:
            manifest[key] += 1
        path.write_text(json.dumps(manifest, indent=2))

    return setup


def drop_from_config(key: str) -> Callable:
    """The run's config.json without one of its settings (a hand edit)."""
    def setup(env: Env, patch, stack) -> None:
        path = env.run / "config.json"
        record = json.loads(path.read_text())
        del record[key]
        path.write_text(json.dumps(record))

    return setup


def edit_config(**changes) -> Callable:
    """The run's config.json with some settings replaced (a hand edit)."""
    def setup(env: Env, patch, stack) -> None:
        path = env.run / "config.json"
        record = json.loads(path.read_text())
        for key, value in changes.items():
            section, _, name = key.partition("__")
            if name:
                record[section][name] = value
            else:
                record[key] = value
        path.write_text(json.dumps(record))

    return setup


def tear_last_line(name: str) -> Callable:
    """A kill in the middle of an append: half of one more record, no newline."""

    def setup(env: Env, patch, stack) -> None:
        with open(env.run / name, "a") as f:
            f.write('{"step": 10, "p_test_ret')

    return setup


def damage_middle_line(env: Env, patch, stack) -> None:
    path = env.run / "metrics.jsonl"
    path.write_text("{not json\n" + path.read_text())


def checkpoint_of_other_networks(env: Env, patch, stack) -> None:
    path = env.run / "checkpoint.msgpack"
    state = flax.serialization.msgpack_restore(path.read_bytes())
    leaves = state["iql"]["actor"]["params"]["params"]  # the actor TrainState's network layers
    layer = next(iter(leaves.values()))
    layer["kernel"] = np.zeros((3, 7), np.float32)
    path.write_bytes(flax.serialization.msgpack_serialize(state))


def truncate(name: str, keep: float = 0.5) -> Callable:
    def setup(env: Env, patch, stack) -> None:
        path = env.file(name) if not name.startswith("run/") else env.tmp / name
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])

    return setup


def flip_a_byte(name: str) -> Callable:
    """An edit that keeps the size (only the sha256 tells)."""

    def setup(env: Env, patch, stack) -> None:
        path = env.file(name)
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
        (env.collection / store.ARRAY_CACHE).unlink()  # the loader must read (and check) the datasets

    return setup


def remove(name: str) -> Callable:
    def setup(env: Env, patch, stack) -> None:
        path = env.collection / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()

    return setup


def old_manifest(env: Env, patch, stack) -> None:
    """A collection made before checksums (format 1): no `files`, no `settings`, no digest of its own."""
    path = env.collection / store.MANIFEST
    manifest = json.loads(path.read_text())
    for key in ("files", "settings", store.MANIFEST_DIGEST):
        del manifest[key]
    manifest["format"] = 1
    path.write_text(json.dumps(manifest))


def damage_cache(env: Env, patch, stack) -> None:
    path = env.collection / store.ARRAY_CACHE
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # zip CRCs catch it
    path.write_bytes(bytes(data))


def lock_held(where: Callable[[Env], Path]) -> Callable:
    """Hold the lock (through another open file: as another process would) for the whole case."""

    def setup(env: Env, patch, stack: contextlib.ExitStack) -> None:
        stack.enter_context(hold_lock(where(env), "a test"))

    return setup


def stale_lock(env: Env, patch, stack) -> None:
    """A lock file left by a process that died (kill -9): no flock on it, a dead pid inside."""
    (env.run / LOCK_NAME).write_text(json.dumps({"pid": 999_999_999, "host": "here", "since": "then"}))


def empty_zoo(env: Env, patch, stack) -> None:
    (env.tmp / "zoo").mkdir()


def damaged_zoo(name: str, content: bytes) -> Callable:
    """A copy of the shipped PointGoal expert in tmp/zoo with one of its files replaced (torn, truncated)."""
    def setup(env: Env, patch, stack) -> None:
        import shutil

        from bati.experts.zoo import ZOO_DIR

        shutil.copytree(ZOO_DIR / "PointGoal", env.tmp / "zoo" / "PointGoal")
        (env.tmp / "zoo" / "PointGoal" / name).write_bytes(content)

    return setup


def context_file(name: str, length: int = 4, **arrays) -> Callable:
    """A `bati infer` context file of PointGoal's sizes (length transitions), some arrays replaced."""

    def setup(env: Env, patch, stack) -> None:
        fields = {"observations": np.zeros((length, 2)), "actions": np.zeros((length, 2)),
                  "rewards": np.zeros(length), "next_observations": np.zeros((length, 2)), **arrays}
        np.savez(env.tmp / name, **fields)

    return setup


# --- the catalogue -------------------------------------------------------------------------------
@dataclass
class Case:
    id: str
    argv: Callable[[Env], list]
    code: int
    needles: tuple[str, ...]
    setup: Callable | None = None
    warning: bool = False  # one `warning:` line (something repaired) instead of an `error:` line
    changes: tuple[str, ...] = ()  # paths (relative to the case's directory) allowed to change
    unwanted: tuple[str, ...] = ()  # words the message must not contain
    check: Callable[[Env], None] | None = None


RESUMED = ("run/eval.json",)  # a resumed finished run re-summarises (wall time, device)
TRAIN = ["train", "--steps", "5"]


def _metrics_without_torn(env: Env) -> None:
    steps = [json.loads(line)["step"] for line in (env.run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [5]


def _recon_config(env: Env) -> None:
    """A run directory recording a Recon run (its config only: the refusal must not need more)."""
    (env.tmp / "recon").mkdir()
    record = json.loads((env.run / "config.json").read_text())
    (env.tmp / "recon" / "config.json").write_text(json.dumps({**record, "method": "recon"}))


def _no_lock_left(env: Env) -> None:
    assert not (env.run / LOCK_NAME).exists()


CASES = [
    # --- settings refused before any work
    Case("unknown family", lambda e: [*TRAIN, "--family", "Nope", "--data-root", e.data], 2, ("'Nope'", "PointGoal")),
    Case("unknown method", lambda e: [*TRAIN, "--method", "nope", "--data-root", e.data], 2, ("'nope'", "focal")),
    Case("unknown scale", lambda e: [*TRAIN, "--scale", "huge"], 2, ("--scale", "huge")),
    Case("steps 0", lambda e: ["train", "--steps", "0", "--data-root", e.data], 2, ("steps must be an integer >= 1", "0")),
    Case("steps -5", lambda e: ["train", "--steps", "-5", "--data-root", e.data], 2, ("steps", "-5")),
    Case("steps not an integer", lambda e: ["train", "--steps", "abc"], 2, ("--steps", "abc")),
    Case("steps without a value", lambda e: ["train", "--steps"], 2, ("--steps", "bati train --help")),
    Case("noise inf", lambda e: [*TRAIN, "--noise", "inf", "--data-root", e.data], 2, ("eps=inf",)),
    Case("noise nan", lambda e: [*TRAIN, "--noise", "nan", "--data-root", e.data], 2, ("nan",)),
    Case("noise -1", lambda e: [*TRAIN, "--noise", "-1", "--data-root", e.data], 2, ("eps=-1",)),
    Case("train --seeds with nothing", lambda e: [*TRAIN, "--seeds", "--data-root", e.data], 2, ("--seeds needs",)),
    Case("run --seeds with nothing", lambda e: ["run", "--seeds", "--data-root", e.data], 2, ("seeds must be",)),
    Case("negative seed", lambda e: [*TRAIN, "--seed", "-1", "--data-root", e.data], 2, ("integer", ">= 0", "-1")),
    Case("repeated seeds", lambda e: [*TRAIN, "--seeds", "1", "1", "--data-root", e.data], 2, ("distinct",)),
    Case("negative data seed", lambda e: [*TRAIN, "--data-seed", "-2", "--data-root", e.data], 2, ("data_seed", "-2")),
    Case("config with another setting", lambda e: ["train", "--config", e.run, "--steps", "9"], 2,
         ("--config reruns", "leave out --steps")),
    Case("method setting out of range", lambda e: [*TRAIN, "--bati.latent-samples", "0", "--data-root", e.data], 2,
         ("bati.latent_samples", ">= 1")),
    *[Case(f"range: {' '.join(args)}", lambda e, args=args: [*TRAIN, *args, "--data-root", e.data, "--out-dir",
                                                             e.tmp / "new-run"], 2, needles)
      for args, needles in [
          (("--iql.expectile", "1.5"), ("iql.expectile", "below 1")),
          (("--iql.expectile", "0"), ("iql.expectile", "> 0")),
          (("--iql.expectile", "nan"), ("iql.expectile", "nan")),
          (("--iql.discount", "-0.5"), ("iql.discount", "at most 1")),
          (("--iql.tau", "2"), ("iql.tau", "at most 1")),
          (("--iql.max-exp-advantage", "-1"), ("iql.max_exp_advantage", "> 0")),
          (("--method", "csro", "--csro.club-weight", "-1"), ("csro.club_weight", ">= 0")),
          (("--method", "csro", "--csro.club-weight", "nan"), ("csro.club_weight", "finite")),
          (("--method", "focal", "--focal.push-weight", "-1"), ("focal.push_weight", ">= 0")),
          (("--method", "focal", "--focal.push-epsilon", "0"), ("focal.push_epsilon", "> 0")),
          (("--method", "unicorn", "--unicorn.focal-weight", "-1"), ("unicorn.focal_weight", ">= 0")),
          (("--method", "er-trl", "--ertrl.covariance-epsilon", "-1"), ("ertrl.covariance_epsilon", "> 0")),
          (("--method", "er-trl", "--ertrl.entropy-weight", "nan"), ("ertrl.entropy_weight", "finite")),
          (("--bati.embedding-log-var", "nan"), ("bati.embedding_log_var", "finite")),
          (("--bati.refine-steps", "2", "--bati.refine-learning-rate", "nan"), ("bati.refine_learning_rate",)),
          (("--method", "dpt", "--dpt.num-layers", "0"), ("dpt.num_layers", ">= 1")),
          (("--method", "dpt", "--dpt.num-heads", "3"), ("dpt.model_dim (64) must be a multiple of dpt.num_heads",)),
          (("--method", "dpt", "--dpt.model-dim", "0"), ("dpt.model_dim", ">= 1")),
          (("--method", "dpt", "--dpt.max-length", "10"), ("dpt.max_length (10) must be >= the context length",)),
          (("--eval-context-length", "5000"), ("eval_context_length (5000)", "context data")),
          (("--task-key", "goal"), ("--task-key applies to your own data",)),
          (("--held-out", "1.5"), ("--held-out applies to your own data",)),
      ]],
    Case("sweep: a setting twice", lambda e: ["sweep", "--families", FAMILY, "--settings", "steps=100", "steps=200",
                                              "--out-dir", e.tmp / "sweep", "--data-root", e.data], 2,
         ("setting steps is given twice",)),
    Case("output inside the package", lambda e: [*TRAIN, "--data-root", e.data, "--out-dir",
                                                 Path(collect_mod.__file__).parents[1] / "run-here"], 2,
         ("lies inside the bati package",)),
    Case("sweep inside the package", lambda e: ["sweep", "--families", FAMILY, "--data-root", e.data, "--out-dir",
                                                Path(collect_mod.__file__).parents[1] / "sweep-here"], 2,
         ("lies inside the bati package",)),
    Case("likelihood of a run without a table", lambda e: ["likelihood", "--run-dir", e.tmp / "recon"], 2,
         ("method 'recon' has no task table",), setup=lambda e, m, s: _recon_config(e)),
    Case("unknown logging sink", lambda e: [*TRAIN, "--log-to", "csv", "--data-root", e.data], 2,
         ("unknown logging sink 'csv'",)),
    Case("--datasets without a value", lambda e: ["train", "--datasets", "--data-root", e.data], 2,
         ("--datasets needs at least one value",)),
    Case("iql.hidden_dims 0", lambda e: [*TRAIN, "--iql.hidden-dims", "0", "--data-root", e.data], 2,
         ("iql.hidden_dims must be one or more integers >= 1", "(0,)")),
    Case("iql.hidden_dims -5", lambda e: [*TRAIN, "--iql.hidden-dims", "-5", "--data-root", e.data], 2,
         ("iql.hidden_dims must be one or more integers >= 1", "(-5,)")),
    Case("iql.hidden_dims empty", lambda e: [*TRAIN, "--iql.hidden-dims", "--data-root", e.data], 2,
         ("iql.hidden_dims must be one or more integers >= 1", "()")),
    Case("csro.club_hidden_dims 0", lambda e: [*TRAIN, "--method", "csro", "--csro.club-hidden-dims", "0",
                                               "--data-root", e.data], 2, ("csro.club_hidden_dims must be",)),
    Case("steps beyond any plan", lambda e: ["train", "--steps", "99999999999999999999", "--data-root", e.data], 2,
         ("steps must be at most 1,000,000,000",)),
    # every count and rate of a run, each refused by name before any work (0 never means "the default")
    *(Case(f"train --{opt} {bad}", (lambda o, b: lambda e: [*TRAIN, f"--{o}", b, "--data-root", e.data])(opt, bad), 2,
           (f"{opt.replace('-', '_')} must be",))
      for opt, bad in (("context-length", "0"), ("eval-context-length", "0"), ("task-batch", "0"),
                       ("batch-size", "0"), ("eval-every", "0"), ("checkpoint-every", "0"), ("log-every", "0"), ("eval-workers", "0"),
                       ("episodes-per-task", "0"), ("context-episodes", "0"), ("learning-rate", "0"),
                       ("learning-rate", "nan"), ("iql.learning-rate", "-1"), ("iql.temperature", "inf"))),
    Case("train --method er-trl --ertrl.noise-dim 0", lambda e: [*TRAIN, "--method", "er-trl", "--ertrl.noise-dim",
                                                                  "0", "--data-root", e.data], 2,
         ("ertrl.noise_dim must be an integer >= 1",)),
    Case("train --method er-trl --ertrl.gan-hidden-dims 0", lambda e: [*TRAIN, "--method", "er-trl",
                                                                        "--ertrl.gan-hidden-dims", "0",
                                                                        "--data-root", e.data], 2,
         ("ertrl.gan_hidden_dims must be one or more integers >= 1",)),
    Case("train --zoo-dir without the expert", lambda e: [*TRAIN, "--zoo-dir", e.tmp, "--data-root", e.data,
                                                           "--out-dir", e.tmp / "new"], 2,
         ("no per-task experts for PointGoal in", "bati experts train --family PointGoal --per-task")),
    Case("run --zoo-dir without the expert", lambda e: ["run", "--zoo-dir", e.tmp, "--data-root", e.data,
                                                         "--out-dir", e.tmp / "new"], 2,
         ("no per-task experts for PointGoal in",)),
    Case("own dataset missing", lambda e: ["train", "--datasets", e.tmp / "nope", "--out-dir", e.tmp / "new"], 2,
         ("no Minari dataset",)),
    Case("run --methods all bogus", lambda e: ["run", "--methods", "all", "bogus", "--data-root", e.data], 2,
         ("'bogus'", "or all")),
    Case("envs --task without --family", lambda e: ["envs", "--task", "1"], 2, ("--task needs --family",)),
    Case("misspelt option", lambda e: ["train", "--famly", "X"], 2, ("--famly", "perhaps you meant --family")),
    Case("no command", lambda e: [], 2, ("Expected one of", "train")),
    Case("collect --workers 0", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh, "--workers", "0"],
         2, ("workers=0",)),
    Case("sweep: unknown setting", lambda e: ["sweep", "--settings", "stepz=3", "--out-dir", e.tmp / "sweep"], 2,
         ("unknown setting 'stepz'",)),
    Case("sweep: iql.hidden_dims=[-5]", lambda e: ["sweep", "--settings", "iql.hidden_dims=[-5]", "--out-dir",
                                                    e.tmp / "sweep", "--data-root", e.data], 2,
         ("iql.hidden_dims must be one or more integers >= 1", "(-5,)")),
    Case("collect --seed -1", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh, "--seed", "-1"], 2,
         ("seed must be an integer >= 0, got -1",)),
    Case("run --steps 0 (before the data)", lambda e: ["run", "--steps", "0", "--data-root", e.fresh, "--out-dir",
                                                        e.tmp / "new"], 2, ("steps must be an integer >= 1, got 0",)),
    Case("run --out-dir is a file", lambda e: ["run", "--data-root", e.fresh, "--out-dir", e.tmp / "a_file"], 2,
         ("the experiment directory", "a_file is a file")),
    Case("experts train --total-steps 0", lambda e: ["experts", "train", "--family", FAMILY, "--total-steps", "0",
                                                      "--out-dir", e.tmp / "expert"], 2,
         ("total_steps must be an integer >= 1, got 0", "the family's 20,000")),
    Case("experts train: per-task updates never due", lambda e: [
        "experts", "train", "--family", FAMILY, "--per-task", "--tasks", "0", "--total-steps", "200", "--start-steps",
        "100", "--update-every", "1000", "--out-dir", e.tmp / "expert"], 2,
         ("no SAC update would run", "the first at 1,000", "untrained")),
    Case("experts train: updates per step rounding to none", lambda e: [
        "experts", "train", "--family", FAMILY, "--updates-per-step", "0.1", "--out-dir", e.tmp / "expert"], 2,
         ("rounds to 0 SAC updates", "untrained")),
    Case("experts train --sac.hidden-dims 0", lambda e: ["experts", "train", "--family", FAMILY, "--sac.hidden-dims",
                                                          "0", "--out-dir", e.tmp / "expert"], 2,
         ("sac.hidden_dims must be one or more integers >= 1", "(0,)")),
    Case("experts train --export-dir is a file", lambda e: ["experts", "train", "--family", FAMILY, "--export-dir",
                                                             e.tmp / "a_file", "--out-dir", e.tmp / "expert"], 2,
         ("the zoo directory", "a_file is a file")),
    Case("experts merge: a part without experts", lambda e: ["experts", "merge", "--family", FAMILY, "--parts",
                                                              e.tmp / "nope", "--export-dir", e.tmp / "zoo"], 2,
         ("no per-task experts for PointGoal in", "--per-task")),
    Case("experts merge: a part that is a file", lambda e: ["experts", "merge", "--family", FAMILY, "--parts",
                                                            e.tmp / "a_file", "--export-dir", e.tmp / "zoo"], 2,
         ("a_file is a file: --parts takes zoo folders, each holding PointGoal/per-task/",), unwanted=("--zoo-dir",)),
    Case("experts merge --export-dir is a file", lambda e: ["experts", "merge", "--family", FAMILY, "--parts",
                                                             e.tmp / "nope", "--export-dir", e.tmp / "a_file"], 2,
         ("the zoo directory", "a_file is a file")),
    # --- paths and the OS
    Case("out-dir is a file", lambda e: [*TRAIN, "--data-root", e.data, "--out-dir", e.tmp / "a_file"], 2,
         ("the run directory", "a_file is a file")),
    Case("out-dir under a file", lambda e: [*TRAIN, "--data-root", e.data, "--out-dir", e.tmp / "a_file" / "run"], 2,
         ("cannot create the run directory", "a_file is a file")),
    Case("out-dir not writable", lambda e: [*TRAIN, "--data-root", e.data, "--out-dir", e.tmp / "new"], 2,
         ("the run directory", "not writable"), setup=unwritable),
    Case("data root is a file (train)", lambda e: [*TRAIN, "--data-root", e.tmp / "a_file", "--out-dir", e.tmp / "new"],
         2, ("the data root", "a_file is a file")),
    Case("data root is a file (collect)", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.tmp / "a_file"],
         2, ("a_file is a file",)),
    Case("data root not writable (collect)", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh], 2,
         ("the data directory", "not writable"), setup=unwritable),
    Case("disk full writing config.json", lambda e: [*TRAIN, "--data-root", e.data, "--out-dir", e.tmp / "new"], 2,
         ("new/config.json", "no space left on device"), setup=enospc_on_fsync_of("config.json")),
    Case("disk full writing eval.json", lambda e: e.train(), 2, ("run/eval.json", "no space left on device"),
         setup=both(remove_from_run("eval.json"), enospc_on_fsync_of("eval.json"))),
    Case("disk full while collecting", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh], 2,
         (f"fresh/{COLLECTION}", "no space left on device"), setup=enospc_in_collection),
    Case("likelihood --run-dir is a file", lambda e: ["likelihood", "--run-dir", e.tmp / "a_file"], 2,
         ("a_file is a file, not a run directory",)),
    Case("likelihood --run-dir without a run", lambda e: ["likelihood", "--run-dir", e.fresh], 2,
         ("is not a run directory", "no config.json")),
    Case("likelihood on config.json []", lambda e: ["likelihood", "--run-dir", e.run], 2,
         ("config.json holds a JSON list",), setup=write("config.json", "[]")),
    Case("infer: an empty context file", lambda e: ["infer", "--run-dir", e.run, "--context", e.tmp / "c.npz"], 2,
         ("c.npz: not an .npz file",), setup=write("c.npz", b"", where="tmp")),
    Case("infer: a text file", lambda e: ["infer", "--run-dir", e.run, "--context", e.tmp / "c.txt"], 2,
         ("c.txt: not an .npz file (an .npz is a zip of .npy arrays",), setup=write("c.txt", "1 2 3\n", where="tmp"),
         unwanted=("pickled",)),
    Case("likelihood --context-length 0", lambda e: ["likelihood", "--run-dir", e.run, "--context-length", "0"], 2,
         ("context_length must be an integer >= 1, got 0",)),
    Case("likelihood on a read-only run", lambda e: ["likelihood", "--run-dir", e.run], 2,
         ("the run directory", "not writable"), setup=unwritable),
    Case("infer: rewards of shape (C, 1)", lambda e: ["infer", "--run-dir", e.run, "--context", e.tmp / "c.npz"], 2,
         ("c.npz: rewards has shape (4, 1); expected (C,)",), setup=context_file("c.npz", rewards=np.zeros((4, 1)))),
    Case("infer: complex actions", lambda e: ["infer", "--run-dir", e.run, "--context", e.tmp / "c.npz"], 2,
         ("c.npz: actions holds complex128 values",), setup=context_file("c.npz", actions=np.zeros((4, 2), complex))),
    Case("a torn expert.json", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh, "--zoo-dir",
                                          e.tmp / "zoo", "--experts", "conditioned"], 2,
         ("zoo/PointGoal/expert.json is damaged", "export the expert again"),
         setup=damaged_zoo("expert.json", b'{"family": "Poi')),
    Case("a truncated actor file", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh, "--zoo-dir",
                                              e.tmp / "zoo", "--experts", "conditioned"], 2,
         ("zoo/PointGoal/actor.msgpack is damaged",), setup=damaged_zoo("actor.msgpack", b"\x82\xa5")),
    Case("a torn per-task expert.json", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh,
                                                   "--zoo-dir", e.tmp / "zoo"], 2,
         ("zoo/PointGoal/per-task/expert.json is damaged",), setup=damaged_zoo("per-task/expert.json", b'{"fam')),
    Case("a truncated per-task actors file", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh,
                                                        "--zoo-dir", e.tmp / "zoo"], 2,
         ("zoo/PointGoal/per-task/actors.msgpack is damaged",), setup=damaged_zoo("per-task/actors.msgpack", b"\x82")),
    Case("a data size no machine holds (train)", lambda e: [*TRAIN, "--episodes-per-task", "1000000000", "--data-root",
                                                            e.fresh, "--out-dir", e.tmp / "new"], 2,
         ("1,000,000,000 episodes per training task", "TB of PointGoal data; this machine has", "of memory")),
    Case("no expert to collect with", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh, "--zoo-dir",
                                                 e.tmp / "zoo"], 2, ("no per-task experts for PointGoal",), setup=empty_zoo),
    Case("sweep out-dir is a file", lambda e: ["sweep", "--out-dir", e.tmp / "a_file"], 2, ("a_file is a file",)),
    # --- a run directory's files
    Case("config.json is []", lambda e: e.train(), 2, ("config.json holds a list",), setup=write("config.json", "[]")),
    Case("--config: iql is a list", lambda e: ["train", "--config", e.run], 2,
         ("config setting 'iql' must be an object of settings", "list [1, 2]"), setup=edit_config(iql=[1, 2])),
    Case("--config: hidden_dims is text", lambda e: ["train", "--config", e.run], 2,
         ("iql.hidden_dims must be one or more integers >= 1", "'abc'"), setup=edit_config(iql__hidden_dims="abc")),
    Case("--config: an unknown setting", lambda e: ["train", "--config", e.run], 2,
         ("setting(s) this version does not know: 'stpes'",), setup=edit_config(stpes=5)),
    Case("--config: a recorded setting removed", lambda e: ["train", "--config", e.run], 2,
         ("config.json lacks steps: a run's config.json records every setting it ran with",),
         setup=drop_from_config("steps")),
    Case("--config: an unknown setting in a section", lambda e: ["train", "--config", e.run], 2,
         ("setting(s) this version does not know: 'iql.hiddn'",), setup=edit_config(iql__hiddn=3)),
    Case("config.json torn", lambda e: e.train(), 2, ("config.json is not valid JSON",),
         setup=write("config.json", '{"family": "Poi')),
    Case("rerun with other settings", lambda e: ["train", "--steps", "10", "--data-root", e.data, "--out-dir", e.run], 2,
         ("steps: 5 there, 10 now",)),
    Case("checkpoint is garbage", lambda e: e.train(), 2, ("checkpoint.msgpack is damaged",),
         setup=write("checkpoint.msgpack", b"\x00garbage"), unwanted=("family", "method")),
    Case("checkpoint truncated", lambda e: e.train(), 2, ("checkpoint.msgpack is damaged", "incomplete"),
         setup=truncate("run/checkpoint.msgpack"), unwanted=("family", "method")),
    Case("checkpoint of other networks", lambda e: e.train(), 2, ("does not match this run's networks",),
         setup=checkpoint_of_other_networks),
    Case("torn last line of metrics.jsonl", lambda e: e.train(), 0, ("metrics.jsonl: dropped its torn last line 2",),
         setup=tear_last_line("metrics.jsonl"), warning=True, changes=(*RESUMED, "run/metrics.jsonl"),
         check=_metrics_without_torn),
    Case("torn last line of eval.jsonl", lambda e: e.train(), 0, ("eval.jsonl: dropped its torn last line 2",),
         setup=tear_last_line("eval.jsonl"), warning=True, changes=(*RESUMED, "run/eval.jsonl")),
    Case("bad line in the middle of metrics.jsonl", lambda e: e.train(), 2, ("metrics.jsonl, line 1",),
         setup=damage_middle_line),
    Case("run directory locked", lambda e: e.train(), 2, ("the run directory", "is in use by pid", str(os.getpid())),
         setup=lock_held(lambda e: e.run / LOCK_NAME)),
    Case("stale lock of a dead process", lambda e: e.train(), 0, (), setup=stale_lock, changes=RESUMED + ("run/.lock",),
         check=_no_lock_left),
    # --- a collection's files
    Case("collection locked", lambda e: ["data", "collect", "--family", FAMILY, "--root", e.fresh], 2,
         ("the collection", "is in use by pid"), setup=lock_held(lambda e: store.lock_path(e.fresh / COLLECTION))),
    Case("dataset edited: verify", lambda e: ["data", "verify", "--root", e.data], 1,
         ("1 of 1 collection(s) damaged",), setup=flip_a_byte("train-03-v0/data/main_data.hdf5"),
         changes=(f"data/{COLLECTION}/arrays.npz",)),
    Case("dataset edited: train", lambda e: e.train(), 2,
         ("train-03-v0/data/main_data.hdf5 was edited", "bati data verify"),
         setup=flip_a_byte("train-03-v0/data/main_data.hdf5"), changes=(f"data/{COLLECTION}/arrays.npz",)),
    Case("dataset truncated: verify", lambda e: ["data", "verify", "--family", FAMILY, "--root", e.data], 1,
         ("damaged",), setup=truncate("p_test-04-v0/data/main_data.hdf5")),
    Case("dataset truncated: info", lambda e: ["data", "info", "--family", FAMILY, "--root", e.data], 2,
         ("p_test-04-v0/data/main_data.hdf5 is truncated",), setup=truncate("p_test-04-v0/data/main_data.hdf5")),
    Case("dataset truncated: train (cached arrays)", lambda e: e.train(), 2,
         ("p_test-04-v0/data/main_data.hdf5 is truncated",), setup=truncate("p_test-04-v0/data/main_data.hdf5")),
    Case("dataset file missing: verify", lambda e: ["data", "verify", "--root", e.data, "--seed", "0"], 1,
         ("damaged",), setup=remove("p_train-19-v0/data/metadata.json")),
    Case("dataset directory missing: info", lambda e: ["data", "info", "--family", FAMILY, "--root", e.data], 2,
         ("train-07-v0 is missing",), setup=remove("train-07-v0")),
    *[Case(f"manifest edited by hand ({key}): {command}",
           lambda e, command=command: ["data", command, "--root", e.data] + (["--family", FAMILY] if command == "info"
                                                                          else []),
           1 if command == "verify" else 2,
           ("damaged",) if command == "verify" else ("manifest.json was edited after the collection",),
           setup=edit_manifest(key))
      for key in ("n_episodes", "train_tasks") for command in ("verify", "info")],
    Case("data info: a negative seed", lambda e: ["data", "info", "--family", FAMILY, "--root", e.data, "--seed", "-1"],
         2, ("seed must be an integer >= 0, got -1",)),
    Case("infer: an object array", lambda e: ["infer", "--run-dir", e.run, "--context", e.tmp / "c.npz"], 2,
         ("c.npz: actions cannot be read as an array of numbers",),
         setup=context_file("c.npz", actions=np.array([[object()] * 2] * 4, dtype=object))),
    Case("manifest is []", lambda e: ["data", "info", "--family", FAMILY, "--root", e.data], 2,
         ("manifest.json holds a JSON list, not a manifest",), setup=write(f"{COLLECTION}/manifest.json", "[]",
                                                                           where="data")),
    Case("manifest torn", lambda e: ["data", "info", "--family", FAMILY, "--root", e.data], 2,
         ("manifest.json is corrupted",), setup=write(f"{COLLECTION}/manifest.json", '{"format": 2, "fam',
                                                      where="data")),
    Case("array cache damaged", lambda e: e.train(), 0, ("arrays.npz is damaged", "rebuilding"), setup=damage_cache,
         warning=True, changes=(*RESUMED, f"data/{COLLECTION}/arrays.npz")),
    Case("verify: nothing matches", lambda e: ["data", "verify", "--root", e.data, "--seed", "7"], 2,
         ("no collection under", "seed=7")),
    Case("verify: unknown family", lambda e: ["data", "verify", "--family", "Nope", "--root", e.data], 2, ("'Nope'",)),
    Case("verify: data root is a file", lambda e: ["data", "verify", "--root", e.tmp / "a_file"], 2,
         ("a_file is a file",)),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_or_fault(case: Case, env: Env, capsys, monkeypatch):
    with contextlib.ExitStack() as stack:
        if case.setup is not None:
            case.setup(env, monkeypatch, stack)
        before = snapshot(env.tmp)
        code, out, lines = call(capsys, case.argv(env))
        monkeypatch.undo()  # the faults end with the command
        after = snapshot(env.tmp)
    assert "Traceback" not in out + "\n".join(lines)
    assert code == case.code, (code, lines)
    if case.warning or case.needles:
        prefix = "warning:" if case.warning else "error:"
        assert len(lines) == 1 and lines[0].startswith(prefix), lines
        for needle in case.needles:
            assert needle in lines[0], (needle, lines[0])
        for word in case.unwanted:
            assert word not in lines[0], (word, lines[0])
    else:
        assert lines == [], lines
    changed = {k for k in before.keys() | after.keys() if before.get(k, b"") != after.get(k, b"") or
               (k in before) != (k in after)}
    assert changed <= set(case.changes), sorted(changed - set(case.changes))
    if case.check is not None:
        case.check(env)


def test_the_catalogue_is_large_enough():
    assert len(CASES) >= 40 and len({c.id for c in CASES}) == len(CASES)


def test_verify_reports_every_damaged_file_by_name(env, capsys):
    flip_a_byte("train-03-v0/data/main_data.hdf5")(env, None, None)
    truncate("p_test-04-v0/data/main_data.hdf5")(env, None, None)
    remove("p_train-19-v0/data/metadata.json")(env, None, None)
    code, out, lines = call(capsys, ["data", "verify", "--root", env.data])
    assert code == 1 and len(lines) == 1
    report = " ".join(out.split())
    assert "train-03-v0/data/main_data.hdf5 was edited" in report
    assert "p_test-04-v0/data/main_data.hdf5 is truncated" in report
    assert "p_train-19-v0/data/metadata.json is missing" in report


def test_collections_without_checksums_are_named_not_refused(env, capsys):
    old_manifest(env, None, None)
    code, out, lines = call(capsys, ["data", "verify", "--root", env.data])
    assert code == 0 and lines == [] and "no checksums (collected before format 2)" in out
    code, out, lines = call(capsys, ["data", "info", "--family", FAMILY, "--root", env.data])
    assert code == 0 and lines == [] and "no checksums (collected before format 2)" in " ".join(out.split())
    assert load_family_data(FAMILY, root=env.data).train.observations.shape == (20, 400, 2)


def test_manifest_records_sizes_checksums_and_settings(env):
    manifest = json.loads((env.collection / store.MANIFEST).read_text())
    assert manifest["format"] == store.FORMAT_VERSION >= store.CHECKSUM_FORMAT
    assert len(manifest["files"]) == 120  # 60 datasets x (main_data.hdf5, metadata.json)
    entry = manifest["files"]["train-00-v0/data/main_data.hdf5"]
    assert entry["bytes"] == env.file("train-00-v0/data/main_data.hdf5").stat().st_size
    assert entry["sha256"] == store.sha256_file(env.file("train-00-v0/data/main_data.hdf5"))
    settings = manifest["settings"]
    assert (settings["family"], settings["n_episodes"], settings["n_context_episodes"]) == (FAMILY, 2, 1)
    assert settings["chunk"] == collect_mod.CHUNK and len(settings["expert_sha256"]) == 64


@pytest.mark.slow
def test_resume_without_a_checkpoint_restarts_the_logs(env, capsys):
    """A kill before the first checkpoint: the resumed run starts over and writes each record once."""
    metrics = (env.run / "metrics.jsonl").read_text()
    (env.run / "checkpoint.msgpack").unlink()
    (env.run / "eval.json").unlink()
    code, _, lines = call(capsys, env.train())
    assert code == 0 and lines == []
    strip = lambda text: [{k: v for k, v in json.loads(line).items() if k != "wall_time"}  # noqa: E731
                          for line in text.splitlines()]
    assert strip((env.run / "metrics.jsonl").read_text()) == strip(metrics)
    assert [json.loads(line)["step"] for line in (env.run / "eval.jsonl").read_text().splitlines()] == [5]


# --- locks across processes ----------------------------------------------------------------------
HOLDER = textwrap.dedent("""
    import sys, time
    from bati.io import hold_lock
    with hold_lock(sys.argv[1], "a test"):
        print("held", flush=True)
        time.sleep(120)
""")


def test_a_lock_held_by_another_process_and_taken_over_after_its_kill(env, capsys):
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(env.run / LOCK_NAME)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = snapshot(env.tmp)
        code, _, lines = call(capsys, env.train())
        assert code == 2 and len(lines) == 1 and f"in use by pid {holder.pid} on " in lines[0], lines
        assert snapshot(env.tmp) == before
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert (env.run / LOCK_NAME).exists()  # left behind by the killed holder: no flock on it any more
    code, _, lines = call(capsys, env.train())
    assert code == 0 and lines == [] and not (env.run / LOCK_NAME).exists()


def test_a_lock_without_flock_takes_over_only_dead_pids_of_this_host(tmp_path, monkeypatch):
    import socket

    from bati import io as bati_io
    from bati.errors import LockedError

    monkeypatch.setattr(bati_io, "_flock", lambda fd: None)  # a file system without flock
    lock = tmp_path / LOCK_NAME
    lock.write_text(json.dumps({"pid": 999_999_999, "host": socket.gethostname()}))
    with hold_lock(lock, "the dir"):
        assert json.loads(lock.read_text())["pid"] == os.getpid()
        with pytest.raises(LockedError, match=f"in use by pid {os.getpid()}"):
            with hold_lock(lock, "the dir"):
                pass
    assert not lock.exists()
    lock.write_text(json.dumps({"pid": 999_999_999, "host": "elsewhere"}))
    with pytest.raises(LockedError, match="on elsewhere .*if it is gone, delete"):
        with hold_lock(lock, "the dir"):
            pass


# --- kill -9 at random points, then resume ----------------------------------------------------------
KILLS = 4  # random kill points per test, each in the process resumed after the previous kill
TRAIN_SCRIPT = textwrap.dedent("""
    import sys
    from pathlib import Path
    from bati.rl.iql import IQLConfig
    from bati.config import TrainConfig
    from bati.train import train
    config = TrainConfig(family="PointGoal", steps=60, log_every=5, eval_every=20, checkpoint_every=10,
                         iql=IQLConfig(hidden_dims=(32, 32)), task_batch=4, batch_size=8, context_length=20,
                         eval_context_length=20, episodes_per_task=2, context_episodes=1,
                         data_root=Path(sys.argv[1]), out_dir=Path(sys.argv[2]))
    train(config, show_progress=False)
""")


def _run_script(script: str, *args, kill_after: float | None = None) -> bool:
    """Run `script` in a new process group; with `kill_after`, SIGKILL the group then. True if it finished."""
    process = subprocess.Popen([sys.executable, "-c", script, *map(str, args)], start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        process.wait(timeout=kill_after if kill_after is not None else 600)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        return False
    assert process.returncode == 0, process.stderr.read()
    return True


def _records(path: Path) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k != "wall_time"} for line in path.read_text().splitlines()]


@pytest.mark.slow
def test_kill_9_at_random_points_of_training_then_resume_gives_the_same_run(world, tmp_path, monkeypatch):
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "xla"))  # a kill may leave a half-written entry
    rng = random.Random(13)
    assert _run_script(TRAIN_SCRIPT, world / "data", tmp_path / "straight")  # compiles (and fills the cache)
    start = time.perf_counter()
    assert _run_script(TRAIN_SCRIPT, world / "data", tmp_path / "again")  # the duration the killed runs share
    duration = time.perf_counter() - start
    kills = sorted(rng.uniform(0.3, 1.0) * duration for _ in range(KILLS))
    finished, killed_at = False, []
    for delay in kills:  # each kill lands in a resumed process: kills during a resume are tested too
        finished = _run_script(TRAIN_SCRIPT, world / "data", tmp_path / "killed", kill_after=delay)
        if not finished:
            killed_at.append(delay)
    assert killed_at, kills  # at least one kill came before the end
    if not finished:
        assert _run_script(TRAIN_SCRIPT, world / "data", tmp_path / "killed")
    straight = tmp_path / "straight"
    for other in (tmp_path / "again", tmp_path / "killed"):  # programs from the cache give the same run too
        assert (straight / "checkpoint.msgpack").read_bytes() == (other / "checkpoint.msgpack").read_bytes(), kills
        assert _records(straight / "metrics.jsonl") == _records(other / "metrics.jsonl"), kills
        assert _records(straight / "eval.jsonl") == _records(other / "eval.jsonl"), kills
        a, b = (json.loads((d / "eval.json").read_text()) for d in (straight, other))
        for key in ("p_test_return", "p_train_return", "curve", "steps"):
            assert a[key] == b[key], key
    killed = tmp_path / "killed"
    assert not (killed / LOCK_NAME).exists()


COLLECT_SCRIPT = textwrap.dedent("""
    import sys
    from bati.data import collect as collect_mod
    collect_mod.CHUNK = 8  # ten chunks: the datasets are written one by one while the kill may come
    collect_mod.collect("PointGoal", "quick", 0, root=sys.argv[1], n_episodes=2, n_context_episodes=1,
                        progress=False, workers=1)
""")


def _contents(path: Path) -> dict:
    """Every dataset's arrays, options and metadata (minus the collection's random id)."""
    manifest = json.loads((path / store.MANIFEST).read_text())
    out = {}
    for name in (n for split in store.SPLITS for n in manifest["datasets"][split]):
        data = store.read_dataset(path / name, 2, 2, 200)
        # provenance, not data: a fresh id per collection, and the commit (a commit made while the test runs
        # would otherwise fail it: seen 2026-11-25)
        data["metadata"] = {k: v for k, v in data["metadata"].items() if k not in ("collection_id", "commit")}
        data["options"] = json.dumps(data["options"], default=lambda x: np.asarray(x).tolist())
        out[name] = data
    return out


@pytest.mark.slow
def test_kill_9_at_random_points_of_a_collection_then_recollect_gives_the_same_data(tmp_path, monkeypatch):
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "xla"))  # a kill may leave a half-written entry
    rng = random.Random(7)
    assert _run_script(COLLECT_SCRIPT, tmp_path / "straight")  # compiles (and fills the cache)
    start = time.perf_counter()
    assert _run_script(COLLECT_SCRIPT, tmp_path / "again")  # the duration the killed collections share
    duration = time.perf_counter() - start
    for delay in sorted(rng.uniform(0.3, 1.0) * duration for _ in range(KILLS)):
        if _run_script(COLLECT_SCRIPT, tmp_path / "killed", kill_after=delay):
            break
    assert _run_script(COLLECT_SCRIPT, tmp_path / "killed")  # completes, or finds it complete
    straight, killed = tmp_path / "straight" / COLLECTION, tmp_path / "killed" / COLLECTION
    a, b = _contents(straight), _contents(killed)
    assert list(a) == list(b) and len(a) == 60
    for name in a:
        for key in ("observations", "actions", "rewards", "options", "metadata"):
            assert np.array_equal(a[name][key], b[name][key]) if key in ("observations", "actions", "rewards") \
                else a[name][key] == b[name][key], (name, key)
    assert store.verify_collection(killed)[0] == "ok"
    leftovers = [p.name for p in (tmp_path / "killed" / FAMILY).iterdir() if p.name != "quick-seed0-eps1-per-task-experts"]
    assert leftovers == []  # no partial directory, no lock file


def test_a_directory_that_is_not_writable_is_named_not_its_lock_file(tmp_path, monkeypatch):
    import bati.io as io_module
    from bati.errors import describe_os_error

    def denied(path, what):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(io_module, "_acquire", denied)
    run = tmp_path / "run"
    run.mkdir()
    with pytest.raises(PermissionError) as caught:
        with hold_lock(run / LOCK_NAME, "the run directory"):
            pass
    assert describe_os_error(caught.value) == f"{run}: permission denied"


def test_verify_names_a_manifest_edited_by_hand(env, capsys):
    edit_manifest("n_episodes")(env, None, None)
    code, out, lines = call(capsys, ["data", "verify", "--root", env.data])
    assert code == 1 and len(lines) == 1
    assert "manifest.json was edited after the collection" in " ".join(out.split())
