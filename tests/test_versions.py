"""A family's env version (FamilyRecord.version): data, experts and runs of another version are kept apart."""

from __future__ import annotations

import dataclasses
import shutil

import pytest

from bati.config import TrainConfig, differing_settings, digest_view
from bati.data import store
from bati.data.collect import collect
from bati.data.store import DatasetError
from bati.envs.point import PointGoalFamily
from bati.envs import get_family
from bati.experts import load
from bati.experts.zoo import ZOO_DIR


@pytest.fixture
def version2(monkeypatch):
    """PointGoal as if its env had changed once (version 2)."""
    monkeypatch.setattr(PointGoalFamily, "record", dataclasses.replace(PointGoalFamily.record, version=2))


def test_data_of_another_version_lives_apart_and_is_refused(tmp_path, monkeypatch):
    first = collect("PointGoal", root=tmp_path, n_episodes=2, n_context_episodes=1, progress=False, workers=1)
    assert first.path.name == "quick-seed0-eps1-per-task-experts" and first.manifest["family_version"] == 1
    monkeypatch.setattr(PointGoalFamily, "record", dataclasses.replace(PointGoalFamily.record, version=2))
    path = store.collection_dir(tmp_path, get_family("PointGoal"), "quick", 0, 1.0)
    assert path.name == "quick-seed0-eps1-per-task-experts-v2"  # the version-1 collection stays where it was, untouched
    shutil.copytree(first.path, path)  # a version-1 collection where version 2's belongs
    with pytest.raises(DatasetError, match="env version 1; this bati's PointGoal is version 2"):
        collect("PointGoal", root=tmp_path, n_episodes=2, n_context_episodes=1, progress=False, workers=1)


def test_an_expert_of_another_version_is_refused(version2, tmp_path):
    shutil.copytree(ZOO_DIR / "PointGoal", tmp_path / "PointGoal")  # expert.json without a version: 1
    with pytest.raises(ValueError, match="env version 1, not the current version 2; retrain"):
        load("PointGoal", tmp_path)


def test_a_run_records_its_version_and_a_run_of_another_version_differs(version2):
    current = TrainConfig(family="PointGoal").resolved().record()
    assert current["family_version"] == 2
    saved = {k: v for k, v in current.items() if k != "family_version"}  # recorded before versions existed
    assert differing_settings(saved, current, list(current)) == ["family_version"]
    assert digest_view(current)["family_version"] == 2


def test_version_1_keeps_old_run_records_and_digests():
    current = TrainConfig(family="PointGoal").resolved().record()
    assert current["family_version"] == 1
    saved = {k: v for k, v in current.items() if k != "family_version"}
    assert differing_settings(saved, current, list(current)) == []
    assert "family_version" not in digest_view(current)
