"""bati.data: Eq. 9 / Eq. 10 collection, Minari storage, caching, crash safety, loader, samplers."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import time
from collections import Counter
from pathlib import Path

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bati.cli import main
from bati.data import collect as collect_mod
from bati.data import store
from bati.data.batch import TaskData, ensure_family_data, load_family_data, sample_batch, sample_contexts
from bati.data.collect import collect
from bati.data.plan import make_plan, n_minority
from bati.envs import get_family
from bati.errors import BatiWarning
from bati.io import git_commit

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("data")

FAMILY = "PointGoal"
SMALL = {"n_episodes": 5, "n_context_episodes": 2}
TINY = {"n_episodes": 2, "n_context_episodes": 1}


def tiny(root, seed=0, **kwargs):
    return collect(FAMILY, "quick", seed, root=root, progress=False, **{**TINY, **kwargs})


@pytest.fixture(scope="module")
def tiny_seed0(tmp_path_factory):
    """A tiny PointGoal collection (2 episodes per training task, 1 per context dataset)."""
    return tiny(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """One PointGoal collection (5 episodes per training task, 2 per context dataset), loaded."""
    root = tmp_path_factory.mktemp("data")
    result = collect(FAMILY, "quick", 0, root=root, progress=False, **SMALL)
    return result, load_family_data(FAMILY, "quick", 0, root=root)


def split_arrays(data):
    return {f"{split}.{name}": np.asarray(getattr(getattr(data, split), name))
            for split in ("train", "p_test", "p_train")
            for name in ("observations", "actions", "rewards", "next_observations", "collector")}


def brute_force_distances(data):
    """(test, train) Euclidean distances of the PointGoal goals, without the family's code."""
    test = np.asarray(data.test_tasks, dtype=np.float64)
    train = np.asarray(data.train_tasks, dtype=np.float64)
    return np.sqrt(((test[:, None, :] - train[None, :, :]) ** 2).sum(-1))


# --- the plan (who collects what), for any family --------------------------------------------
@pytest.mark.parametrize("n", [2, 10, 20, 500])
def test_eq9_plan_proportions(n):
    plan = make_plan(get_family(FAMILY), 0, n, 5)
    train = [d for d in plan.datasets if d.split == "train"]
    assert len(train) == 20
    n_other = max(1, round(0.1 * n))
    for i, d in enumerate(train):
        assert d.task_index == i and d.task == plan.train_tasks[i] and len(d.collectors) == n
        assert (d.collectors == i).sum() == n - n_other
        others = d.collectors[d.collectors != i]
        assert len(others) == n_other and np.all((others >= 0) & (others < 20))


def test_eq9_other_collectors_are_uniform_over_the_other_tasks():
    plan = make_plan(get_family(FAMILY), 0, 500, 5)
    # rank of each "other" collector among the 19 other tasks (0..18), pooled over the 20 tasks
    ranks = Counter(int(c) - (c > d.task_index) for d in plan.datasets if d.split == "train"
                    for c in d.collectors if c != d.task_index)
    assert sum(ranks.values()) == 20 * 50 and set(ranks) == set(range(19))
    assert all(25 <= count <= 85 for count in ranks.values()), ranks  # expected 52.6 each


def test_eq10_plan_reward_family_matches_brute_force():
    family = get_family(FAMILY)
    plan = make_plan(family, 3, 4, 6)
    test, train = np.asarray(plan.test_tasks), np.asarray(plan.train_tasks)
    distances = np.linalg.norm(test[:, None] - train[None], axis=-1)
    for split, expected in (("p_test", distances.argmax(1)), ("p_train", distances.argmin(1))):
        datasets = [d for d in plan.datasets if d.split == split]
        assert [d.task for d in datasets] == plan.test_tasks
        for j, d in enumerate(datasets):
            assert len(d.collectors) == 6 and np.all(d.collectors == expected[j]), (split, j)


def test_eq10_plan_dynamics_family_mixes_in_the_most_similar_expert():
    family = get_family("HopperParam")
    assert family.kind == "dynamics"
    plan = make_plan(family, 0, 4, 20)
    test, train = np.asarray(plan.test_tasks), np.asarray(plan.train_tasks)
    distances = np.abs(test[:, None] - train[None])
    for j, d in enumerate(d for d in plan.datasets if d.split == "p_test"):
        counts = Counter(d.collectors.tolist())
        assert counts == {int(distances[j].argmax()): 18, int(distances[j].argmin()): 2}
    assert n_minority(5) == 1 and n_minority(20) == 2 and n_minority(1000) == 100


def test_plan_is_reproducible_and_seed_dependent():
    family = get_family(FAMILY)
    a, b, c = make_plan(family, 0, 10, 3), make_plan(family, 0, 10, 3), make_plan(family, 1, 10, 3)
    assert all(np.array_equal(x.collectors, y.collectors) and np.array_equal(x.reset_seeds, y.reset_seeds)
               for x, y in zip(a.datasets, b.datasets))
    assert a.train_tasks != c.train_tasks
    seeds = np.concatenate([d.reset_seeds for d in a.datasets])
    assert len(np.unique(seeds)) == len(seeds) == 20 * 10 + 2 * 20 * 3



def test_the_recorded_commit_says_when_the_code_differs_from_it(tmp_path):
    import subprocess

    from bati.io import uncommitted_changes

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    assert git_commit(tmp_path) == "unknown"  # not a checkout
    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "first")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tmp_path, capture_output=True,
                          text=True).stdout.strip()
    assert git_commit(tmp_path) == head and not uncommitted_changes(tmp_path)
    (tmp_path / "code.py").write_text("x = 2\n")  # an edit not committed: the commit alone is not the code
    assert git_commit(tmp_path) == head and uncommitted_changes(tmp_path)  # the record names the commit alone
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "new.py").write_text("y = 1\n")  # a new file counts too
    assert uncommitted_changes(tmp_path)


def test_a_short_commit_keeps_its_dirty_mark():
    from bati.io import short_commit

    assert short_commit("e01df6a-dirty") == "e01df6a-dirty" and short_commit("e01df6a") == "e01df6a"
    assert short_commit("0123456789abcdef0123456789abcdef01234567-dirty") == "0123456789ab-dirty"


def test_the_running_code_commit_is_read_once_per_process(monkeypatch):
    import bati.io as io

    reads = []
    monkeypatch.setattr(io, "_read_state", lambda directory: (reads.append(directory) or f"c{len(reads)}", False))
    io._running_code_state.cache_clear()
    try:
        assert git_commit() == "c1" and git_commit() == "c1"  # a commit made meanwhile is not the running code
        assert io.code_record() == {"commit": "c1"} and reads == [Path(io.__file__).parent]
    finally:
        io._running_code_state.cache_clear()


def test_a_record_flags_code_that_differs_from_its_commit(monkeypatch):
    import bati.io as io

    monkeypatch.setattr(io, "_read_state", lambda directory: ("abc1234", True))
    io._running_code_state.cache_clear()
    try:
        assert io.code_record() == {"commit": "abc1234", "uncommitted_changes": True}
    finally:
        io._running_code_state.cache_clear()


# --- the collected data -----------------------------------------------------------------------
def test_collection_layout_and_manifest(small):
    result, data = small
    # the default collectors: one SAC per training task (App. C.2), named in the directory
    assert result.path.name == "quick-seed0-eps1-per-task-experts" and result.path.parent.name == FAMILY
    assert not result.cached and result.manifest["experts"] == "per-task"
    names = sorted(p.name for p in result.path.iterdir() if p.is_dir())
    assert names == sorted(f"{s}-{i:02d}-v0" for s in ("train", "p_test", "p_train") for i in range(20))
    manifest = json.loads((result.path / "manifest.json").read_text())
    for key, value in {"family": FAMILY, "scale": "quick", "seed": 0, "noise": 1.0, "n_episodes": 5,
                       "n_context_episodes": 2, "transitions": (100 + 80) * 200}.items():
        assert manifest[key] == value, key
    assert manifest["commit"] == git_commit()
    train, test = get_family(FAMILY).split_tasks(0)
    assert manifest["train_tasks"] == train and manifest["test_tasks"] == test
    assert not list(result.path.parent.glob(".*partial*"))


def test_stored_eq9_proportions_and_collectors(small):
    _, data = small
    collector = np.asarray(data.train.collector).reshape(20, 5, 200)
    assert np.all(collector == collector[:, :, :1])  # one collector per episode
    for i in range(20):
        episodes = collector[i, :, 0]
        assert (episodes == i).sum() == 4
        assert len(episodes[episodes != i]) == 1 and 0 <= episodes[episodes != i][0] < 20


def test_stored_eq10_collectors_match_brute_force(small):
    _, data = small
    distances = brute_force_distances(data)
    assert np.array_equal(np.asarray(data.p_test.collector), np.repeat(distances.argmax(1)[:, None], 400, 1))
    assert np.array_equal(np.asarray(data.p_train.collector), np.repeat(distances.argmin(1)[:, None], 400, 1))
    assert data.manifest["p_test_most_different"] == distances.argmax(1).tolist()


def test_episodes_are_driven_by_the_collectors_expert(small):
    """A PointGoal expert ends next to its own goal: episodes end at the collector's goal."""
    _, data = small
    for split, tasks in (("train", data.train_task_arrays), ("p_test", data.test_task_arrays),
                         ("p_train", data.test_task_arrays)):
        split_data = getattr(data, split)
        final = np.asarray(split_data.next_observations).reshape(20, -1, 200, 2)[:, :, -1]
        collector = np.asarray(split_data.collector).reshape(20, -1, 200)[:, :, 0]
        to_collector_goal = np.linalg.norm(final - data.train_task_arrays[collector], axis=-1)
        assert to_collector_goal.mean() < 0.3, split
        if split == "p_test":  # the most different goal is far from the true one
            assert np.linalg.norm(final - tasks[:, None], axis=-1).mean() > 1.0


def test_transitions_are_consistent_and_noisy(small):
    _, data = small
    obs, act = np.asarray(data.train.observations), np.asarray(data.train.actions)
    nxt, rew = np.asarray(data.train.next_observations), np.asarray(data.train.rewards)
    assert obs.shape == (20, 1000, 2) and act.shape == (20, 1000, 2) and rew.shape == (20, 1000)
    assert obs.dtype == act.dtype == rew.dtype == np.float32 and data.train.collector.dtype == jnp.int32
    expected_next = np.clip(obs + 0.1 * np.clip(act, -1, 1), -2, 2)
    np.testing.assert_allclose(nxt, expected_next, atol=1e-5)
    episodes = obs.reshape(20, 5, 200, 2)
    assert np.all(episodes[:, :, 0] == 0)  # PointGoal starts at the origin
    np.testing.assert_array_equal(episodes[:, :, 1:], nxt.reshape(20, 5, 200, 2)[:, :, :-1])
    # eps = 1: rewards use a noisy goal, so they differ from the noise-free -|pos - goal|
    noise_free = -np.linalg.norm(nxt - data.train_task_arrays[:, None], axis=-1)
    assert 0.5 < np.abs(rew - noise_free).mean() < 1.5
    # experts act stochastically: the 4 own-expert episodes of a task are not identical
    own = np.asarray(data.train.collector).reshape(20, 5, 200)[0, :, 0] == 0
    actions = act.reshape(20, 5, 200, 2)[0][own]
    assert not np.allclose(actions[0], actions[1])


def test_metadata_round_trip_through_minari(small, monkeypatch):
    import minari

    result, data = small
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(result.path))
    assert set(minari.list_local_datasets()) == {f"{s}-{i:02d}-v0" for s in ("train", "p_test", "p_train")
                                                 for i in range(20)}
    for split, index, tasks in (("train", 4, data.train_tasks), ("p_test", 7, data.test_tasks)):
        dataset = minari.load_dataset(f"{split}-{index:02d}-v0")
        meta = dataset.storage.metadata["bati"]
        assert (meta["family"], meta["scale"], meta["seed"], meta["noise"]) == (FAMILY, "quick", 0, 1.0)
        assert meta["split"] == split and meta["task_index"] == index and meta["task"] == tasks[index]
        assert meta["commit"] == data.manifest["commit"]
        episodes = list(dataset.storage.get_episode_metadata(range(dataset.total_episodes)))
        collectors = np.asarray(getattr(data, split).collector).reshape(20, -1, 200)[index, :, 0]
        assert len(episodes) == len(collectors)
        for e, episode in enumerate(episodes):
            options = episode["options"]
            assert options["split"] == split and int(options["task_index"]) == index
            np.testing.assert_allclose(options["task"], tasks[index])
            assert int(options["collector"]) == collectors[e] == meta["collectors"][e]
            np.testing.assert_allclose(options["collector_task"], data.train_tasks[collectors[e]])
        first = next(dataset.iterate_episodes())
        assert first.observations.shape == (201, 2) and first.truncations[-1] and not first.terminations.any()
        flat = getattr(data, split)
        np.testing.assert_allclose(first.actions, np.asarray(flat.actions[index, :200]))
        np.testing.assert_allclose(first.rewards, np.asarray(flat.rewards[index, :200]), rtol=1e-6)
        env = dataset.recover_environment()
        assert env.unwrapped.task == tasks[index] and env.unwrapped.noise == 1.0


# --- caching and crash safety -------------------------------------------------------------------
def test_second_collect_is_cached(small, monkeypatch):
    result, _ = small
    manifest = result.path / "manifest.json"
    before = manifest.stat().st_mtime_ns

    def boom(*args, **kwargs):
        raise AssertionError("recollected")

    monkeypatch.setattr(collect_mod, "run_collection", boom)
    monkeypatch.setattr(collect_mod, "load_expert", boom)
    start = time.perf_counter()
    again = collect(FAMILY, "quick", 0, root=result.path.parents[1], progress=False, **SMALL)
    assert again.cached and time.perf_counter() - start < 0.5
    assert manifest.stat().st_mtime_ns == before and again.manifest == result.manifest
    with pytest.raises(ValueError, match="holds 5 episodes per training task"):
        collect(FAMILY, "quick", 0, root=result.path.parents[1], progress=False, n_episodes=12,
                n_context_episodes=2)


def test_loader_array_cache(small):
    result, data = small
    cache = result.path / "arrays.npz"
    assert cache.is_file()
    from_minari = load_family_data(FAMILY, "quick", 0, root=result.path.parents[1], cache=False)
    stamp = cache.stat().st_mtime_ns
    from_cache = load_family_data(FAMILY, "quick", 0, root=result.path.parents[1])
    assert cache.stat().st_mtime_ns == stamp
    a, b, c = split_arrays(data), split_arrays(from_minari), split_arrays(from_cache)
    for key in a:
        assert np.array_equal(a[key], b[key]) and np.array_equal(a[key], c[key]), key
    assert from_cache.obs_dim == from_cache.action_dim == from_cache.task_dim == 2
    assert from_cache.train_task_arrays.shape == (20, 2) and from_cache.test_task_arrays.shape == (20, 2)


def test_crash_leaves_nothing_and_rerun_succeeds(tmp_path, monkeypatch):
    real_write = store.write_dataset
    calls = []

    def crash_after_three(*args, **kwargs):
        if len(calls) == 3:
            raise KeyboardInterrupt("simulated crash")
        calls.append(args[1])
        return real_write(*args, **kwargs)

    monkeypatch.setattr(store, "write_dataset", crash_after_three)
    with pytest.raises(KeyboardInterrupt):
        tiny(tmp_path)
    assert len(calls) == 3  # it really crashed mid-collection, after writing datasets
    assert not list(tmp_path.rglob("manifest.json")) and not list(tmp_path.rglob("main_data.hdf5"))
    assert list((tmp_path / FAMILY).iterdir()) == []
    with pytest.raises(FileNotFoundError):
        load_family_data(FAMILY, root=tmp_path)

    monkeypatch.setattr(store, "write_dataset", real_write)
    # a killed run (no cleanup) leaves a partial dir of a dead process: the next run removes it;
    # a target directory without a manifest is incomplete (or foreign): it is replaced
    stale = tmp_path / FAMILY / ".quick-seed0-eps1-per-task-experts.partial-999999999-dead"
    (stale / "train-00-v0").mkdir(parents=True)
    target = store.collection_dir(tmp_path, get_family(FAMILY), "quick", 0, 1.0)
    (target / "train-00-v0").mkdir(parents=True)
    (target / "junk.txt").write_text("left over")
    with pytest.raises(FileNotFoundError):
        load_family_data(FAMILY, root=tmp_path)
    result = tiny(tmp_path)
    assert not result.cached and (result.path / "manifest.json").is_file()
    assert not stale.exists() and not (target / "junk.txt").exists()
    assert sorted(p.name for p in (tmp_path / FAMILY).iterdir()) == ["quick-seed0-eps1-per-task-experts"]
    assert load_family_data(FAMILY, root=tmp_path).train.observations.shape == (20, 400, 2)


def test_reproducible_from_the_seed(tiny_seed0, tmp_path):
    roots = {"a": tiny_seed0.path.parents[1], "b": tmp_path / "b", "c": tmp_path / "c"}
    a, b, c = tiny_seed0, tiny(roots["b"], seed=0), tiny(roots["c"], seed=1)
    load = {name: split_arrays(load_family_data(FAMILY, "quick", seed, root=roots[name], cache=False))
            for name, seed in (("a", 0), ("b", 0), ("c", 1))}
    for key in load["a"]:
        assert np.array_equal(load["a"][key], load["b"][key]), key
    assert not np.array_equal(load["a"]["train.actions"], load["c"]["train.actions"])
    assert a.manifest["train_tasks"] == b.manifest["train_tasks"] != c.manifest["train_tasks"]


def test_the_data_fingerprint_follows_the_numbers_not_the_files(tiny_seed0, tmp_path):
    """FamilyData.fingerprint: equal for the same collection read twice (from the Minari files and from the
    array cache), different for another seed's data and for one changed reward."""
    root = tiny_seed0.path.parents[1]
    read = load_family_data(FAMILY, "quick", 0, root=root, cache=False)
    cached = load_family_data(FAMILY, "quick", 0, root=root)
    assert read.fingerprint() == cached.fingerprint() and len(read.fingerprint()) == 16
    other_seed = load_family_data(FAMILY, "quick", 1, root=tiny(tmp_path / "c", seed=1).path.parents[1])
    assert other_seed.fingerprint() != read.fingerprint()
    edited = dataclasses.replace(read, p_train=read.p_train.replace(rewards=read.p_train.rewards.at[0, 0].add(1e-3)))
    assert edited.fingerprint() != read.fingerprint()


def test_noise_override(tmp_path):
    result = tiny(tmp_path, noise=0.0)
    assert result.path.name == "quick-seed0-eps0-per-task-experts" and result.manifest["noise"] == 0.0
    data = load_family_data(FAMILY, noise=0.0, root=tmp_path)
    next_obs = np.asarray(data.train.next_observations)
    noise_free = -np.linalg.norm(next_obs - data.train_task_arrays[:, None], axis=-1)
    np.testing.assert_allclose(np.asarray(data.train.rewards), noise_free, atol=1e-5)


# --- samplers ---------------------------------------------------------------------------------
def synthetic(n_tasks=20, episodes=3, length=10):
    """obs[k, i] = (k, i): every sample says which task and which step it came from."""
    k, i = np.meshgrid(np.arange(n_tasks), np.arange(episodes * length), indexing="ij")
    obs = np.stack([k, i], -1).astype(np.float32)
    return TaskData(
        observations=jnp.asarray(obs),
        actions=jnp.asarray(obs * 10),
        rewards=jnp.asarray(1000.0 * k + i, dtype=jnp.float32),
        next_observations=jnp.asarray(obs + np.array([0, 1], np.float32)),
        collector=jnp.asarray(k, dtype=jnp.int32),
        episode_length=length,
    )


def test_sample_batch_shapes_tasks_and_reproducibility(small):
    _, data = small
    key = jax.random.PRNGKey(0)
    batch = sample_batch(data.train, key, task_batch=16, batch_size=32)
    assert batch["task_ids"].shape == (16,) and batch["observations"].shape == (16, 32, 2)
    assert batch["actions"].shape == (16, 32, 2) and batch["rewards"].shape == (16, 32)
    assert batch["next_observations"].shape == (16, 32, 2)
    same = sample_batch(data.train, key, task_batch=16, batch_size=32)
    other = sample_batch(data.train, jax.random.PRNGKey(1), task_batch=16, batch_size=32)
    assert all(np.array_equal(batch[k], same[k]) for k in batch)
    assert not np.array_equal(batch["observations"], other["observations"])

    syn = synthetic(episodes=5, length=200)  # the shapes of data.train: the jitted sampler is reused
    keys = jax.random.split(jax.random.PRNGKey(2), 50)
    # pure jax: traceable with an abstract key (no host round trip), e.g. inside a jitted step
    shapes = jax.eval_shape(jax.vmap(lambda k: sample_batch(syn, k, task_batch=16, batch_size=32)), keys)
    assert shapes["observations"].shape == (50, 16, 32, 2)
    samples = [sample_batch(syn, k, task_batch=16, batch_size=32) for k in keys]
    batches = {name: np.stack([b[name] for b in samples]) for name in samples[0]}
    ids = np.asarray(batches["task_ids"])
    assert all(len(set(row)) == 16 for row in ids) and ids.min() >= 0 and ids.max() < 20
    obs = np.asarray(batches["observations"])
    assert np.all(obs[..., 0] == ids[:, :, None])  # each row's transitions come from its task
    np.testing.assert_array_equal(np.asarray(batches["actions"]), obs * 10)
    np.testing.assert_array_equal(np.asarray(batches["rewards"]), 1000 * obs[..., 0] + obs[..., 1])
    np.testing.assert_array_equal(np.asarray(batches["next_observations"])[..., 1], obs[..., 1] + 1)
    steps = obs[..., 1].ravel()
    assert steps.min() >= 0 and steps.max() < 1000 and len(np.unique(steps)) > 900  # uniform over all
    assert 0.45 < (steps < 500).mean() < 0.55
    assert np.bincount(ids.ravel(), minlength=20).min() > 0
    with pytest.raises(ValueError, match="task_batch=21"):
        sample_batch(syn, keys[0], task_batch=21, batch_size=4)


def test_sample_contexts_are_windows_inside_one_episode():
    syn = synthetic(episodes=3, length=10)
    task_ids = jnp.array([3, 3, 0, 19, 7])
    keys = jax.random.split(jax.random.PRNGKey(0), 200)
    sampler = jax.jit(jax.vmap(lambda k: sample_contexts(syn, k, task_ids, length=4)))
    ctx = sampler(keys)
    obs = np.asarray(ctx["observations"])
    assert obs.shape == (200, 5, 4, 2) and ctx["rewards"].shape == (200, 5, 4)
    assert np.all(obs[..., 0] == np.asarray(task_ids)[None, :, None])  # the right task
    steps = obs[..., 1]
    assert np.all(np.diff(steps, axis=-1) == 1)  # consecutive transitions
    assert np.all(steps[..., 0] // 10 == steps[..., -1] // 10)  # never across two episodes
    starts = steps[..., 0]
    assert set(np.unique(starts % 10)) == set(range(7)) and set(np.unique(starts // 10)) == {0, 1, 2}
    np.testing.assert_array_equal(np.asarray(ctx["actions"]), obs * 10)
    np.testing.assert_array_equal(np.asarray(ctx["next_observations"])[..., 1], steps + 1)
    np.testing.assert_array_equal(np.asarray(ctx["rewards"]), 1000 * obs[..., 0] + steps)
    again = sampler(keys)
    assert np.array_equal(np.asarray(again["observations"]), obs)  # same keys, same contexts
    assert not np.array_equal(obs[0], obs[1])
    # longer than an episode: whole consecutive episodes from an episode's first step
    long = np.asarray(jax.vmap(lambda k: sample_contexts(syn, k, task_ids, length=25))(keys)["observations"])[..., 1]
    assert long.shape == (200, 5, 25) and np.all(long[..., 0] % 10 == 0) and np.all(np.diff(long, axis=-1) == 1)
    assert set(np.unique(long[..., 0] // 10)) == {0}  # 3 episodes needed: only the first can start it
    with pytest.raises(ValueError, match="context length 31"):
        sample_contexts(syn, keys[0], task_ids, length=31)


def test_sample_contexts_on_collected_data(small):
    _, data = small
    ctx = sample_contexts(data.p_test, jax.random.PRNGKey(0), jnp.arange(20), length=200)
    assert ctx["observations"].shape == (20, 200, 2) and ctx["actions"].shape == (20, 200, 2)
    assert ctx["rewards"].shape == (20, 200) and ctx["next_observations"].shape == (20, 200, 2)
    obs, nxt = np.asarray(ctx["observations"]), np.asarray(ctx["next_observations"])
    assert np.all(obs[:, 0] == 0)  # length 200: exactly one whole episode, from the start state
    np.testing.assert_array_equal(obs[:, 1:], nxt[:, :-1])  # consecutive steps of one episode
    np.testing.assert_allclose(nxt, np.clip(obs + 0.1 * np.asarray(ctx["actions"]), -2, 2), atol=1e-5)
    # the context of test task j ends at the goal of its p_test collector (the most different task)
    goals = data.train_task_arrays[np.asarray(data.manifest["p_test_most_different"])]
    assert np.linalg.norm(nxt[:, -1] - goals, axis=-1).mean() < 0.3


# --- errors -----------------------------------------------------------------------------------
def one_line_error(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:"), err
    assert "Traceback" not in out + err
    return lines[0]


def test_missing_data_error(tmp_path, capsys):
    with pytest.raises(store.DatasetNotFoundError) as info:
        load_family_data(FAMILY, "quick", 3, root=tmp_path)
    message = str(info.value)
    assert str(tmp_path / FAMILY / "quick-seed3-eps1") in message
    assert f"`bati data collect --family PointGoal --scale quick --seed 3 --root {tmp_path}`" in message
    with pytest.raises(FileNotFoundError, match="--noise 0.5"):
        load_family_data(FAMILY, "paper", 0, noise=0.5, root=tmp_path)
    line = one_line_error(capsys, "data", "info", "--family", FAMILY, "--root", str(tmp_path))
    assert "bati data collect --family PointGoal --scale quick --seed 0" in line


def test_missing_expert_error(tmp_path, capsys):
    zoo = tmp_path / "zoo"
    zoo.mkdir()
    with pytest.raises(FileNotFoundError, match="bati experts train --family PointGoal"):
        collect(FAMILY, root=tmp_path / "data", zoo_dir=zoo, progress=False)
    with pytest.raises(FileNotFoundError, match="no per-task experts for PointGoal"):
        ensure_family_data(FAMILY, root=tmp_path / "data", zoo_dir=zoo, progress=False)
    with pytest.raises(FileNotFoundError, match="no expert for PointGoal"):
        ensure_family_data(FAMILY, root=tmp_path / "data", zoo_dir=zoo, progress=False, experts="conditioned")
    line = one_line_error(capsys, "data", "collect", "--family", FAMILY, "--root", str(tmp_path / "data"),
                          "--zoo-dir", str(zoo))
    assert "PointGoal" in line and "bati experts train --family PointGoal" in line
    assert not (tmp_path / "data").exists() or not list((tmp_path / "data").rglob("*.hdf5"))


def test_unknown_family_and_scale(tmp_path):
    with pytest.raises(ValueError, match="NoSuchFamily"):
        collect("NoSuchFamily", root=tmp_path, progress=False)
    with pytest.raises(ValueError, match="unknown scale 'huge'"):
        collect(FAMILY, "huge", root=tmp_path, progress=False)


@pytest.fixture
def tiny_copy(tiny_seed0, tmp_path):
    """A copy of the tiny collection (the tests below damage it)."""
    path = store.collection_dir(tmp_path, get_family(FAMILY), "quick", 0, 1.0)
    shutil.copytree(tiny_seed0.path, path, ignore=shutil.ignore_patterns("arrays.npz"))
    return path


def rerecord_checksums(path):
    """Make the manifest's checksums agree with the (edited) files: what a buggy collector would have
    written, so that the shape checks below, not the integrity check, must catch the mismatch."""
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["files"] = store.file_checksums(path, manifest["datasets"])
    manifest[store.MANIFEST_DIGEST] = store.manifest_digest(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))


def test_shape_mismatch_in_an_episode(tiny_copy):
    file = tiny_copy / "p_test-05-v0" / "data" / "main_data.hdf5"
    with h5py.File(file, "a") as f:
        del f["episode_0/observations"]
        f["episode_0/observations"] = np.zeros((201, 3))
    rerecord_checksums(tiny_copy)
    with pytest.raises(store.DatasetError) as info:
        load_family_data(FAMILY, root=tiny_copy.parents[1])
    message = str(info.value)
    assert str(file) in message and "(201, 3)" in message and "(201, 2)" in message


def test_space_mismatch_in_the_metadata(tiny_copy):
    file = tiny_copy / "train-02-v0" / "data" / "metadata.json"
    meta = json.loads(file.read_text())
    meta["observation_space"] = json.dumps({"type": "Box", "dtype": "float64", "shape": [3],
                                            "low": [-2.0] * 3, "high": [2.0] * 3})
    file.write_text(json.dumps(meta))
    rerecord_checksums(tiny_copy)
    with pytest.raises(store.DatasetError) as info:
        load_family_data(FAMILY, root=tiny_copy.parents[1], cache=False)
    assert str(file) in str(info.value) and "(3,)" in str(info.value) and "(2,)" in str(info.value)


def test_corrupted_files(tiny_copy, capsys):
    root = tiny_copy.parents[1]
    file = tiny_copy / "train-07-v0" / "data" / "main_data.hdf5"
    file.write_bytes(b"not an hdf5 file")
    with pytest.raises(store.DatasetError, match=str(file)):
        load_family_data(FAMILY, root=root)
    assert not (tiny_copy / "arrays.npz").exists()
    shutil.rmtree(tiny_copy / "train-07-v0")
    with pytest.raises(store.DatasetError, match="train-07-v0 is missing"):
        load_family_data(FAMILY, root=root)
    manifest = json.loads((tiny_copy / "manifest.json").read_text())
    manifest["train_tasks"][3] = [1.0, 0.0]
    manifest[store.MANIFEST_DIGEST] = store.manifest_digest(manifest)  # a collector's bug, not a hand edit
    (tiny_copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(store.DatasetError, match=r"train_tasks are not PointGoal.split_tasks\(0\)"):
        load_family_data(FAMILY, root=root)
    (tiny_copy / "manifest.json").write_text("{ truncated")
    with pytest.raises(store.DatasetError, match="manifest.json is corrupted"):
        load_family_data(FAMILY, root=root)
    line = one_line_error(capsys, "data", "info", "--family", FAMILY, "--root", str(root))
    assert "manifest.json is corrupted" in line


def test_cli_collect_and_cache(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(collect_mod.SCALES, "quick", dict(TINY))
    monkeypatch.chdir(tmp_path)  # the default root is the relative path "data"
    assert main(["data", "collect", "--family", FAMILY, "--seed", "2"]) == 0
    out = capsys.readouterr().out
    assert "collected in" in out and "16,000 transitions" in out and "data/PointGoal/quick-seed2-eps1" in out
    assert main(["data", "collect", "--family", FAMILY, "--seed", "2"]) == 0
    assert "already collected" in capsys.readouterr().out
    assert main(["data", "info", "--family", FAMILY, "--seed", "2"]) == 0
    assert "most different" in capsys.readouterr().out
    assert os.path.isfile(tmp_path / "data" / FAMILY / "quick-seed2-eps1" / "manifest.json")
    assert load_family_data(FAMILY, seed=2).train.observations.shape == (20, 400, 2)


def test_a_dataset_changed_after_its_array_cache_was_built_is_noticed(tiny_copy):
    root = tiny_copy.parents[1]
    load_family_data(FAMILY, root=root)  # builds arrays.npz
    file = tiny_copy / "train-03-v0" / "data" / "main_data.hdf5"
    content = bytearray(file.read_bytes())
    content[-1] ^= 0xFF  # an edit of the same size, after the cache was built
    file.write_bytes(bytes(content))
    with pytest.warns(BatiWarning, match="was built from other files"):
        with pytest.raises(store.DatasetError, match=re.escape(str(file))):
            load_family_data(FAMILY, root=root)


def test_a_collection_of_another_env_shape_is_not_already_collected(tiny_copy):
    manifest = json.loads((tiny_copy / "manifest.json").read_text())
    manifest["obs_dim"] = 3  # the env's observations changed since (without a version bump)
    manifest[store.MANIFEST_DIGEST] = store.manifest_digest(manifest)
    (tiny_copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(store.DatasetError, match="obs_dim/action_dim 3/2 do not match the PointGoal env's 2/2"):
        tiny(tiny_copy.parents[1])


def test_bati_data_collect_is_always_the_module():
    import subprocess
    import sys

    code = ("import bati.data as d, types; first = d.collect; import bati.data.collect; "
            "assert isinstance(first, types.ModuleType) and d.collect is first and callable(d.collect.collect)")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_resolved_runs_collection_reads_the_collection_it_names(small):
    from bati.config import TrainConfig

    result, data = small
    root = result.path.parents[1]
    run = TrainConfig(family=FAMILY, data_root=root, episodes_per_task=5, context_episodes=2).resolve()
    assert run.collection.collect(progress=False).cached  # found, not collected again
    assert run.collection.collect(check_only=True) is None
    loaded = run.collection.ensure(progress=False)
    assert loaded.path == data.path and loaded.fingerprint() == data.fingerprint()
    with pytest.raises(ValueError, match="holds 5 episodes per training task"):
        TrainConfig(family=FAMILY, data_root=root, episodes_per_task=6).resolve().collection.collect(check_only=True)


def test_a_collection_larger_than_the_machine_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    from bati.data import collect as collect_module

    monkeypatch.setattr(collect_module, "available_memory", lambda: 10_000)  # 10 KB
    # (20 x 2 + 2 x 20 x 1) episodes x 200 steps x 4 bytes x (2 x obs 2 + action 2 + reward + collector) = 512,000 B
    with pytest.raises(ValueError, match=r"2 episodes per training task and 1 per context dataset make ~500.0 KB of "
                                         r"PointGoal data; this machine has 9.8 KB of memory"):
        collect_module.collect("PointGoal", "quick", root=tmp_path / "data", n_episodes=2, n_context_episodes=1,
                               progress=False, workers=1)
    assert not (tmp_path / "data").exists()
