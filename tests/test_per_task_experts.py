"""Per-task experts (App. C.2): the task-mapped trainer, loading, and collection by the plan's collectors."""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest

from bati.data import store
from bati.data.collect import _chunks, _rollout_chunk, collect
from bati.data.plan import make_plan
from bati.envs import get_family
from bati.envs.rollout import LockstepEnvs
from bati.experts import load
from bati.experts.per_task import PER_TASK_DIR, PerTaskExperts, training_tasks
from bati.experts.sac import SACConfig
from bati.experts.train import ExpertTrainConfig, train_expert

# its tests share module fixtures that take seconds to build: one worker builds them once (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("per_task_experts")

TINY = dict(per_task=True, total_steps=400, start_steps=200, update_every=50, eval_every=400,
            checkpoint_every=200, sac=SACConfig(hidden_dims=(16, 16), batch_size=16))


def _train(tmp_path, name, **settings):
    config = ExpertTrainConfig("PointGoal", out_dir=tmp_path / name, export_dir=tmp_path / f"zoo-{name}",
                               **{**TINY, **settings})
    train_expert(config, show_progress=False)
    return load("PointGoal", tmp_path / f"zoo-{name}", "per-task")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("per-task")
    return {"three": _train(tmp_path, "three", tasks=(0, 1, 2)),
            "alone": _train(tmp_path, "alone", tasks=(1,)),
            "zero-two": _train(tmp_path, "zero-two", tasks=(2, 0)),
            "resumed": (_train(tmp_path, "resumed", tasks=(0, 1, 2), total_steps=200, start_steps=100),
                        _train(tmp_path, "resumed", tasks=(0, 1, 2), start_steps=100)),
            "straight": _train(tmp_path, "straight", tasks=(0, 1, 2), start_steps=100),
            "all": _train(tmp_path, "all", total_steps=300),
            "vmapped": _train(tmp_path, "vmapped", tasks=(0, 1, 2), task_axis="vmap"),
            "dir": tmp_path}


def _actor(experts: PerTaskExperts, i: int):
    return jax.tree_util.tree_map(lambda x: np.asarray(x[i]), experts.actors)


def test_each_task_trained_beside_others_gets_the_parameters_it_gets_alone(trained):
    three, alone = trained["three"], trained["alone"]
    assert three.meta["task_indices"] == [0, 1, 2] and alone.meta["task_indices"] == [1]
    jax.tree_util.tree_map(np.testing.assert_array_equal, _actor(three, 1), _actor(alone, 0))
    # and the tasks did not share parameters: expert 0 differs from expert 1
    assert not np.allclose(_actor(three, 0)["params"]["Dense_0"]["kernel"],
                           _actor(three, 1)["params"]["Dense_0"]["kernel"])


def test_a_tasks_evaluation_episode_is_seeded_by_its_index_not_its_place_in_the_part(monkeypatch):
    from collections import namedtuple

    from bati.experts import per_task

    Episodes = namedtuple("Episodes", "returns")
    seeds = []

    def fake_rollout(family, tasks, act, noise, seed):
        seeds.append(seed)
        return Episodes(np.zeros(len(tasks)))

    monkeypatch.setattr(per_task, "rollout", fake_rollout)
    per_task.evaluate_per_task(None, None, get_family("PointGoal"), ["a", "b"], [5, 7], seed=100)
    assert seeds == [[105, 107]]  # the full program's reset seeds for training tasks 5 and 7


def test_resumed_per_task_training_gives_the_uninterrupted_experts(trained):
    first, resumed = trained["resumed"]
    assert first.meta["train_steps_per_task"] == 200 and resumed.meta["train_steps_per_task"] == 400
    jax.tree_util.tree_map(np.testing.assert_array_equal, resumed.actors, trained["straight"].actors)
    lines = (trained["dir"] / "resumed" / "metrics.jsonl").read_text().splitlines()
    assert len(json.loads(lines[-1])["eval_returns"]) == 3


def test_experts_trained_in_parts_merge_into_the_experts_trained_together(trained, tmp_path):
    from bati.cli import main

    zoo = trained["dir"]
    assert main(["experts", "merge", "--family", "PointGoal", "--parts", str(zoo / "zoo-zero-two"),
                 str(zoo / "zoo-alone"), "--export-dir", str(tmp_path / "merged")]) == 0
    merged = load("PointGoal", tmp_path / "merged", "per-task")
    three = trained["three"]
    assert merged.meta["task_indices"] == [0, 1, 2] and merged.meta["parts"] == 2
    np.testing.assert_allclose(merged.meta["tasks"], three.meta["tasks"])
    jax.tree_util.tree_map(np.testing.assert_array_equal, merged.actors, three.actors)


def test_a_merge_of_overlapping_or_unlike_parts_is_refused_before_writing(trained, tmp_path, capsys):
    from bati.cli import main

    zoo = trained["dir"]
    base = ["experts", "merge", "--family", "PointGoal", "--export-dir", str(tmp_path / "merged"), "--parts"]
    assert main(base + [str(zoo / "zoo-three"), str(zoo / "zoo-alone")]) == 2
    assert "training task(s) [1] are in more than one part" in capsys.readouterr().err
    other_seed = tmp_path / "other-seed"
    shutil.copytree(zoo / "zoo-zero-two", other_seed)
    meta_path = other_seed / "PointGoal" / PER_TASK_DIR / "expert.json"
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "seed": 1}))
    assert main(base + [str(zoo / "zoo-alone"), str(other_seed)]) == 2
    assert "has seed=1" in capsys.readouterr().err
    assert not (tmp_path / "merged").exists()
    assert main(["experts", "merge", "--family", "PointGoal", "--parts", str(zoo / "zoo-alone")]) == 2
    assert "--export-dir or --into-package" in capsys.readouterr().err


def test_export_holds_the_tasks_and_actors_only(trained):
    entry = trained["dir"] / "zoo-three" / "PointGoal" / PER_TASK_DIR
    assert sorted(p.name for p in entry.iterdir()) == ["actors.msgpack", "expert.json"]
    meta = json.loads((entry / "expert.json").read_text())
    family = get_family("PointGoal")
    expected = [family.task_to_array(t).tolist() for t in training_tasks(family)[:3]]
    np.testing.assert_allclose(meta["tasks"], expected)
    assert meta["kind"] == "per-task" and meta["split_seed"] == 0


def _labels(n: int) -> np.ndarray:
    return np.linspace(-0.9, 0.9, n)


def _labelled_experts(family_name: str, n: int) -> PerTaskExperts:
    """Per-task experts whose actor i always acts about _labels(n)[i] on every action dimension (zero
    weights, the mean's bias atanh of it, the smallest std: ~7 std apart from the next expert's)."""
    family = get_family(family_name)
    env = family.make_env(training_tasks(family)[0], noise=0.0)
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    env.close()
    meta = {"kind": "per-task", "obs_dim": obs_dim, "action_dim": action_dim, "hidden_dims": [4],
            "tasks": [family.task_to_array(t).tolist() for t in training_tasks(family)][:n]}
    experts = PerTaskExperts(family, None, meta)
    template = experts._sac.init(jax.random.PRNGKey(0)).actor.params
    targets = np.arctanh(_labels(n))

    def stacked(path, leaf):
        names = [getattr(p, "key", None) for p in path]
        out = np.zeros((n,) + leaf.shape, np.float32)
        if names[-3:] == ["params", "Dense_0", "bias"]:  # the mean head
            out += targets[:, None]
        if names[-3:] == ["params", "Dense_1", "bias"]:  # the log-std head (clipped to its smallest)
            out -= 20.0
        return out

    experts.actors = jax.tree_util.tree_map_with_path(stacked, template)
    return experts


@pytest.mark.parametrize("family_name", ["PointGoal", "HalfCheetahDir"])
def test_eq9_and_eq10_run_the_expert_the_plan_names_for_each_episode(family_name):
    family = get_family(family_name)
    experts = _labelled_experts(family_name, 20)
    plan = make_plan(family, 0, n_episodes=10, n_context_episodes=2)
    chunks = _chunks(family, plan, chunk_size=64)
    jobs = [(d, e) for d in plan.datasets for e in range(len(d.collectors))]
    with LockstepEnvs(family, 0.0) as envs:
        for chunk in chunks[:3]:
            _, actions, _ = _rollout_chunk(family, experts, 0.0, 0, chunk, 64, envs)
            for k in range(len(chunk.tasks)):
                d, e = jobs[chunk.index * 64 + k]
                collector = int(d.collectors[e])
                nearest = np.abs(actions[k, :, 0, None] - _labels(20)).argmin(-1)
                np.testing.assert_array_equal(nearest, collector)
    # Eq. 9: a training task's own expert for 90%; Eq. 10: test tasks from the most different / similar one
    train0 = next(d for d in plan.datasets if d.split == "train" and d.task_index == 0)
    assert np.mean(train0.collectors == 0) == 0.9
    for d in plan.datasets:
        if d.split != "train":
            expected = plan.most_different if d.split == "p_test" else plan.most_similar
            assert np.all(d.collectors == expected[d.task_index])


def test_the_expert_of_any_task_is_the_most_similar_training_tasks_first_on_ties():
    experts = _labelled_experts("HalfCheetahDir", 20)
    family = get_family("HalfCheetahDir")
    train = training_tasks(family)
    for task in (-1.0, 1.0):
        first = next(i for i, t in enumerate(train) if t == task)
        action = experts(np.zeros(experts.meta["obs_dim"]), task)
        np.testing.assert_allclose(action, _labels(20)[first], atol=1e-5)


def test_per_task_collection_is_its_own_collection_and_refuses_other_tasks(trained, tmp_path):
    zoo = tmp_path / "zoo"
    source = trained["dir"] / "zoo-three" / "PointGoal" / PER_TASK_DIR
    (zoo / "PointGoal" / PER_TASK_DIR).mkdir(parents=True)
    for name in ("actors.msgpack", "expert.json"):
        (zoo / "PointGoal" / PER_TASK_DIR / name).write_bytes((source / name).read_bytes())
    with pytest.raises(ValueError, match=r"cover 3 of the 20 training tasks of data seed 0; tasks 3-19 have none: "
                                         r"train them \(`bati experts train --family PointGoal --per-task --tasks 3 4"):
        collect("PointGoal", "quick", root=tmp_path / "data", zoo_dir=zoo, experts="per-task", progress=False,
                workers=1, n_episodes=2, n_context_episodes=1)
    with pytest.raises(ValueError, match="trained for the 3 training tasks of data seed 0; this collection's"):
        collect("PointGoal", "quick", root=tmp_path / "data", zoo_dir=zoo, experts="per-task", progress=False,
                workers=1, n_episodes=2, n_context_episodes=1, seed=1)
    assert not (tmp_path / "data" / "PointGoal").exists() or not any((tmp_path / "data" / "PointGoal").iterdir())
    family = get_family("PointGoal")
    path = store.collection_dir(tmp_path, family, "quick", 0, 1.0, None, "per-task")
    assert path.name.endswith("-per-task-experts")
    assert "--experts" not in store.collect_command(family, "quick", 0, 1.0, tmp_path, None, "per-task")  # the default
    assert "--experts per-task" in store.collect_command(family, "quick", 1, 1.0, tmp_path, None, "per-task")
    with pytest.raises(ValueError, match="choose one of conditioned, per-task"):
        collect("PointGoal", "quick", root=tmp_path / "data", experts="per_task", progress=False)


def test_a_missing_per_task_export_names_the_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="--per-task"):
        load("PointGoal", tmp_path, "per-task")


def test_per_task_settings_are_refused_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="--tasks picks per-task experts"):
        ExpertTrainConfig("PointGoal", tasks=(0,), out_dir=tmp_path / "r").resolved()
    with pytest.raises(ValueError, match="distinct training-task indices in 0..19"):
        ExpertTrainConfig("PointGoal", per_task=True, tasks=(0, 20), out_dir=tmp_path / "r").resolved()
    with pytest.raises(ValueError, match="must exceed start_steps"):
        ExpertTrainConfig("PointGoal", per_task=True, total_steps=100, out_dir=tmp_path / "r").resolved()
    assert not (tmp_path / "r").exists()


def test_all_tasks_experts_collect_a_loadable_collection_and_have_a_card(trained, tmp_path):
    from bati.data import load_family_data
    from bati.experts.card import write_card

    zoo = trained["dir"] / "zoo-all"
    result = collect("PointGoal", "quick", root=tmp_path, zoo_dir=zoo, experts="per-task", progress=False, workers=1,
                     n_episodes=2, n_context_episodes=1)
    assert result.manifest["experts"] == "per-task" and result.manifest["settings"]["experts"] == "per-task"
    data = load_family_data("PointGoal", "quick", root=tmp_path, experts="per-task")
    assert len(data.train_tasks) == 20
    assert len(load_family_data("PointGoal", "quick", root=tmp_path).train_tasks) == 20  # the default's
    with pytest.raises(Exception, match="no PointGoal data"):  # the conditioned collection is another one
        load_family_data("PointGoal", "quick", root=tmp_path, experts="conditioned")
    card = write_card("PointGoal", zoo_dir=zoo, experts="per-task")
    assert card["experts"] == "per-task" and len(card["train_returns"]) == 20
    assert "all 20 trained as one program in" in (zoo / "PointGoal" / PER_TASK_DIR / "card.md").read_text()
    assert not (zoo / "PointGoal" / "card.md").exists()


def test_the_card_of_merged_experts_says_how_many_programs_trained_them(trained, tmp_path):
    from bati.experts.card import write_card

    zoo = tmp_path / "zoo"
    shutil.copytree(trained["dir"] / "zoo-all", zoo)
    meta_path = zoo / "PointGoal" / PER_TASK_DIR / "expert.json"
    meta_path.write_text(json.dumps({**json.loads(meta_path.read_text()), "parts": 4, "train_wall_time_s": 150.0}))
    card = write_card("PointGoal", zoo_dir=zoo, experts="per-task")
    assert card["train_parts"] == 4
    text = (zoo / "PointGoal" / PER_TASK_DIR / "card.md").read_text()
    assert "all 20 trained in 4 programs (`bati experts merge` joined them), in all 2.5 min" in text


def test_vmapped_updates_train_the_experts_the_mapped_updates_train(trained):
    from bati.experts.per_task import default_task_axis

    # the same losses and streams, one batched program instead of a loop: equal up to float rounding
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4),
                           trained["vmapped"].actors, trained["three"].actors)
    assert json.loads((trained["dir"] / "vmapped" / "config.json").read_text())["task_axis"] == "vmap"
    assert json.loads((trained["dir"] / "three" / "config.json").read_text())["task_axis"] == default_task_axis()
    assert default_task_axis("cpu") == "map" and default_task_axis("gpu") == "vmap"
    with pytest.raises(ValueError, match="task_axis='pmap'"):
        ExpertTrainConfig("PointGoal", per_task=True, task_axis="pmap").resolved()


def test_the_export_records_its_learning_curve_and_the_merge_joins_the_parts_curves(trained, tmp_path):
    from bati.experts.per_task import _merged_curve

    three = trained["three"].meta
    logged = [json.loads(line) for line in (trained["dir"] / "three" / "metrics.jsonl").read_text().splitlines()]
    assert three["eval_curve"] == {"steps": [r["steps"] for r in logged], "mean_return": [r["eval_return"] for r in logged]}
    assert three["final_eval_returns"] == logged[-1]["eval_returns"]
    a = {"tasks": [[0.0]] * 3, "eval_curve": {"steps": [10, 20, 30], "mean_return": [1.0, 2.0, 4.0]}}
    b = {"tasks": [[0.0]], "eval_curve": {"steps": [10, 20], "mean_return": [5.0, 6.0]}}
    assert _merged_curve([a, b]) == {"steps": [10, 20], "mean_return": [2.0, 3.0]}  # weighted by tasks: 3 and 1
    assert _merged_curve([a, {"tasks": [[0.0]]}]) is None


def test_a_card_says_whether_the_curve_still_rose_over_the_budgets_last_fifth():
    from bati.experts.card import learning_curve

    rising = learning_curve({"eval_curve": {"steps": [0, 50, 100], "mean_return": [0.0, 50.0, 100.0]}})
    assert rising == {"from_steps": 80, "to_steps": 100, "change": 20.0, "final": 100.0, "still_rising": True}
    flat = learning_curve({"eval_curve": {"steps": [0, 80, 100], "mean_return": [0.0, 98.0, 100.0]}})
    assert flat["change"] == pytest.approx(2.0) and not flat["still_rising"]  # 2 < 5% of 100
    assert learning_curve({}) is None


def test_per_task_contexts_draw_their_collector_among_tied_training_tasks():
    family = get_family("HalfCheetahDir")
    first = make_plan(family, 0, n_episodes=10, n_context_episodes=20)
    drawn = make_plan(family, 0, n_episodes=10, n_context_episodes=20, ties="drawn")
    train = first.train_tasks
    used = set()
    for f, d in zip(first.datasets, drawn.datasets):
        if f.split == "train":  # Eq. 9's datasets and every reset seed stay as they were
            np.testing.assert_array_equal(f.collectors, d.collectors)
            continue
        task = f.task
        wanted = -task if f.split == "p_test" else task  # the opposite direction, or the same one
        assert all(train[c] == wanted for c in d.collectors), (f.name, d.collectors)
        assert len(set(f.collectors)) == 1  # "first": one expert for every episode
        used.update(int(c) for c in d.collectors)
        np.testing.assert_array_equal(f.reset_seeds, d.reset_seeds)
    assert used == set(range(len(train)))  # every training task's expert collects some context
    point = get_family("PointGoal")  # no ties: the same plan either way
    for f, d in zip(make_plan(point, 0, 4, 2).datasets, make_plan(point, 0, 4, 2, ties="drawn").datasets):
        np.testing.assert_array_equal(f.collectors, d.collectors)
    with pytest.raises(ValueError, match="ties='last'"):
        make_plan(family, 0, 4, 2, ties="last")


def test_a_per_task_collection_by_other_experts_is_refused_not_reused(trained, tmp_path):
    zoo = tmp_path / "zoo"
    shutil.copytree(trained["dir"] / "zoo-all", zoo)
    sizes = dict(root=tmp_path / "data", zoo_dir=zoo, experts="per-task", progress=False, workers=1, n_episodes=2,
                 n_context_episodes=1)
    first = collect("PointGoal", "quick", **sizes)
    assert first.manifest["settings"]["ties"] == "drawn"
    assert collect("PointGoal", "quick", **sizes).cached
    shutil.copy(trained["dir"] / "zoo-vmapped" / "PointGoal" / PER_TASK_DIR / "actors.msgpack",
                zoo / "PointGoal" / PER_TASK_DIR / "actors.msgpack")  # retrained experts, same place
    with pytest.raises(ValueError, match="collected by other per-task experts than this bati's"):
        collect("PointGoal", "quick", **sizes)
    assert (first.path / store.MANIFEST).is_file()  # refused, nothing removed


def test_a_card_for_a_read_only_zoo_is_refused_before_any_episode(trained, tmp_path, monkeypatch):
    import os

    from bati.errors import PathError
    from bati.experts import card as card_module

    zoo = tmp_path / "zoo"
    shutil.copytree(trained["dir"] / "zoo-all", zoo)
    monkeypatch.setattr(card_module, "expert_episodes", lambda *a, **k: pytest.fail("evaluated before the check"))
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if mode & os.W_OK else real(path, mode, **kw))
    with pytest.raises(PathError, match="not writable"):
        card_module.write_card("PointGoal", zoo_dir=zoo, experts="per-task")


def test_the_default_experts_are_per_task_where_they_were_trained_for_the_tasks():
    """App. C.2's per-task experts collect by default where they exist for the collection's training tasks (data
    seed 0, the default split); elsewhere the family's one expert does, and a run records which."""
    from bati.config import TrainConfig
    from bati.envs import TaskSplit
    from bati.experts.kinds import family_experts

    point, kuhn = get_family("PointGoal"), get_family("KuhnPoker")
    assert family_experts(point) == family_experts(point, None, 0, TaskSplit()) == "per-task"
    assert family_experts(point, None, 1) == "conditioned"  # trained for seed 0's training tasks only
    assert family_experts(point, None, 0, TaskSplit(n_train=10, n_test=30)) == "conditioned"
    assert family_experts(kuhn) == "conditioned"  # exact best responses: one expert
    assert family_experts(kuhn, "conditioned") == "conditioned" and family_experts(point, "per-task", 1) == "per-task"
    with pytest.raises(ValueError, match="experts='both': choose one of conditioned, per-task"):
        family_experts(point, "both")
    assert TrainConfig(family="PointGoal").resolved().experts == "per-task"
    assert TrainConfig(family="PointGoal", data_seed=1).resolved().experts == "conditioned"
    assert TrainConfig(family="PointGoal", experts="conditioned").resolved().experts == "conditioned"
    # a record from before the setting existed ran on the task-conditioned expert's data
    assert TrainConfig.from_record({"family": "PointGoal", "method": "bati"}).resolved().experts == "conditioned"
    paths = {kind: store.collection_dir("d", point, "quick", 0, 1.0, experts=kind) for kind in (None, "conditioned")}
    assert paths[None].name == "quick-seed0-eps1-per-task-experts" and paths["conditioned"].name == "quick-seed0-eps1"
    assert store.collect_command(point, "quick", 0, 1.0, "data").endswith("--seed 0")
    assert store.collect_command(point, "quick", 0, 1.0, "data", experts="conditioned").endswith("--experts conditioned")


def test_every_output_names_the_data_by_who_collected_it():
    """A kind's name, except where the family's expert is not a SAC: Kuhn poker's data are its exact best
    responses' whatever the kind (its one expert), in live tables, reports and the results index alike."""
    from bati.config import TrainConfig
    from bati.experiments.index import Study, study_data
    from bati.experiments.sweep import cell_data
    from bati.experts.kinds import data_label, experts_label
    from pathlib import Path

    assert experts_label("per-task") == "per-task experts" and experts_label(None) == "one task-conditioned expert"
    assert data_label("per-task", "AntDir") == "per-task experts' data"
    assert data_label("conditioned", get_family("PointGoal")) == "one task-conditioned expert's data"
    assert data_label("conditioned", "KuhnPoker") == data_label("per-task", "KuhnPoker") == "exact best responses' data"
    assert data_label("per-task", "NoSuchFamily") == "per-task experts' data"  # not registered here: its kind
    assert cell_data(TrainConfig(family="KuhnPoker").resolved()) == "exact best responses"
    assert cell_data(TrainConfig(family="AntDir", experts="conditioned", episodes_per_task=50).resolved()) == \
        "one task-conditioned expert, 50 episodes per task"
    assert study_data(Study(Path("cpu/experiments/kuhn"), "", "kuhn", "cpu")) == "exact best responses' data"
    assert study_data(Study(Path("cpu/experiments/ood-tasks"), "", "ood-tasks", "cpu")) == "per-task experts' data"


def test_dpt_labels_take_each_tasks_own_expert():
    """DPT's labels on (B, T) rows of B tasks: each task's per-task expert on its rows (B actors gathered), the
    same as asking row by row; a test task's label is its most similar training task's expert's."""
    expert = load("PointGoal", kind="per-task")
    family = get_family("PointGoal")
    train, test = family.split_tasks(0)
    tasks = np.stack([family.task_to_array(t) for t in [train[3], train[7], test[0]]]).astype(np.float32)
    obs = np.random.default_rng(0).uniform(-1, 1, (3, 5, 2)).astype(np.float32)
    labels = np.asarray(jax.jit(expert.task_mean_actions)(obs, tasks))
    rows = np.asarray(expert.mean_action(obs, np.broadcast_to(tasks[:, None], (3, 5, 2))))
    np.testing.assert_allclose(labels, rows, atol=1e-6)
    own = expert.act_for_collectors(obs[0], np.full(5, 3), tasks[[0] * 5], True, jax.random.PRNGKey(0))
    np.testing.assert_allclose(labels[0], own, atol=1e-6)
