"""An expert's card: its returns on the 20 training and 20 test tasks, and how task-specific it is.

The returns of the expert for M in M (with the family's default eps) are the paper's
"Oracle (Pre-IQL)" row. The task-specificity gap compares, on each test task M, the expert for
M with the expert for the most different training task (the p_test context collector of Eq. 10).
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from bati.envs import get_family
from bati.envs.rollout import Episodes, rollout
from bati.experts.kinds import ExpertsKind, family_experts
from bati.experts.zoo import ZOO_DIR, Expert, load_for
from bati.io import atomic_write_json, atomic_write_text, check_directory, code_record

HALF_CHEETAH_CONTROL_COST = 0.05
PAPER_ORACLE = {"AntDir": 58.7, "HalfCheetahVel": -139.3, "HalfCheetahDir": 291.2, "HopperParam": 290.2,
                "WalkerParam": 549.2}
"""Table 4's "Oracle (Pre-IQL)" row: the paper's experts' own return on the test tasks."""


def expert_episodes(expert: Expert, env_tasks, policy_tasks, noise, seed, collectors=None) -> Episodes:
    """One deterministic episode per env task, acting as the expert for the matching policy task (or, with
    `collectors`, as the expert of those training tasks: per-task experts run expert `collectors[k]`)."""
    family = expert.family
    task_arrays = np.stack([family.task_to_array(t) for t in policy_tasks])
    key = jax.random.PRNGKey(seed)
    if collectors is None:
        act = lambda obs, _: expert.act_from_arrays(obs, task_arrays, True, key)
    else:
        act = lambda obs, _: expert.act_for_collectors(obs, np.asarray(collectors), task_arrays, True, key)
    return rollout(family, env_tasks, act, noise=noise, seed=seed)


def test_task_experts(family, train: list, test: list, seed: int, drawn: bool) -> tuple[list[int], list[int]]:
    """Per test task, the training task whose expert is the most different one and the one whose expert acts for
    it. Among tied training tasks (HalfCheetahDir's directions) the first, or with `drawn` (per-task experts,
    which differ among tied tasks, as their collections draw them: `bati.data.plan`) one drawn per test task."""
    from bati.data.plan import tied

    rng = np.random.default_rng([seed, CARD_TIES_STREAM])
    pick = (lambda c: int(rng.choice(c))) if drawn else (lambda c: int(c[0]))
    different = [pick(tied(family, t, train, farthest=True)) for t in test]
    similar = [pick(tied(family, t, train, farthest=False)) for t in test]
    return different, similar


CARD_TIES_STREAM = 0xCA4D


def learning_curve(meta: dict) -> dict | None:
    """Whether an expert's training curve was still rising at its budget, from the evaluations its export
    records (`eval_curve`: steps and mean evaluation return): the change of the mean return over the last
    fifth of the budget, and "rising" where it is more than RISING of the final return's size (None: not
    recorded, exports from before curves were kept)."""
    curve = meta.get("eval_curve")
    if not curve or len(curve["steps"]) < 2:
        return None
    steps, returns = np.asarray(curve["steps"], float), np.asarray(curve["mean_return"], float)
    start = steps[-1] * 0.8
    before = float(np.interp(start, steps, returns))
    change = float(returns[-1] - before)
    rising = change > RISING * max(abs(float(returns[-1])), 1e-9)
    return {"from_steps": int(start), "to_steps": int(steps[-1]), "change": change, "final": float(returns[-1]),
            "still_rising": bool(rising)}


RISING = 0.05
"""A curve whose mean evaluation return grew by more than 5% of its final value over the budget's last fifth
is still rising (not converged)."""


def write_card(family_name: str, seed: int = 0, zoo_dir: str | Path | None = None,
               experts: ExpertsKind | None = None) -> dict:
    """Evaluate the expert of `family_name` (or its per-task experts) and write card.json / card.md next to it.
    Per-task experts: the expert for training task i is expert i, for a test task the most similar training
    task's (App. C.2; among tied ones, one drawn per test task), and the card lies in the experts' own
    directory."""
    family = get_family(family_name)
    if family.discrete_actions:  # nothing shipped to describe: its values are exact (docs/environments.md)
        raise ValueError(f"{family_name}'s expert is the exact best response, computed, not shipped: it has no "
                         "card; its exact values per hand are bati.envs.kuhn.best_response_value")
    experts = family_experts(family, experts, seed)
    expert = load_for(family, zoo_dir, experts)
    directory = Path(zoo_dir or ZOO_DIR) / family_name
    train, test = family.split_tasks(seed)
    if experts == "per-task":
        from bati.experts.per_task import PER_TASK_DIR

        expert.check_tasks(train)
        directory = directory / PER_TASK_DIR
    check_directory(directory, "the expert's directory (its card goes beside it)", package=zoo_dir is None)
    different, similar = test_task_experts(family, train, test, seed, drawn=experts == "per-task")
    wrong = [train[j] for j in different]
    noise = family.default_noise

    own = expert_episodes(expert, train + test, train + test, noise, seed=1000 + seed,
                          collectors=list(range(len(train))) + similar)
    against = expert_episodes(expert, test, wrong, noise, seed=1000 + seed + len(train), collectors=different)
    own_test = own.returns[len(train):]
    card = {
        "family": family_name,
        "experts": experts,
        "split_seed": seed,
        "eval_noise": noise,
        "train_steps": expert.meta.get("train_steps", expert.meta.get("train_steps_per_task")),
        "train_wall_time_s": expert.meta["train_wall_time_s"],
        "train_parts": expert.meta.get("parts", 1),
        "learning_curve": learning_curve(expert.meta),
        "paper_oracle": PAPER_ORACLE.get(family_name),
        "train_tasks": train,
        "test_tasks": test,
        "train_returns": own.returns[: len(train)].tolist(),
        "test_returns": own_test.tolist(),
        "train_returns_noise_free": own.noise_free_returns[: len(train)].tolist(),
        "test_returns_noise_free": own.noise_free_returns[len(train):].tolist(),
        "oracle_test_return": float(own_test.mean()),
        "oracle_train_return": float(own.returns[: len(train)].mean()),
        "most_different_expert_test_return": float(against.returns.mean()),
        "task_specificity_gap": float(own_test.mean() - against.returns.mean()),
        **code_record(),
    }
    if family_name == "HalfCheetahVel":
        # noise-free reward = -|v - v*| - 0.05 |a|^2, so |v - v*| is recovered exactly.
        control = HALF_CHEETAH_CONTROL_COST * np.sum(own.actions**2, axis=-1)
        velocity_error = -(own.noise_free_rewards + control)
        card["velocity_error_mean"] = float(velocity_error[:, 50:].mean())
    card["summary"] = _summary(card)
    atomic_write_json(directory / "card.json", card)
    atomic_write_text(directory / "card.md", _markdown(card))
    return card


def _summary(card: dict) -> str:
    text = (
        f"{card['family']}: oracle return (test tasks, eps={card['eval_noise']:g}) "
        f"{card['oracle_test_return']:.1f}; most-different expert {card['most_different_expert_test_return']:.1f}; "
        f"gap {card['task_specificity_gap']:.1f}"
    )
    if "velocity_error_mean" in card:
        text += f"; mean |v - v*| after step 50: {card['velocity_error_mean']:.3f}"
    return text


def _markdown(card: dict) -> str:
    rows = "\n".join(
        f"| {kind} | {i} | {_fmt(task)} | {ret:.1f} | {free:.1f} |"
        for kind, tasks, rets, frees in (
            ("train", card["train_tasks"], card["train_returns"], card["train_returns_noise_free"]),
            ("test", card["test_tasks"], card["test_returns"], card["test_returns_noise_free"]),
        )
        for i, (task, ret, free) in enumerate(zip(tasks, rets, frees))
    )
    per_task = card.get("experts") == "per-task"
    parts = card.get("train_parts", 1)
    how = ("as one program in" if parts == 1
           else f"in {parts} programs (`bati experts merge` joined them), in all")
    what = (f"One SAC per training task (App. C.2), {card['train_steps']:,} environment transitions each, all "
            f"{len(card['train_tasks'])} trained {how} {card['train_wall_time_s'] / 60:.1f} min"
            if per_task else f"Task-conditioned SAC, {card['train_steps']:,} environment transitions, "
            f"{card['train_wall_time_s'] / 60:.1f} min of training")
    flag = " --experts per-task" if per_task else ""
    return f"""# Expert card: {card['family']}{' (per-task experts)' if per_task else ''}

{what} on this project's 2-core CPU machine.
Evaluated with `bati experts card --family {card['family']} --seed {card['split_seed']}{flag}` at commit
`{card['commit']}` (deterministic actions, one episode per task, eps = {card['eval_noise']:g}).

**{card['summary']}**

- Oracle (Pre-IQL) return: test tasks {card['oracle_test_return']:.1f}, training tasks {card['oracle_train_return']:.1f}{_paper(card)}
- Budget: {card['train_steps']:,} transitions{' per task' if per_task else ''}; {_curve(card)}
- On each test task M, the expert for the most different training task (the p_test collector)
  earns {card['most_different_expert_test_return']:.1f}: a gap of {card['task_specificity_gap']:.1f}.

| split | # | task | return (eps) | noise-free return |
| --- | --- | --- | --- | --- |
{rows}
"""


def _paper(card: dict) -> str:
    paper = card.get("paper_oracle")
    return "" if paper is None else f" (the paper's Table 4: {paper:.1f})"


def _curve(card: dict) -> str:
    curve = card.get("learning_curve")
    if curve is None:
        return "training curve not recorded with the export"
    state = "still rising (not converged)" if curve["still_rising"] else "flat (within 5% of its final value)"
    return (f"mean evaluation return (eps 0, own tasks) {curve['change']:+.1f} over the last fifth "
            f"({curve['from_steps']:,} -> {curve['to_steps']:,}), final {curve['final']:.1f}: {state}")


def _fmt(task) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in task) + "]" if isinstance(task, list) else f"{task:.3f}"
