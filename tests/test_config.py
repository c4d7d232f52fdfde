"""TrainConfig: defaults from the family's record, per-method sections, the CLI is the dataclass, and runs
recorded by older versions keep their identity and digests."""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path
from typing import get_type_hints

import gymnasium as gym
import pytest

from bati.cli import main
from bati.config import (
    NOT_IDENTITY,
    ResolvedConfig,
    TrainConfig,
    apply_settings,
    differing_settings,
    digest_view,
    family_of,
    method_sections,
)
from bati.envs import EPISODE_LENGTH, FAMILY_NAMES, family_available, get_family
from bati.experiments.sweep import Grid, SweepError, config_digest
from bati.methods import METHODS
from bati.methods.csro import CSROConfig
from bati.records import VERSION_KEY, read_record
from bati.rl.iql import IQLConfig

RESULTS = Path(__file__).parent.parent / "results"


def test_every_builtin_record_matches_its_registration_and_table3():
    for name in FAMILY_NAMES:
        if not family_available(name):
            continue
        record = get_family(name).record
        assert record.name == name and not record.terminates
        assert gym.spec(f"bati/{name}-v0").max_episode_steps == record.episode_length == EPISODE_LENGTH
    hopper, ant = get_family("HopperParam").record, get_family("AntDir").record
    assert (hopper.latent_dim, hopper.net_dims, hopper.paper_episodes) == (40, (128, 128), 1500)
    assert (ant.latent_dim, ant.net_dims, ant.paper_episodes, ant.club_weight) == (5, (64, 64), 500, 5.0)


def test_user_set_iql_settings_survive_resolved():
    # the old resolved() overwrote iql.hidden_dims and iql.learning_rate with its own values
    config = TrainConfig(iql=IQLConfig(hidden_dims=(48, 48), learning_rate=1e-3), learning_rate=5e-4).resolved()
    assert config.iql.hidden_dims == (48, 48) and config.iql.learning_rate == 1e-3 and config.learning_rate == 5e-4
    assert TrainConfig().resolved().iql.hidden_dims == (128, 128)
    assert TrainConfig(scale="paper").resolved().iql.hidden_dims == (256, 256)


def test_each_scale_sets_its_collection_steps_batch_and_nets():
    expected = {"quick": ("quick", 3_000, 64, (128, 128)), "cpu": ("paper", 100_000, 64, (128, 128)),
                "paper": ("paper", 100_000, 256, (256, 256))}
    for scale, (data, steps, batch, dims) in expected.items():
        config = TrainConfig(family="AntDir", scale=scale).resolved()
        assert (config.data_scale, config.steps, config.batch_size, config.iql.hidden_dims) == (data, steps, batch, dims)
        assert config.out_dir == Path("runs") / "AntDir" / scale / "bati-seed0"
    # a setting given by hand wins over the scale's default
    assert TrainConfig(scale="cpu", steps=500, batch_size=32).resolved().steps == 500
    with pytest.raises(ValueError, match="unknown scale 'huge'; choose one of: quick, cpu, paper"):
        TrainConfig(scale="huge").resolved()


def test_method_sections_take_the_family_default_unless_set():
    assert TrainConfig(family="HopperParam", method="csro").resolved().csro.club_weight == 2.5
    assert TrainConfig(family="PointGoal", method="unicorn").resolved().unicorn.focal_weight == 0.15
    set_by_hand = TrainConfig(family="HopperParam", method="csro", csro=CSROConfig(club_weight=0.5)).resolved()
    assert set_by_hand.csro.club_weight == 0.5


def test_every_method_with_hyperparameters_has_its_section():
    sections = method_sections()
    for name, cls in METHODS.items():
        if cls.Config is not None:
            assert sections[cls.config_key] is cls.Config, name
            assert dataclasses.is_dataclass(cls.Config) and cls.Config.__dataclass_params__.frozen


def test_the_built_in_sections_are_declared_fields_holding_their_methods_config():
    """TrainConfig declares a field per section of the methods in METHODS (nothing added at import time for
    them), holding the Config the methods read, in METHODS' order, after the run settings."""
    hints = get_type_hints(TrainConfig, include_extras=False)
    declared = [name for name in TrainConfig.__dataclass_fields__ if name in method_sections()]
    assert declared == list(method_sections()) == list(dict.fromkeys(
        cls.config_key for cls in METHODS.values() if cls.config_key is not None))
    source = inspect.getsource(TrainConfig)
    for name, config_class in method_sections().items():
        assert hints[name] is config_class, name
        assert f"    {name}: " in source, f"{name} is added at import time, not declared"
    assert [f.name for f in dataclasses.fields(TrainConfig)][-len(declared):] == declared


def test_config_json_holds_only_the_run_methods_section_and_reads_back():
    config = TrainConfig(family="HopperParam", method="bati-r").resolved()
    record = config.record()
    assert "bati" in record and not {"csro", "unicorn", "focal", "dpt"} & set(record)
    assert TrainConfig.from_record(record).resolved() == config
    assert "bati" not in TrainConfig(method="recon").resolved().record()


def test_an_old_record_upgrades_to_the_same_run():
    config = TrainConfig(family="HopperParam", method="csro").resolved()
    old = config.record()
    old.pop("csro")  # before method sections existed
    old.pop(VERSION_KEY)  # and records named their version
    old["iql"] = {("beta" if k == "temperature" else k): v for k, v in old["iql"].items()}
    old["rl_hidden_dims"] = old["iql"]["hidden_dims"]
    assert read_record(old)["iql"]["temperature"] == 0.05 and "rl_hidden_dims" not in read_record(old)
    # CSRO drew CLUB's negatives from any task before the setting existed: that is the run it was
    then = dataclasses.replace(config, csro=dataclasses.replace(config.csro, club_negatives="any-task")).record()
    assert differing_settings(old, then, [k for k in then if k not in NOT_IDENTITY]) == []
    for changed in (config.record(), dataclasses.replace(config, csro=CSROConfig(club_weight=9.0)).resolved().record()):
        assert differing_settings(old, changed, [k for k in changed if k not in NOT_IDENTITY]) == ["csro"]


def test_method_settings_added_later_keep_old_runs_and_their_digests():
    """focal.distance and focal.same_task came after runs were recorded: a section without them is the squared
    distance and pairs by training task, the run it always was, and its sweep digest does not change whether the
    fields are written or not."""
    for method, key in (("focal", "focal"), ("er-trl", "ertrl"), ("unicorn", "unicorn")):
        config = TrainConfig(family="AntDir", method=method).resolved()
        new = config.record()
        old = json.loads(json.dumps(new))
        for field in ("distance", "same_task"):
            old[key].pop(field)
        old.pop(VERSION_KEY)  # a record written before records named their version
        assert read_record(old)[key] == new[key]
        assert differing_settings(old, new, [k for k in new if k not in NOT_IDENTITY]) == []
        other = dataclasses.replace(config, **{key: dataclasses.replace(getattr(config, key), push_weight=2.0)})
        with_field = other.record()
        without = json.loads(json.dumps(with_field))
        for field in ("distance", "same_task"):
            without[key].pop(field)
        assert digest_view(with_field) == digest_view(without)
        root_mean = dataclasses.replace(config, **{key: dataclasses.replace(getattr(config, key), distance="root-mean")})
        assert differing_settings(old, root_mean.record(), [key]) == [key]
        assert config_digest(root_mean) != config_digest(config)
        by_value = dataclasses.replace(config, **{key: dataclasses.replace(getattr(config, key), same_task="value")})
        assert differing_settings(old, by_value.record(), [key]) == [key]
        assert config_digest(by_value) != config_digest(config)


def test_a_record_names_its_version_which_is_not_part_of_the_runs_identity():
    """config.json names the version of its format; a record without one is version 1 and is read as the
    older versions wrote it: the same run, the same digest."""
    config = TrainConfig(family="HopperParam", method="csro").resolved()
    record = config.record()
    assert record[VERSION_KEY] == 2 and VERSION_KEY in NOT_IDENTITY
    version_1 = {k: v for k, v in record.items() if k != VERSION_KEY}
    assert read_record(version_1) == record and digest_view(version_1) == digest_view(record)
    assert differing_settings(version_1, record, list(record)) == []
    # a setting missing from a version-1 record is its value before it existed; a version-2 record has them all
    for recorded, negatives in ((version_1, "any-task"), (record, "same-task")):
        csro = {k: v for k, v in recorded["csro"].items() if k != "club_negatives"}
        assert TrainConfig.from_record({**recorded, "csro": csro}).csro.club_negatives == negatives
    with pytest.raises(ValueError, match="record_version must be an integer, got 'two'"):
        TrainConfig.from_record({**record, VERSION_KEY: "two"})
    with pytest.raises(ValueError, match="record_version 3. was written by a newer bati"):
        TrainConfig.from_record({**record, VERSION_KEY: 3})


def test_committed_run_directories_keep_their_digests(monkeypatch):
    """The sweep digest names a run's directory: configs written before the method sections and the IQL
    renames must map to the same names, or every committed result would be retrained. A run of an earlier
    env version (FamilyRecord.version) keeps its digest under that version and gets another one under
    the current version (so a sweep retrains it rather than reusing it). CSRO runs from before
    csro.club_negatives were moved to where their any-task config digests, out of today's CSRO's way."""
    checked = older = 0
    for path in sorted(RESULTS.rglob("config.json")):
        setting = path.parent.parent.name
        if not setting.startswith(("quick-", "cpu-", "paper-")):
            continue
        saved = json.loads(path.read_text())
        config = TrainConfig.from_record(saved).resolved()
        digest = lambda: config_digest(config, exclude=NOT_IDENTITY + ("method", "seed"))[:8]  # noqa: E731
        family = type(family_of(config.family))
        recorded = saved.get("family_version", 1)
        if recorded != family.record.version:
            assert digest() != setting.rsplit("-", 1)[1], path
            older += 1
        with monkeypatch.context() as patch:
            patch.setattr(family, "record", dataclasses.replace(family.record, version=recorded))
            assert digest() == setting.rsplit("-", 1)[1], path
        checked += 1
    assert checked >= 10 and older >= 1


def test_dotted_settings_and_their_errors():
    config = apply_settings(TrainConfig(method="csro"), {"iql.hidden_dims": (8, 8), "csro.club_weight": 3.0,
                                                          "steps": 7})
    assert (config.iql.hidden_dims, config.csro.club_weight, config.steps) == ((8, 8), 3.0, 7)
    with pytest.raises(ValueError, match="unknown setting 'iql.nope'"):
        apply_settings(TrainConfig(), {"iql.nope": 1})
    assert Grid(settings=("csro.club_weight=3", "iql.hidden_dims=[8,8]")).overrides() == \
        {"csro.club_weight": 3, "iql.hidden_dims": (8, 8)}
    with pytest.raises(SweepError, match="unknown setting 'iql.discrete'"):  # derived from the family
        Grid(settings=("iql.discrete=true",)).overrides()


def test_bati_train_rejects_settings_beside_config(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(TrainConfig(steps=5).resolved().record()))
    assert main(["train", "--config", str(run), "--steps", "9"]) == 2
    err = capsys.readouterr().err
    assert "leave out --steps" in err and len(err.strip().splitlines()) == 1
    assert main(["train", "--family", "Nope"]) == 2  # checked before any work
    assert "unknown task family 'Nope'" in capsys.readouterr().err
    assert main(["train", "--bati.latent-samples", "0", "--out-dir", str(tmp_path / "new")]) == 2
    assert "bati.latent_samples must be an integer >= 1" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_another_methods_hyperparameters_are_refused_in_one_line(tmp_path, capsys):
    """A method never reads another method's section: setting it would record a config whose setting did
    nothing (and give the run a digest of its own), so it is refused before any work."""
    with pytest.raises(ValueError, match=r"focal.distance is read by focal only, not by csro \(which reads csro"):
        apply_settings(TrainConfig(method="csro"), {"focal.distance": "root-mean"}).resolved()
    with pytest.raises(ValueError, match="bati.latent_samples is read by bati, bati-r, bati-auto only, not by "
                                         r"oracle \(which has no hyperparameters of its own\)"):
        apply_settings(TrainConfig(method="oracle"), {"bati.latent_samples": 7}).resolved()
    apply_settings(TrainConfig(method="csro"), {"csro.distance": "root-mean"}).resolved()  # its own: fine
    assert main(["train", "--method", "focal", "--bati.latent-samples", "3", "--out-dir", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "bati.latent_samples is read by bati" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()


def test_a_run_resolves_once_into_the_family_object_and_its_collection():
    from bati.envs import get_family

    run = TrainConfig(family="AntDir", scale="cpu", seed=1, episodes_per_task=50, experts="per-task").resolve()
    assert run.family is not None and run.family.name == "AntDir" and run.config == \
        TrainConfig(family="AntDir", scale="cpu", seed=1, episodes_per_task=50, experts="per-task").resolved()
    c = run.collection
    assert (c.family, c.scale, c.seed, c.noise, c.experts, c.n_episodes) == (run.family, "paper", 0, 1.0, "per-task", 50)
    assert run.record() == run.config.record() and run.record()["family_version"] == run.family.record.version
    other = run.for_seed(2)  # no lookup: the same family object, the seed's default directory
    assert other.family is run.family and other.config.seed == 2
    assert other.config.out_dir == TrainConfig(family="AntDir", scale="cpu", seed=2).resolved().out_dir
    assert TrainConfig(family="AntDir").resolve(run.family).family is run.family
    with pytest.raises(ValueError, match="resolving a AntDir config with the family PointGoal"):
        TrainConfig(family="AntDir").resolve(get_family("PointGoal"))


def test_the_resolved_config_is_typed_with_the_values_that_run():
    narrowed = [f for f in dataclasses.fields(ResolvedConfig) if f.kw_only]
    assert {f.name for f in narrowed} >= {"family", "steps", "batch_size", "task_batch", "context_length",
                                          "eval_context_length", "eval_every", "checkpoint_every", "noise", "out_dir"}
    hints = get_type_hints(ResolvedConfig, include_extras=False)
    run = TrainConfig(family="HalfCheetahDir", scale="cpu").resolve()
    assert type(run.config) is ResolvedConfig
    for f in narrowed:  # no None left, of the declared type (the Literal of the experts kinds aside)
        value = getattr(run.config, f.name)
        assert value is not None, f.name
        if isinstance(hints[f.name], type):
            assert isinstance(value, hints[f.name]), (f.name, value)
    assert (run.config.steps, run.config.eval_every, run.config.context_length, run.config.noise) == \
        (100_000, 10_000, 200, 0.8)
    assert run.collection.sizes == (1_000, 20) and run.config.episodes_per_task is None  # the scale's, as recorded
    with pytest.raises(TypeError, match="steps"):  # built only with every value
        ResolvedConfig(**{f.name: getattr(run.config, f.name) for f in dataclasses.fields(ResolvedConfig)
                          if f.name != "steps"})


def test_a_context_longer_than_the_context_data_is_refused_by_the_collection():
    with pytest.raises(ValueError, match=r"eval_context_length \(4001\) must be at most the 4,000 transitions"):
        TrainConfig(family="AntDir", scale="cpu", eval_context_length=4001).resolve()
