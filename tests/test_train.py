"""Training and evaluation: smoke tests of every method on every family, resume, faults."""

from __future__ import annotations

import json
import os
import re
import threading
from pathlib import Path

import flax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bati.checkpoints as checkpoints_module
import bati.run_dir as run_dir_module
import bati.train as train_module
from bati.config import TrainConfig, family_of
from bati.data import Collection
from bati.device import machine_record
from bati.envs import FAMILY_NAMES, get_family
from bati.evaluate import Evaluator
from bati.experts import load as load_expert
from bati.methods import METHODS
from bati.rl.iql import IQLConfig
from bati.train import TrainingError, train, train_seeds
from bati.trainer import Trainer

TINY = dict(iql=IQLConfig(hidden_dims=(32, 32)), task_batch=4, batch_size=8, context_length=20, log_every=5)


# KuhnPoker: tests/test_kuhn.py trains every method on a small collected dataset (it needs the games extra)
@pytest.mark.parametrize("family", [name for name in FAMILY_NAMES if name != "KuhnPoker"])
@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_trains_and_evaluates_on_every_family(method, family, synthetic_data):
    data = synthetic_data(family)
    config = TrainConfig(family=family, method=method, steps=5, **TINY).resolved()
    expert = load_expert(family) if METHODS[method].needs_expert_actions else None  # DPT imitates it
    trainer = Trainer(config, data, family_of(config.family), expert)
    state = trainer.init(jax.random.PRNGKey(0))
    state, metrics = trainer.run_chunk(state, jax.random.PRNGKey(1), data.train, length=5)
    assert int(state.step) == 5
    assert all(np.isfinite(float(v)) for v in metrics.values())
    result = Evaluator(trainer.method, trainer.iql, data, config.context_length,
                       family=get_family(data.family)).evaluate(state, jax.random.PRNGKey(2), 0)
    for source in ("p_test", "p_train"):
        assert result.returns[source].shape == (len(data.test_tasks),)
        assert np.all(np.isfinite(result.returns[source]))
        assert result.latents[source].shape == (len(data.test_tasks), trainer.spec.latent_dim)
        if trainer.method.infers_task:
            assert np.all(result.inference_errors[source] >= 0)
        else:  # no-context: no latent, no inference error
            assert np.all(np.isnan(result.inference_errors[source]))


@pytest.fixture
def point_data(monkeypatch, synthetic_data):
    data = synthetic_data("PointGoal")
    monkeypatch.setattr(Collection, "ensure", lambda *a, **k: data)
    return data


def _config(tmp_path, name, **overrides):
    settings = {**TINY, "steps": 20, "eval_every": 10, **overrides}
    return TrainConfig(family="PointGoal", out_dir=tmp_path / name, **settings)


@pytest.mark.parametrize("method", ["bati", "recon"])
def test_train_writes_a_run_directory(tmp_path, point_data, method):
    summary = train(_config(tmp_path, method, method=method), show_progress=False)
    out = tmp_path / method
    for name in ("config.json", "metrics.jsonl", "eval.jsonl", "checkpoint.msgpack", "eval.json"):
        assert (out / name).exists(), name
    assert [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()] == [5, 10, 15, 20]
    assert [e["step"] for e in summary["curve"]] == [10, 20]
    assert json.loads((out / "eval.json").read_text())["p_test_return"] == summary["p_test_return"]


def _params(path, template):
    return flax.serialization.from_bytes(template, path.read_bytes())


def _killed_at_second_checkpoint(monkeypatch):
    """Make the second checkpoint write die (as a kill would): the run stops after step 20's logs."""
    real, calls = checkpoints_module.atomic_write_bytes, []

    def write(path, data):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(path, data)

    monkeypatch.setattr(checkpoints_module, "atomic_write_bytes", write)


def test_resume_after_interruption_gives_the_same_parameters(tmp_path, point_data, monkeypatch):
    train(_config(tmp_path, "straight"), show_progress=False)
    with monkeypatch.context() as patch:
        _killed_at_second_checkpoint(patch)
        with pytest.raises(KeyboardInterrupt):
            train(_config(tmp_path, "resumed"), show_progress=False)  # killed before its step-20 checkpoint
    train(_config(tmp_path, "resumed"), show_progress=False)  # resumes from its step-10 checkpoint
    template = Trainer(_config(tmp_path, "x").resolved(), point_data, family_of("PointGoal")).init(jax.random.PRNGKey(0))
    straight = _params(tmp_path / "straight" / "checkpoint.msgpack", template)
    resumed = _params(tmp_path / "resumed" / "checkpoint.msgpack", template)
    assert int(resumed.step) == 20
    jax.tree_util.tree_map(np.testing.assert_array_equal, straight, resumed)
    steps = [json.loads(line)["step"] for line in (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()]
    assert steps == [5, 10, 15, 20]


def test_a_long_stretch_between_checkpoints_gets_a_timed_checkpoint_that_resumes_exactly(tmp_path, point_data,
                                                                                         monkeypatch):
    train(_config(tmp_path, "straight"), show_progress=False)
    monkeypatch.setattr(train_module, "CHECKPOINT_SECONDS", 0.0)  # every log boundary is "10 minutes later"
    with monkeypatch.context() as patch:
        _killed_at_second_checkpoint(patch)
        with pytest.raises(KeyboardInterrupt):
            train(_config(tmp_path, "resumed"), show_progress=False)  # killed writing step 10's checkpoint
    template = Trainer(_config(tmp_path, "x").resolved(), point_data, family_of("PointGoal")).init(jax.random.PRNGKey(0))
    assert int(_params(tmp_path / "resumed" / "checkpoint.msgpack", template).step) == 5  # a timed one (eval_every 10)
    train(_config(tmp_path, "resumed"), show_progress=False)
    straight = _params(tmp_path / "straight" / "checkpoint.msgpack", template)
    resumed = _params(tmp_path / "resumed" / "checkpoint.msgpack", template)
    jax.tree_util.tree_map(np.testing.assert_array_equal, straight, resumed)
    records = [json.loads(line) for line in (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [5, 10, 15, 20]
    straight_records = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    for a, b in zip(records, straight_records):
        assert {k: v for k, v in a.items() if k != "wall_time"} == {k: v for k, v in b.items() if k != "wall_time"}


def test_same_config_and_seed_reproduce_the_same_numbers(tmp_path, point_data):
    a = train(_config(tmp_path, "a"), show_progress=False)
    b = train(_config(tmp_path, "b"), show_progress=False)
    assert a["p_test_return"] == b["p_test_return"] and a["p_train_task_returns"] == b["p_train_task_returns"]


def test_nan_loss_stops_with_a_clear_error_and_keeps_the_last_checkpoint(tmp_path, monkeypatch, point_data):
    with monkeypatch.context() as patch:
        _killed_at_second_checkpoint(patch)
        with pytest.raises(KeyboardInterrupt):
            train(_config(tmp_path, "nan", steps=20), show_progress=False)  # stops with a step-10 checkpoint
    before = (tmp_path / "nan" / "checkpoint.msgpack").read_bytes()
    poisoned = point_data.train.replace(rewards=jnp.full_like(point_data.train.rewards, jnp.nan))
    monkeypatch.setattr(Collection, "ensure", lambda *a, **k: type(point_data)(
        **{**point_data.__dict__, "train": poisoned}))
    with pytest.raises(TrainingError, match="non-finite"):
        train(_config(tmp_path, "nan", steps=20), show_progress=False)
    assert (tmp_path / "nan" / "checkpoint.msgpack").read_bytes() == before


def test_a_run_directory_of_another_family_or_method_is_refused(tmp_path, point_data):
    train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    with pytest.raises(ValueError, match="method: 'bati' there, 'recon' now"):
        train(_config(tmp_path, "run", steps=5, eval_every=5, method="recon"), show_progress=False)


def test_a_rerun_with_any_other_setting_is_refused_and_names_it(tmp_path, point_data):
    train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    with pytest.raises(ValueError, match="steps: 5 there, 10 now"):
        train(_config(tmp_path, "run", steps=10, eval_every=5), show_progress=False)
    with pytest.raises(ValueError, match="eval_context_length: 20 there, 30 now"):
        train(_config(tmp_path, "run", steps=5, eval_every=5, eval_context_length=30), show_progress=False)


def test_a_rerun_of_a_finished_run_rewrites_none_of_its_files(tmp_path, point_data):
    first = train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    files = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (tmp_path / "run").iterdir() if p.is_file()}
    again = train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    assert again == json.loads(json.dumps(first))  # the record as written, its wall time included
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (tmp_path / "run").iterdir()
            if p.is_file() and p.name in files} == files


def test_a_checkpoint_with_other_networks_is_refused(tmp_path, point_data):
    train(_config(tmp_path, "small", steps=5, eval_every=5, iql=IQLConfig(hidden_dims=(16, 16))), show_progress=False)
    train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    (tmp_path / "run" / "checkpoint.msgpack").write_bytes((tmp_path / "small" / "checkpoint.msgpack").read_bytes())
    with pytest.raises(ValueError, match="does not match this run's networks"):
        train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)


def test_likelihood_split_reports_errors_for_each_part_of_eq8(tmp_path, monkeypatch, point_data):
    from bati.experiments import probes
    from bati.report import likelihood

    monkeypatch.setattr(Collection, "load", lambda *a, **k: point_data)
    train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    report = probes.likelihood_split(tmp_path / "run", context_length=20)
    max_distance = 2.0  # PointGoal goals lie on the unit circle
    for source in ("p_train", "p_test"):
        for part in ("full", "reward", "state"):
            assert 0.0 <= report[f"{source}_{part}_error"] <= max_distance
            assert 0.0 <= report[f"{source}_{part}_picks_collector"] <= 1.0
    assert "| p_test | reward |" in likelihood.likelihood_split_markdown(report)
    # saved beside the run, and redone only for another step or context length while the checkpoint is there
    run_dir = tmp_path / "run"
    assert probes.likelihood_split_due(run_dir, step=5, context_length=20)
    saved = probes.save_likelihood_split(run_dir, context_length=20)
    assert likelihood.read_likelihood_split(run_dir) == json.loads(json.dumps(saved))
    assert saved["step"] == 5 and saved["context_length"] == 20 and saved["commit"]
    assert not probes.likelihood_split_due(run_dir, step=5, context_length=20)
    assert probes.likelihood_split_due(run_dir, step=5, context_length=30)
    (run_dir / "checkpoint.msgpack").unlink()  # a committed run whose machine is gone: nothing to redo it from
    assert not probes.likelihood_split_due(run_dir, step=5, context_length=30)
    (run_dir / "likelihood.json").write_text("{}")
    assert likelihood.read_likelihood_split(run_dir) is None
    assert [m for m in ("bati", "bati-r", "bati-auto", "focal", "recon", "oracle") if probes.has_task_table(m)] \
        == ["bati", "bati-r", "bati-auto"]
    train(_config(tmp_path, "recon", steps=5, eval_every=5, method="recon"), show_progress=False)
    with pytest.raises(ValueError, match="no task table"):
        probes.likelihood_split(tmp_path / "recon", context_length=20)


def test_auroc_matches_hand_computation():
    from bati.inference import auroc

    # pairs (positive, negative): 2>1, 2=2 (1/2), 3>1, 3>2 -> 3.5 / 4
    assert auroc(np.array([2.0, 3.0]), np.array([1.0, 2.0])) == 0.875
    assert auroc(np.array([0.0]), np.array([1.0])) == 0.0


def test_infer_and_novelty_on_a_trained_bati_auto_run(tmp_path, monkeypatch, point_data, capsys):
    from bati.cli import main
    from bati.experiments.probes import run_probe
    from bati.report.probes import Probe

    monkeypatch.setattr(Collection, "load", lambda *a, **k: point_data)
    train(_config(tmp_path, "run", steps=5, eval_every=5, method="bati-auto"), show_progress=False)
    run_dir = tmp_path / "run"
    evals = [json.loads(line) for line in (run_dir / "eval.jsonl").read_text().splitlines()]
    assert min(abs(evals[-1]["state_weight"] - w) for w in (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)) < 1e-6
    assert json.loads((run_dir / "eval.json").read_text())["diagnostics"]["state_weight"] == evals[-1]["state_weight"]
    # a p_train context of test task 1, as a user's file; and the same with rewards no task explains
    context = {name: np.asarray(getattr(point_data.p_train, name)[1, :20])
               for name in ("observations", "actions", "rewards", "next_observations")}
    np.savez(tmp_path / "ctx.npz", **context)
    np.savez(tmp_path / "odd.npz", **{**context, "rewards": context["rewards"] + 1000.0})
    assert main(["infer", "--run-dir", str(run_dir), "--context", str(tmp_path / "ctx.npz")]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert 0 <= plain["task_index"] < point_data.train.n_tasks and plain["task"] == point_data.train_tasks[plain["task_index"]]
    assert main(["infer", "--run-dir", str(run_dir), "--context", str(tmp_path / "odd.npz")]) == 0
    odd = json.loads(capsys.readouterr().out)
    assert odd["unknown"] is True and odd["score"] > max(plain["score"], odd["threshold"])
    np.savez(tmp_path / "bad.npz", **{**context, "actions": context["actions"][:5]})
    assert main(["infer", "--run-dir", str(run_dir), "--context", str(tmp_path / "bad.npz")]) == 2
    assert "actions has shape (5, 2); expected (C, dim) with C = 20 transitions" in capsys.readouterr().err
    assert main(["infer", "--run-dir", str(run_dir), "--context", str(tmp_path / "none.npz")]) == 2
    assert "none.npz: cannot read the context file" in capsys.readouterr().err
    saved = run_probe(run_dir, Probe(novelty=True, repeats=2))
    for key in ("p_train_auroc", "p_test_auroc", "p_test_vs_p_train_auroc", "p_train_flagged", "p_test_flagged"):
        assert 0.0 <= saved[key] <= 1.0, key
    assert json.loads((run_dir / "probes" / "novelty.json").read_text())["threshold"] == saved["threshold"]


def test_a_rules_probe_opens_its_runs_checkpoint_with_the_rules_inference(tmp_path, monkeypatch, point_data):
    from bati.experiments.probes import run_probe
    from bati.report.probes import Probe, probe_path, read_probe

    monkeypatch.setattr(Collection, "load", lambda *a, **k: point_data)
    train_seeds(_config(tmp_path, "unused", steps=5, eval_every=5), (0,), show_progress=False, runs_dir=tmp_path / "r",
                rules=("bati-r",))
    train(_config(tmp_path, "alone", steps=5, eval_every=5, method="bati-r"), show_progress=False)
    probe = Probe(eval_context_length=10, repeats=1)
    as_rule = run_probe(tmp_path / "r" / "bati-seed0", probe, "bati-r")
    alone = run_probe(tmp_path / "alone", probe)
    assert as_rule["method"] == "bati-r" and as_rule["p_test_return"] == alone["p_test_return"]
    assert probe_path(tmp_path / "r" / "bati-seed0", probe, "bati-r").parent.name == "bati-r"
    assert read_probe(tmp_path / "r" / "bati-seed0", probe) is None  # the run's own probe is another file
    own = run_probe(tmp_path / "r" / "bati-seed0", probe)
    assert own["method"] == "bati" and read_probe(tmp_path / "r" / "bati-seed0", probe) == own
    with pytest.raises(ValueError, match="'focal' is not a test-time rule"):
        run_probe(tmp_path / "r" / "bati-seed0", probe, "focal")


def test_training_step_vmaps_over_seeds(synthetic_data):
    data = synthetic_data("PointGoal")
    trainer = Trainer(TrainConfig(family="PointGoal", method="bati", steps=3, **TINY).resolved(), data,
                      family_of("PointGoal"))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states = jax.vmap(trainer.init)(keys)
    run = jax.jit(jax.vmap(lambda s, k: trainer._run_chunk(s, k, data.train, 3)))
    states, metrics = run(states, keys)
    assert metrics["critic_loss"].shape == (2,)
    single, _ = trainer.run_chunk(trainer.init(keys[1]), keys[1], data.train, length=3)
    np.testing.assert_allclose(states.method.params["table"][1], single.method.params["table"], rtol=1e-4, atol=1e-5)
    assert not np.allclose(states.method.params["table"][0], states.method.params["table"][1])


def test_one_run_stacked_is_exactly_the_plain_program(synthetic_data):
    # the training loop always holds its runs stacked; a lone run must keep the unvmapped program's numbers
    data = synthetic_data("PointGoal")
    trainer = Trainer(TrainConfig(family="PointGoal", method="csro", steps=3, **TINY).resolved(), data,
                      family_of("PointGoal"))
    key = jax.random.PRNGKey(3)
    plain, plain_metrics = trainer.run_chunk(trainer.init(key), key, data.train, length=3)
    stacked, metrics = trainer.run_chunks(jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], trainer.init(key)), key[None],
                                          data.train, length=3)
    assert metrics["critic_loss"].shape == (1,)
    for a, b in zip(jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(stacked)):
        assert b.shape == (1, *a.shape) and np.array_equal(np.asarray(a), np.asarray(b)[0])
    assert {k: float(v) for k, v in plain_metrics.items()} == {k: float(v[0]) for k, v in metrics.items()}


def test_each_step_logs_how_far_apart_the_tasks_latents_are(synthetic_data):
    data = synthetic_data("PointGoal")
    for method in ("oracle", "no-context"):
        trainer = Trainer(TrainConfig(family="PointGoal", method=method, steps=1, **TINY).resolved(), data,
                          family_of("PointGoal"))
        key = jax.random.PRNGKey(3)
        _, metrics = trainer.step(trainer.init(jax.random.PRNGKey(0)), key, data.train)
        if method == "no-context":  # no latent, nothing to spread
            assert "latent_spread" not in metrics
            continue
        k_batch, k_context, _ = jax.random.split(key, 3)
        tasks = np.asarray(trainer.make_batch(data.train, k_batch, k_context)["task_arrays"])  # the oracle's z
        np.testing.assert_allclose(metrics["latent_spread"], tasks.std(axis=0).mean(), rtol=1e-5)


def _trained(method, data, steps=5):
    config = TrainConfig(family=data.family, method=method, steps=steps, **TINY).resolved()
    expert = load_expert(data.family) if METHODS[method].needs_expert_actions else None
    trainer = Trainer(config, data, family_of(config.family), expert)
    start = trainer.init(jax.random.PRNGKey(0))
    state, _ = trainer.run_chunk(start, jax.random.PRNGKey(1), data.train, length=steps)
    return trainer, start, state


def test_dpt_is_its_own_policy_so_iql_is_left_untouched(synthetic_data):
    trainer, start, state = _trained("dpt", synthetic_data("PointGoal"))
    same = jax.tree_util.tree_map(lambda a, b: bool(jnp.array_equal(a, b)), start.iql, state.iql)
    assert all(jax.tree_util.tree_leaves(same))
    changed = jax.tree_util.tree_map(lambda a, b: bool(jnp.array_equal(a, b)), start.method.params, state.method.params)
    assert not all(jax.tree_util.tree_leaves(changed))


def test_oracle_infers_the_true_task_whatever_the_context(synthetic_data):
    data = synthetic_data("PointGoal")
    trainer, _, state = _trained("oracle", data)
    evaluator = Evaluator(trainer.method, trainer.iql, data, 20, family=get_family(data.family))
    result = evaluator.evaluate(state, jax.random.PRNGKey(2), 0)
    for source in ("p_test", "p_train"):
        np.testing.assert_allclose(result.latents[source], data.test_task_arrays, rtol=1e-6)
        # nearest training task to the true one: the smallest distance there is
        distances = get_family(data.family).distance_matrix(data.test_tasks, data.train_tasks)
        np.testing.assert_allclose(result.inference_errors[source], distances.min(axis=1))


def test_seeds_in_one_program_equal_the_runs_trained_alone(tmp_path, point_data):
    together = train_seeds(_config(tmp_path, "unused"), (0, 1, 2), show_progress=False, runs_dir=tmp_path / "vmapped")
    alone = train(_config(tmp_path, "alone", seed=1), show_progress=False)
    template = Trainer(_config(tmp_path, "x").resolved(), point_data, family_of("PointGoal")).init(jax.random.PRNGKey(0))
    vmapped = _params(tmp_path / "vmapped" / "bati-seed1" / "checkpoint.msgpack", template)
    single = _params(tmp_path / "alone" / "checkpoint.msgpack", template)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5), vmapped, single)
    assert together[1]["seed"] == 1 and together[1]["steps"] == 20
    np.testing.assert_allclose(together[1]["p_test_return"], alone["p_test_return"], rtol=1e-3, atol=1e-2)
    for seed in (0, 1, 2):  # every seed has a complete run directory of its own
        out = tmp_path / "vmapped" / f"bati-seed{seed}"
        assert [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()] == [5, 10, 15, 20]
        assert json.loads((out / "config.json").read_text())["seed"] == seed
    assert together[0]["p_test_task_returns"] != together[2]["p_test_task_returns"]


def test_seeds_resumed_from_different_steps_are_brought_level(tmp_path, point_data, monkeypatch):
    runs = tmp_path / "runs"
    train(_config(runs, "bati-seed1", seed=1), show_progress=False)
    with monkeypatch.context() as patch:
        _killed_at_second_checkpoint(patch)  # seed 0 stops with a step-10 checkpoint
        with pytest.raises(KeyboardInterrupt):
            train(_config(runs, "bati-seed0", seed=0), show_progress=False)
    summaries = train_seeds(_config(tmp_path, "unused"), (0, 1), show_progress=False, runs_dir=runs)
    assert [s["steps"] for s in summaries] == [20, 20]
    for seed in (0, 1):
        steps = [json.loads(line)["step"] for line in (runs / f"bati-seed{seed}" / "eval.jsonl").read_text().splitlines()]
        assert steps == [10, 20]


def test_run_results_record_the_device_and_references(tmp_path, point_data):
    summary = train(_config(tmp_path, "run", steps=5, eval_every=5), show_progress=False)
    assert summary["device"].startswith(jax.devices()[0].platform)
    assert summary["config"]["steps"] == 5 and summary["config"]["method"] == "bati"
    references = summary["reference_returns"]
    assert references["expert"] > references["random"]  # the PointGoal expert reaches its goals
    runtime = json.loads((tmp_path / "run" / "config.json").read_text())["runtime"]
    assert "device" in runtime and summary["cpu_cores"] == runtime["cpu_cores"] >= 1  # the cores it could use
    assert summary["data"]["fingerprint"] == point_data.fingerprint()  # the numbers it trained on


def test_the_cores_recorded_are_those_the_process_may_use(monkeypatch):
    """`taskset -c 1` on a 2-core machine: the run used one core, and its numbers are one core's."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {1}, raising=False)
    assert machine_record()["cpu_cores"] == 1


def test_no_context_trains_iql_without_a_latent(tmp_path, point_data):
    summary = train(_config(tmp_path, "none", steps=5, eval_every=5, method="no-context"), show_progress=False)
    assert np.isfinite(summary["p_test_return"]) and np.isnan(summary["p_test_inference_error"])


@pytest.mark.parametrize("seeds", [(), (1, 1), (-1,)])
def test_bad_seed_lists_are_refused_before_any_work(tmp_path, seeds):
    with pytest.raises(ValueError, match="seeds must be distinct"):
        train_seeds(_config(tmp_path, "x"), seeds, show_progress=False, runs_dir=tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_a_tensorboard_sink_mirrors_the_logs(tmp_path, point_data):
    train(_config(tmp_path, "tb", log_to=("tensorboard",)), show_progress=False)
    events = list((tmp_path / "tb" / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1
    raw = events[0].read_bytes()
    assert b"train/representation_loss" in raw and b"eval/p_test_return" in raw
    # a sink is not part of the run's identity: resuming without it is the same run
    train(_config(tmp_path, "tb"), show_progress=False)


def test_unknown_or_missing_sinks_fail_before_any_work(tmp_path, monkeypatch):
    import importlib.util

    from bati.sinks import SinkUnavailable

    with pytest.raises(ValueError, match="unknown logging sink 'csv'"):
        TrainConfig(log_to=("csv",)).resolved()
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "wandb" else real(name, *a))
    with pytest.raises(SinkUnavailable, match=r"pip install 'bati\[wandb\]'"):
        TrainConfig(log_to=("wandb",)).resolved()


def test_a_run_takes_its_expert_from_zoo_dir(tmp_path, point_data, monkeypatch):
    """The expert of --zoo-dir gives the reference return (and would collect missing data, and label DPT)."""
    import shutil

    from bati.experts.zoo import ZOO_DIR

    zoo = tmp_path / "zoo"
    shutil.copytree(ZOO_DIR / "PointGoal", zoo / "PointGoal")
    asked, loaded, used = [], [], []
    real_load, real_references = run_dir_module.load_expert, train_module.reference_returns
    monkeypatch.setattr(run_dir_module, "load_expert",
                        lambda family, zoo_dir=None, experts=None: asked.append(zoo_dir)
                        or loaded.append(real_load(family, zoo_dir, experts)) or loaded[-1])
    monkeypatch.setattr(train_module, "reference_returns",
                        lambda data, **k: used.append(k.get("expert")) or real_references(data, **k))
    summary = train(_config(tmp_path, "own-zoo", zoo_dir=zoo), show_progress=False)
    assert asked == [zoo] and used == loaded  # loaded once, from the zoo, and the reference return is its
    package_expert = real_load(get_family("PointGoal"))  # the same actor, from the package zoo
    assert summary["reference_returns"]["expert"] == real_references(
        point_data, family=get_family("PointGoal"), expert=package_expert)["expert"]


def _context_file(tmp_path, name="ctx.npz", c=4, **override):
    arrays = {"observations": np.zeros((c, 2)), "actions": np.zeros((c, 2)), "rewards": np.zeros(c),
              "next_observations": np.zeros((c, 2)), **override}
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("make, message", [
    (lambda d: (d / "empty.npz").write_bytes(b"") or d / "empty.npz", "not an .npz file"),
    (lambda d: np.save(d / "one.npy", np.zeros(3)) or d / "one.npy", "one array (.npy), not an .npz context file"),
    (lambda d: _context_file(d, rewards=np.zeros((4, 1))), "rewards has shape (4, 1); expected (C,)"),
    (lambda d: _context_file(d, rewards=np.float64(1.0)), "rewards has shape (); expected (C,)"),
    (lambda d: _context_file(d, c=0), "the context is empty (0 transitions)"),
    (lambda d: _context_file(d, actions=np.zeros((3, 2))), "actions has shape (3, 2); expected (4, 2)"),
    (lambda d: _context_file(d, actions=np.zeros((4, 2), complex)), "actions holds complex128 values"),
    (lambda d: _context_file(d, observations=np.full((4, 2), 1e39)), "observations holds NaN or infinite values"),
    (lambda d: _context_file(d, rewards=np.array(["a", "b", "c", "d"])), "rewards holds <U1 values"),
])
def test_a_bad_context_file_is_one_line_naming_the_file_and_the_array(tmp_path, make, message):
    from bati.inference import InferenceError, read_context

    path = make(tmp_path)
    with pytest.raises(InferenceError, match=re.escape(message)) as caught:
        read_context(path, obs_dim=2, action_dim=2)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)
    assert read_context(_context_file(tmp_path, "good.npz"), 2, 2)["rewards"].shape == (1, 4)


def test_checkpoints_of_the_layout_before_the_method_train_state_load_with_the_same_numbers(tmp_path, point_data):
    """Checkpoints written before the method's parameters lived in a flax TrainState (method, method_opt) are
    read back in today's layout with every number as saved."""
    from bati.checkpoints import load_checkpoint

    trainer = Trainer(_config(tmp_path, "x").resolved(), point_data, family_of("PointGoal"))
    state, _ = trainer.run_chunk(trainer.init(jax.random.PRNGKey(0)), jax.random.PRNGKey(1), point_data.train, length=3)
    new = flax.serialization.to_state_dict(state)
    old = {"method": new["method"]["params"], "method_opt": new["method"]["opt_state"], "iql": new["iql"],
           "step": new["step"]}
    (tmp_path / "old.msgpack").write_bytes(flax.serialization.msgpack_serialize(old))
    restored = load_checkpoint(tmp_path / "old.msgpack", trainer.init(jax.random.PRNGKey(5)))
    same = jax.tree_util.tree_map(lambda a, b: bool(np.array_equal(a, b)), restored, state)
    assert all(jax.tree_util.tree_leaves(same))


def _evals(out):
    return [json.loads(line) for line in (out / "eval.jsonl").read_text().splitlines()]


def _rule_evals(out, rule):
    return [{"step": e["step"], **e["rules"][rule]} for e in _evals(out)]


def test_test_time_rules_give_the_numbers_of_runs_trained_alone_in_one_run(tmp_path, point_data):
    # bati-r and bati-auto train exactly as bati: evaluated as rules of its run (one training, one directory), each
    # rule's evaluations are those of a run of it trained alone (same states, same evaluation keys)
    runs = tmp_path / "runs"
    together = train_seeds(_config(tmp_path, "unused"), (0,), show_progress=False, runs_dir=runs,
                           rules=("bati-r", "bati-auto"))
    assert sorted(p.name for p in runs.iterdir()) == ["bati-seed0"]  # no folder of a rule's own
    saved = json.loads((runs / "bati-seed0" / "eval.json").read_text())
    for rule in ("bati-r", "bati-auto"):
        alone = train(_config(tmp_path / "alone", f"{rule}-seed0", method=rule), show_progress=False)
        assert _rule_evals(runs / "bati-seed0", rule) == _evals(tmp_path / "alone" / f"{rule}-seed0")
        entry = saved["rules"][rule]
        assert entry["p_test_return"] == alone["p_test_return"] and entry["curve"] == alone["curve"]
        assert entry["wall_time_s"] > 0
    assert "state_weight" in saved["rules"]["bati-auto"]["diagnostics"]  # BATI-auto calibrated, as alone
    assert together[0]["method"] == "bati" and "rules" not in together[0]
    plain = train(_config(tmp_path / "plain", "bati-seed0"), show_progress=False)
    assert {k: v for k, v in saved.items() if k not in ("rules", "wall_time_s", "config")} == \
        {k: v for k, v in plain.items() if k not in ("wall_time_s", "config")}  # the run's own numbers unchanged


def _without_wall_time(path):
    return [{k: v for k, v in json.loads(line).items() if k != "wall_time"} for line in path.read_text().splitlines()]


def test_evaluating_beside_training_gives_the_files_of_evaluating_in_turn(tmp_path, point_data):
    # two seeds in one program, bati-r as a rule, evaluations (every 5 steps) without and with a
    # checkpoint (every 10): the thread changes when the records are written, not what they say
    settings = dict(steps=20, eval_every=5, checkpoint_every=10)
    for name, beside in (("in-turn", False), ("beside", True)):
        train_seeds(_config(tmp_path, "unused", eval_beside_training=beside, **settings), (0, 1), show_progress=False,
                    runs_dir=tmp_path / name, rules=("bati-r",))
    for run in ("bati-seed0", "bati-seed1"):
        a, b = tmp_path / "in-turn" / run, tmp_path / "beside" / run
        assert [e["step"] for e in _evals(b)] == [5, 10, 15, 20]
        assert _evals(a) == _evals(b), run
        assert _without_wall_time(a / "metrics.jsonl") == _without_wall_time(b / "metrics.jsonl"), run
        assert (a / "checkpoint.msgpack").read_bytes() == (b / "checkpoint.msgpack").read_bytes(), run
        saved = [json.loads((d / "eval.json").read_text()) for d in (a, b)]
        assert saved[0]["p_test_return"] == saved[1]["p_test_return"]


def test_training_goes_on_while_an_evaluation_runs_beside_it(tmp_path, point_data, monkeypatch):
    # the evaluation of step 10 waits until training has logged step 15: it can end only if training went on
    logged_15, saw = threading.Event(), []
    real_append, real_evaluate = train_module.append_jsonl, Evaluator.evaluate_runs

    def append(path, record):
        real_append(path, record)
        if path.name == "metrics.jsonl" and record["step"] >= 15:
            logged_15.set()

    def evaluate_runs(self, states, keys, seeds):
        if seeds[0] == 10:  # seed 0 * 7919 + step 10
            saw.append(logged_15.wait(timeout=120))
        return real_evaluate(self, states, keys, seeds)

    monkeypatch.setattr(train_module, "append_jsonl", append)
    monkeypatch.setattr(Evaluator, "evaluate_runs", evaluate_runs)
    train(_config(tmp_path, "run", eval_beside_training=True), show_progress=False)
    assert saw == [True]
    assert [e["step"] for e in _evals(tmp_path / "run")] == [10, 20]


def test_a_checkpoint_waits_for_the_evaluation_of_its_step_beside_training(tmp_path, point_data, monkeypatch):
    # step 20's evaluation fails in its thread: the run stops with step 10's checkpoint and evaluation only, and
    # resuming it gives the run trained without a failure
    real_evaluate = Evaluator.evaluate_runs

    def evaluate_runs(self, states, keys, seeds):
        if seeds[0] == 20:
            raise KeyboardInterrupt  # as a kill would stop it
        return real_evaluate(self, states, keys, seeds)

    with monkeypatch.context() as patch:
        patch.setattr(Evaluator, "evaluate_runs", evaluate_runs)
        with pytest.raises(KeyboardInterrupt):
            train(_config(tmp_path, "resumed", eval_beside_training=True), show_progress=False)
    resumed = tmp_path / "resumed"
    assert [e["step"] for e in _evals(resumed)] == [10] and not (resumed / "eval.json").exists()
    template = Trainer(_config(tmp_path, "x").resolved(), point_data, family_of("PointGoal")).init(jax.random.PRNGKey(0))
    assert int(checkpoints_module.load_checkpoint(resumed / "checkpoint.msgpack", template).step) == 10
    train(_config(tmp_path, "resumed", eval_beside_training=True), show_progress=False)
    train(_config(tmp_path, "straight"), show_progress=False)
    assert _evals(resumed) == _evals(tmp_path / "straight")
    assert (resumed / "checkpoint.msgpack").read_bytes() == (tmp_path / "straight" / "checkpoint.msgpack").read_bytes()


def test_a_rule_follows_a_resumed_run_and_one_asked_for_after_the_run_began_is_refused(tmp_path, point_data,
                                                                                    monkeypatch):
    runs = tmp_path / "runs"
    with monkeypatch.context() as patch:
        _killed_at_second_checkpoint(patch)  # stops with a step-10 checkpoint and step-20 logs
        with pytest.raises(KeyboardInterrupt):
            train_seeds(_config(tmp_path, "unused"), (0,), show_progress=False, runs_dir=runs, rules=("bati-r",))
    assert [e["step"] for e in _evals(runs / "bati-seed0")] == [10, 20]
    train_seeds(_config(tmp_path, "unused"), (0,), show_progress=False, runs_dir=runs, rules=("bati-r",))
    alone = tmp_path / "alone" / "bati-r-seed0"
    train(_config(tmp_path / "alone", "bati-r-seed0", method="bati-r"), show_progress=False)
    assert _rule_evals(runs / "bati-seed0", "bati-r") == _evals(alone)  # step 20's evaluation redone once, from 10
    before = (runs / "bati-seed0" / "eval.json").read_bytes()
    with pytest.raises(ValueError, match="has evaluations without bati-auto .*train bati-auto on its own"):
        train_seeds(_config(tmp_path, "unused"), (0,), show_progress=False, runs_dir=runs, rules=("bati-auto",))
    assert (runs / "bati-seed0" / "eval.json").read_bytes() == before  # nothing written


@pytest.mark.parametrize("rules, message", [
    (("focal",), "'focal' is not a test-time rule of a 'bati' run"),
    (("bati",), "'bati' is not a test-time rule of a 'bati' run"),
    (("bogus",), "unknown test-time rule 'bogus'"),
])
def test_methods_that_train_otherwise_are_not_test_time_rules(tmp_path, rules, message):
    with pytest.raises(ValueError, match=message):
        train_seeds(_config(tmp_path, "x"), (0,), show_progress=False, runs_dir=tmp_path / "r", rules=rules)
    assert not (tmp_path / "r").exists()


def test_the_first_evaluation_prepared_beside_training_gives_the_same_numbers(tmp_path, point_data, monkeypatch):
    # Evaluator.warm_up compiles the evaluation and starts its envs in a thread while the first chunks train
    warm = train_seeds(_config(tmp_path, "unused"), (0, 1), show_progress=False, runs_dir=tmp_path / "warm",
                       rules=("bati-r",))
    skipped = []
    monkeypatch.setattr(Evaluator, "warm_up", lambda self, *args: skipped.append(type(self).__name__))
    cold = train_seeds(_config(tmp_path, "unused"), (0, 1), show_progress=False, runs_dir=tmp_path / "cold",
                       rules=("bati-r",))
    assert skipped == ["Evaluator", "Evaluator"]  # the run's evaluator and bati-r's, once each
    for name in ("bati-seed0", "bati-seed1"):
        assert _evals(tmp_path / "warm" / name) == _evals(tmp_path / "cold" / name)
    assert [r["p_test_return"] for r in warm] == [r["p_test_return"] for r in cold]


def test_an_evaluator_waits_for_its_warm_up_and_a_failed_one_is_left_to_the_evaluation(point_data):
    config = _config(Path("unused"), "unused").resolved()
    trainer = Trainer(config, point_data, family_of("PointGoal"))
    evaluator = Evaluator(trainer.method, trainer.iql, point_data, config.context_length,
                          family=get_family("PointGoal"))
    state = trainer.init(jax.random.PRNGKey(0))
    stacked = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], state)
    evaluator.warm_up(stacked, jax.random.PRNGKey(1)[None], [0])
    result = evaluator.evaluate_runs(stacked, jax.random.PRNGKey(1)[None], [0])[0]
    assert not evaluator._warming.is_alive() and len(evaluator.envs) == len(point_data.test_tasks)
    assert result.returns["p_test"].shape == (len(point_data.test_tasks),)
    broken = Evaluator(trainer.method, trainer.iql, point_data, config.context_length, family=get_family("PointGoal"))
    broken.warm_up(None, None, [0])  # raises in its thread, silently: the evaluation meets the real problem
    with pytest.raises(AttributeError):
        broken.evaluate_runs(None, None, [0])
    evaluator.close(), broken.close()


def test_bati_train_says_where_its_run_is(tmp_path, point_data, capsys):
    from bati.cli import main

    args = ["train", "--family", "PointGoal", "--steps", "10", "--eval-every", "10", "--log-every", "5",
            "--task-batch", "4", "--batch-size", "8", "--context-length", "20", "--iql.hidden-dims", "16", "16"]
    assert main(args + ["--out-dir", str(tmp_path / "one")]) == 0
    assert f"run directory: {tmp_path / 'one'}" in capsys.readouterr().out
    assert main(args + ["--seeds", "0", "1", "--out-dir", str(tmp_path / "two")]) == 0
    assert f"run directories: {tmp_path / 'two'}/bati-seed{{0,1}}" in capsys.readouterr().out
