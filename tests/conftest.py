"""Shared fixtures: small synthetic FamilyData for any family (random-action rollouts, no experts)."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile


def _share_compiled_programs() -> None:
    """Most of the suite's time is XLA compiling the same small programs again (each test builds its own
    trainer), so the tests of a process and the processes they start share JAX's persistent compilation cache,
    in a temporary directory removed at exit. One cache per xdist worker: JAX writes an entry without a lock,
    and a reader in a concurrent process could catch it half written (JAX then warns and compiles anew).
    A JAX_COMPILATION_CACHE_DIR of your own is left alone."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    owner = os.environ.get("BATI_TESTS_XLA_CACHE_OF")
    if owner == worker or (owner is None and "JAX_COMPILATION_CACHE_DIR" in os.environ):
        return
    cache = tempfile.mkdtemp(prefix=f"bati-tests-xla-{worker}-")
    atexit.register(shutil.rmtree, cache, ignore_errors=True)
    os.environ.update(BATI_TESTS_XLA_CACHE_OF=worker, JAX_COMPILATION_CACHE_DIR=cache,
                      JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")


def _compile_without_most_optimisations() -> None:
    """XLA without most of its optimisation passes: the programs compile in about half the time, and compiling is
    most of the suite's time (HopperParam's eleven smoke tests 173 -> 115 s). Numbers then differ from a
    production run in their last bits; the tests compare runs within the suite, never with committed numbers.
    A JAX_DISABLE_MOST_OPTIMIZATIONS of your own (e.g. 0, to test the production programs) is left alone."""
    os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")


_share_compiled_programs()  # before JAX is imported: it reads these settings then
_compile_without_most_optimisations()

import jax.numpy as jnp
import numpy as np
import pytest

from bati.data import FamilyData, TaskData
from bati.envs import get_family
from bati.envs.rollout import rollout


def synthetic_family_data(name: str, n_train: int = 4, n_test: int = 3, episodes: int = 1, length: int = 40,
                          seed: int = 0) -> FamilyData:
    """Random-action episodes (shorter than 200 steps) in a few tasks of the family, shaped like real data."""
    family = get_family(name)
    train_tasks, test_tasks = family.split_tasks(seed, n_train, n_test)
    rng = np.random.default_rng(seed)

    def task_data(tasks, offset):
        eps = [rollout(family, tasks, lambda o, _: rng.uniform(-1, 1, (len(tasks), action_dim)), None,
                       seed=offset + 100 * e, length=length) for e in range(episodes)]
        cat = lambda field: jnp.asarray(np.concatenate([getattr(e, field) for e in eps], axis=1))
        n = episodes * length
        return TaskData(cat("observations"), cat("actions"), cat("rewards"), cat("next_observations"),
                        jnp.zeros((len(tasks), n), jnp.int32), episode_length=length)

    probe = family.make_env(train_tasks[0])
    obs_dim, action_dim = probe.observation_space.shape[0], probe.action_space.shape[0]
    arrays = lambda tasks: np.stack([family.task_to_array(t) for t in tasks])
    return FamilyData(name, "quick", seed, family.default_noise, train_tasks, test_tasks, arrays(train_tasks),
                      arrays(test_tasks), task_data(train_tasks, 0), task_data(test_tasks, 1), task_data(test_tasks, 2),
                      obs_dim, action_dim, family.task_dim)


@pytest.fixture(scope="session")
def synthetic_data():
    cache: dict[str, FamilyData] = {}

    def get(name: str) -> FamilyData:
        if name not in cache:
            cache[name] = synthetic_family_data(name)
        return cache[name]

    return get
