"""bati.data.collect with worker processes: the same datasets (and bytes) whatever their number."""

from __future__ import annotations

import json
import uuid
from types import SimpleNamespace

import numpy as np
import pytest

from bati.data import collect as collect_mod
from bati.data import store
from bati.data.batch import ensure_family_data
from bati.data.collect import collect
from bati.envs import get_family

FAMILY = "PointGoal"
TINY = {"n_episodes": 2, "n_context_episodes": 1}  # 40 + 20 + 20 = 80 episodes
CHUNK = 8  # -> 10 chunks: datasets span chunks, chunks finish out of order in 2 workers


def tiny(root, workers, **kwargs):
    return collect(FAMILY, "quick", 0, root=root, progress=False, workers=workers, **{**TINY, **kwargs})


def dataset_content(path):
    """Every dataset's arrays, episode options and metadata (minus what names the collection)."""
    manifest = json.loads((path / store.MANIFEST).read_text())
    content = {}
    for split in store.SPLITS:
        for name in manifest["datasets"][split]:
            data = store.read_dataset(path / name, 2, 2, 200)
            meta = {k: v for k, v in data.pop("metadata").items() if k != "collection_id"}
            content[name] = {**data, "metadata": meta}
    return content


def same_tree(a, b) -> bool:
    """Equal nested dicts / lists of numbers, strings and arrays (Minari returns options as arrays)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same_tree(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and not isinstance(b, np.ndarray):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(map(same_tree, a, b))
    return np.array_equal(np.asarray(a), np.asarray(b))


def test_same_datasets_and_bytes_with_1_and_2_workers(tmp_path, monkeypatch):
    monkeypatch.setattr(collect_mod, "CHUNK", CHUNK)
    # collection_id is a fresh uuid4 per collection (it keys the loader's array cache) and is
    # stored in every dataset's metadata: fix it so that the files can be compared byte for byte
    fixed = uuid.UUID(int=7)
    monkeypatch.setattr(collect_mod, "uuid", SimpleNamespace(uuid4=lambda: fixed))
    one, two = tiny(tmp_path / "w1", workers=1), tiny(tmp_path / "w2", workers=2)
    assert not one.cached and not two.cached
    assert (one.manifest["workers"], two.manifest["workers"]) == (1, 2)
    assert one.manifest["collection_id"] == two.manifest["collection_id"] == fixed.hex

    a, b = dataset_content(one.path), dataset_content(two.path)
    assert list(a) == list(b) and len(a) == 60
    for name in a:
        for key in ("observations", "actions", "rewards"):
            assert np.array_equal(a[name][key], b[name][key]), (name, key)
        assert same_tree(a[name]["options"], b[name]["options"]), name
        assert a[name]["metadata"] == b[name]["metadata"], name
    # the chunks really differ: the episodes of one dataset span chunks with different keys
    assert not np.array_equal(a["train-00-v0"]["actions"][0], a["train-00-v0"]["actions"][1])

    # byte for byte (h5py writes no timestamps; Minari's metadata.json holds no dates)
    files = sorted(p.relative_to(one.path) for p in one.path.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two.path) for p in two.path.rglob("*") if p.is_file())
    assert len([f for f in files if f.name == "main_data.hdf5"]) == 60
    for file in files:
        if file.name == store.MANIFEST:  # wall times, creation date and workers differ
            continue
        assert (one.path / file).read_bytes() == (two.path / file).read_bytes(), file
    # the workers are how it was made, not what it is: the 2-worker collection is a cache hit
    again = tiny(tmp_path / "w2", workers=1)
    assert again.cached and again.manifest == two.manifest
    assert not list((tmp_path / "w2" / FAMILY).glob(".*partial*"))


@pytest.mark.parametrize("workers", [0, -1, 1.5, True])
def test_bad_workers_rejected_before_anything_is_written(tmp_path, workers):
    with pytest.raises(ValueError, match=r"^workers=") as info:
        tiny(tmp_path / "data", workers=workers)
    assert "\n" not in str(info.value) and ">= 1" in str(info.value)
    with pytest.raises(ValueError, match=r"^workers="):
        ensure_family_data(FAMILY, root=tmp_path / "data", progress=False, workers=workers, **TINY)
    assert not (tmp_path / "data").exists()


def test_worker_error_propagates_and_leaves_nothing(tmp_path, monkeypatch):
    """A worker that cannot load the expert: its error reaches the caller, no partial dir stays."""
    monkeypatch.setattr(collect_mod, "CHUNK", CHUNK)
    real = collect_mod.load_expert
    zoo = tmp_path / "zoo"
    (zoo / FAMILY / "per-task").mkdir(parents=True)  # the family's default experts: one SAC per training task
    expert_dir = collect_mod.Path(collect_mod.__file__).parents[1] / "experts" / "zoo" / FAMILY / "per-task"
    for name in ("expert.json", "actors.msgpack"):
        (zoo / FAMILY / "per-task" / name).write_bytes((expert_dir / name).read_bytes())
    expert = real(get_family(FAMILY), zoo)  # the main process has its experts; the workers will find none

    def main_only(family, zoo_dir=None, experts=None):
        (zoo / FAMILY / "per-task" / "expert.json").unlink(missing_ok=True)
        return expert

    monkeypatch.setattr(collect_mod, "load_expert", main_only)
    with pytest.raises(FileNotFoundError, match="no per-task experts for PointGoal"):
        tiny(tmp_path / "data", workers=2, zoo_dir=zoo)
    assert list((tmp_path / "data" / FAMILY).iterdir()) == []


def test_crash_in_the_main_process_stops_the_workers(tmp_path, monkeypatch):
    import multiprocessing

    monkeypatch.setattr(collect_mod, "CHUNK", CHUNK)
    real_write, calls = store.write_dataset, []

    def crash_after_three(*args, **kwargs):
        if len(calls) == 3:
            raise KeyboardInterrupt("simulated crash")
        calls.append(args[1])
        return real_write(*args, **kwargs)

    monkeypatch.setattr(store, "write_dataset", crash_after_three)
    with pytest.raises(KeyboardInterrupt):
        tiny(tmp_path, workers=2)
    assert len(calls) == 3  # it crashed mid-collection, after writing datasets
    assert list((tmp_path / FAMILY).iterdir()) == [] and not multiprocessing.active_children()
