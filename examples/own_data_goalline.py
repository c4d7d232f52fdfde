"""docs/own-data.md end to end: build the GoalLine Minari dataset, train methods on it, tabulate.

    python examples/own_data_goalline.py [--out runs/own-data/goalline] [--steps 3000] [--seeds 0 1 2]

Writes OUT/minari/ (the dataset), OUT/runs/<method>-seed<s>/ (one `bati train --datasets ... --eval-env
GoalLine-v0` run each, resumable) and OUT/report.md (held-out task-inference accuracy, representation loss
and return in the env on held-out contexts, mean and std over seeds, with the command, commit, device and
wall time).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

GOALS = (-0.8, -0.3, 0.3, 0.8)
METHODS = ("bati", "bati-r", "recon", "focal", "unicorn", "csro", "oracle", "no-context")


class GoalLine(gym.Env):
    """Reach a goal on a line from -1.5 or 1.5; the episode terminates within 0.05 of the goal."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-2.0, 2.0, (1,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.goal = float(options["goal"])
        self.x = np.array([self.np_random.choice([-1.5, 1.5])], np.float32)
        return self.x.copy(), {}

    def step(self, action):
        self.x = np.clip(self.x + 0.1 * np.clip(action, -1, 1), -2, 2).astype(np.float32)
        distance = abs(float(self.x[0]) - self.goal)
        return self.x.copy(), -distance, distance < 0.05, False, {}


# the env, registered with its time limit: `--eval-env GoalLine-v0` measures returns in it
gym.register("GoalLine-v0", entry_point=GoalLine, max_episode_steps=40)


def build(root: Path, episodes: int) -> Path:
    """The dataset goalline/mixed-v0 under `root` (built once): `episodes` per goal, the goal in each
    episode's reset options. Returns its directory."""
    from minari import DataCollector

    root = Path(root).resolve()  # Minari mishandles a relative MINARI_DATASETS_PATH
    path = root / "goalline" / "mixed-v0"
    if path.is_dir():
        return path
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        _collect(DataCollector(gym.wrappers.TimeLimit(GoalLine(), max_episode_steps=40)), episodes)
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH")
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous
    return path


def _collect(env, episodes: int) -> None:
    rng = np.random.default_rng(0)
    for goal in GOALS:
        for _ in range(episodes):
            obs, _ = env.reset(seed=int(rng.integers(1 << 30)), options={"goal": goal})
            done = False
            while not done:  # a noisy behaviour: head for the goal half of the time
                action = np.sign([goal - obs[0]]) if rng.random() < 0.5 else rng.uniform(-1, 1, 1)
                obs, _, terminated, truncated, _ = env.step(np.asarray(action, np.float32))
                done = terminated or truncated
    env.create_dataset(dataset_id="goalline/mixed-v0", algorithm_name="noisy scripted", author="bati",
                       description="docs/own-data.md's GoalLine: 4 goals, a noisy scripted behaviour")


def main() -> None:
    parser = argparse.ArgumentParser(description="docs/own-data.md end to end: the GoalLine Minari dataset, "
                                     f"{', '.join(METHODS)} trained on it, one report.",
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/own-data/goalline"),
                        help="where the dataset, runs and report go (the committed study: results/own-data/goalline)")
    parser.add_argument("--steps", type=int, default=3000, help="gradient steps of each run")
    parser.add_argument("--episodes", type=int, default=30, help="episodes per goal in the dataset")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds of each method")
    args = parser.parse_args()
    from bati.cli import main as bati
    from bati.io import atomic_write_text, git_commit
    from bati.device import describe_device

    start = time.perf_counter()
    dataset = build(args.out / "minari", args.episodes)
    rows = []
    for method in METHODS:
        code = bati(["train", "--datasets", str(dataset), "--task-key", "goal", "--eval-env", "GoalLine-v0",
                     "--method", method,
                     "--context-length", "10", "--task-batch", "4", "--steps", str(args.steps),
                     "--seeds", *map(str, args.seeds), "--out-dir", str(args.out / "runs")])
        if code != 0:
            sys.exit(code)
        summaries = [json.loads((args.out / "runs" / f"{method}-seed{s}" / "eval.json").read_text())
                     for s in args.seeds]
        acc = np.array([s["held_out_inference_accuracy"] for s in summaries])
        loss = np.array([s["held_out_representation_loss"] for s in summaries])
        ret = np.array([s["held_out_return"] for s in summaries])
        rows.append(f"| {method} | {acc.mean():.2f} ± {acc.std():.2f} | {loss.mean():.3f} ± {loss.std():.3f} | "
                    f"{ret.mean():.2f} ± {ret.std():.2f} |")
    data = summaries[0]["data"]
    data_return = np.mean([t["episode_return_mean"] for t in data["tasks"]])
    text = "\n".join([
        "# GoalLine (docs/own-data.md): diagnostics and returns on your own data",
        "",
        f"`python examples/own_data_goalline.py --steps {args.steps} --episodes {args.episodes} --seeds "
        f"{' '.join(map(str, args.seeds))}` at commit {git_commit()}, {describe_device()}, "
        f"{(time.perf_counter() - start) / 60:.1f} min. {len(GOALS)} tasks (goals {list(GOALS)}), "
        f"{args.episodes} episodes each; {data.get('transitions')} of {data.get('transitions_read')} transitions "
        "kept as segments of 10; 20% of each task's segments held out. Mean ± std over seeds of the last 5 "
        "evaluations; chance accuracy 0.25. Return: one episode in GoalLine-v0 per held-out context (8 per "
        f"task), acting on that context's latent; the data's own episodes average {data_return:.2f} "
        "(the noisy behaviour that recorded it).",
        "",
        "| method | held-out inference accuracy | held-out representation loss | return in the env |",
        "| --- | --- | --- | --- |",
        *rows,
        "",
    ])
    atomic_write_text(args.out / "report.md", text)
    print(text)


if __name__ == "__main__":
    main()
