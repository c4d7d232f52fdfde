"""The paper's experiments as named specs: `bati experiment NAME --scale quick|paper`.

A spec is one or more sweep grids (its parts), the probes run on their finished cells (evaluations
of the final checkpoints under other test-time settings, e.g. Table 1's context lengths), the table
it reports (rows x columns of a record key) and the paper's own numbers for that table, typed once
here with the table or figure they come from. The specs are plain values (no JAX, no planning):
`bati.experiments.pipeline` plans and runs them, `bati.experiments.report` reports them. Experiments share one
results directory per scale (`default_out_dir`): a cell two specs have in common is trained once.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from bati.envs import MUJOCO_FAMILIES as MUJOCO
from bati.envs import TaskFamily
from bati.errors import BatiError
from bati.report.probes import Probe

SCALES = ("quick", "cpu", "paper")
MAIN_METHODS = ("bati", "bati-r", "bati-auto", "recon", "focal", "unicorn", "csro", "er-trl", "dpt", "oracle",
                "no-context")
# Beyond the paper (docs/methods.md): BATI with Eq. 8's terms weighted by calibration, beside its two fixed forms.
STATE_TERM_METHODS = ("bati", "bati-r", "bati-auto")
# The methods of the paper's ablation tables (Tables 1, 2, 5 and Figs. 5, 7), and our reward-only BATI.
ABLATION_METHODS = ("bati", "bati-r", "csro", "focal", "recon", "unicorn")
# The noise ablation adds ER-TRL (beyond the paper): its entropy term targets exactly a behaviour-shifted context.
NOISE_METHODS = ABLATION_METHODS + ("er-trl",)
DEFAULT_SEEDS = {"quick": (0,), "cpu": (0, 1, 2), "paper": (0, 1, 2, 3, 4)}
# The data question: Table 4's context encoders and BATI on data of per-task experts beside the conditioned one's.
EXPERTS_METHODS = ("bati", "bati-r", "recon", "focal", "unicorn", "csro", "oracle")
# Self-collected context: main's methods but DPT (its causal transformer reads a repeated window as a sequence).
SELF_COLLECT_METHODS = ("bati", "bati-r", "recon", "focal", "unicorn", "csro", "oracle", "no-context")


class ExperimentError(BatiError, ValueError):
    """An experiment that cannot start (unknown name or scale, contradictory overrides): nothing written."""


@dataclass(frozen=True)
class Part:
    """One sweep grid of a spec (scale and seeds are the experiment's), with the probes of its cells."""

    families: tuple[str, ...]
    methods: tuple[str, ...]
    noises: tuple[float, ...] = ()
    settings: tuple[str, ...] = ()
    probes: tuple[Probe, ...] = ()


@dataclass(frozen=True)
class PaperTable:
    """Numbers the paper reports, as printed: values[row][column] (e.g. "46.4 ± 2.9")."""

    source: str
    values: dict[str, dict[str, str]]


@dataclass(frozen=True)
class Spec:
    name: str
    title: str
    claim: str
    """What the paper concludes from it (the verdict in docs/results.md checks this)."""
    parts: tuple[Part, ...]
    rows: str = "method"
    columns: str = "family"
    """Record keys of the table: method, family, noise, split, context_length, context_mix, probe, family_probe,
    family_noise, family_experts, task_range."""
    metric: str = "p_test_return"
    paper: PaperTable | None = None
    figures: tuple[str, ...] = ("curves",)
    """curves: learning curves (p_test, p_train); vs: final metric against the column key; tsne."""
    extra_metrics: tuple[str, ...] = ()
    """More tables, of numbers a method reports itself (its eval.json's diagnostics, e.g. state_weight)."""
    scales: tuple[str, ...] = SCALES
    ours: bool = False
    """Beyond the paper: no table or figure of the paper to compare with."""
    seeds: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """Default seeds per scale where they differ from DEFAULT_SEEDS (a cheap family runs more at quick)."""
    for_family: Callable[[TaskFamily], tuple[Part, ...]] | None = None
    """The spec's parts for a family of your own (registered with `register_family`, docs/extending.md),
    where the experiment transfers to any family; None: only the paper's families."""
    likelihood_split: bool = False
    """Keep `bati likelihood`'s split of Eq. 8 (`<run>/likelihood.json`) for each finished BATI run (the trained
    model's, which BATI-R and BATI-auto share), and report it: which term of the likelihood picks the task, and
    whether it picks the collector's."""
    by_task_value: bool = False
    """Report each method's return on the test tasks of each task value, where a family's tasks take a few values
    (HalfCheetahDir: left and right): which tasks a method fails on."""


def _settings(**values) -> tuple[str, ...]:
    return tuple(f"{k}={json.dumps(v)}" for k, v in values.items())


# How the transferable experiments read on a family of your own; each rule gives the paper's own
# settings back on the paper's family (noise: AntDir 0 / 0.5 / 1 and HalfCheetahDir 0 / 0.4 / 0.8 are
# 0, eps / 2, eps; context-length: 50 / 200 / 400 are C / 4, C, 2 C; splits: AntDir's 40 tasks in quarters).
def _main_for(family: TaskFamily) -> tuple[Part, ...]:
    return (Part((family.name,), MAIN_METHODS),)


def _noise_for(family: TaskFamily) -> tuple[Part, ...]:
    eps = family.default_noise
    return (Part((family.name,), NOISE_METHODS, noises=(0.0, eps / 2, eps)),)


def _splits_for(family: TaskFamily) -> tuple[Part, ...]:
    return tuple(Part((family.name,), ABLATION_METHODS, settings=_settings(n_train_tasks=n, n_test_tasks=40 - n))
                 for n in (10, 20, 30))


def _context_length_for(family: TaskFamily) -> tuple[Part, ...]:
    c = family.default_context_length
    short = max(1, c // 4)
    return (Part((family.name,), ABLATION_METHODS, settings=_settings(context_length=short),
                 probes=tuple(Probe(eval_context_length=n) for n in (short, c, 2 * c))),)


PI = math.pi
SPECS: dict[str, Spec] = {s.name: s for s in (
    Spec(
        name="main",
        title="Table 4 with Fig. 4 (p_test) and Fig. 8 (p_train): every method on the five MuJoCo families",
        claim="BATI has the best p_test return on every family, usually by a large margin; encoders drop on p_test",
        parts=(Part(MUJOCO, MAIN_METHODS),),
        for_family=_main_for,
        likelihood_split=True,
        paper=PaperTable("Table 4", {
            "experts (Pre-IQL)": {"AntDir": "58.7", "HalfCheetahVel": "-139.3", "HalfCheetahDir": "291.2",
                       "HopperParam": "290.2", "WalkerParam": "549.2"},
            "bati": {"AntDir": "46.4 ± 2.9", "HalfCheetahVel": "-122.8 ± 1.6", "HalfCheetahDir": "286.1 ± 13.8",
                     "HopperParam": "285.9 ± 5.5", "WalkerParam": "565.2 ± 7.9"},
            "csro": {"AntDir": "28.9 ± 3.0", "HalfCheetahVel": "-134.8 ± 8.9", "HalfCheetahDir": "-340.0 ± 17.2",
                     "HopperParam": "144.4 ± 21.3", "WalkerParam": "279.5 ± 34.0"},
            "focal": {"AntDir": "-46.5 ± 2.2", "HalfCheetahVel": "-279.4 ± 9.4", "HalfCheetahDir": "-336.4 ± 8.5",
                      "HopperParam": "162.6 ± 44.5", "WalkerParam": "317.0 ± 37.0"},
            "recon": {"AntDir": "-18.3 ± 13.7", "HalfCheetahVel": "-201.8 ± 7.4", "HalfCheetahDir": "127.1 ± 258.5",
                      "HopperParam": "157.8 ± 16.7", "WalkerParam": "292.6 ± 38.4"},
            "unicorn": {"AntDir": "-32.0 ± 4.2", "HalfCheetahVel": "-267.3 ± 20.5",
                        "HalfCheetahDir": "-362.9 ± 6.8", "HopperParam": "144.7 ± 21.4",
                        "WalkerParam": "319.0 ± 11.5"},
        }),
    ),
    Spec(
        name="experts",
        title="Table 4 on HalfCheetahDir and AntDir with the data made as App. C.2 makes it (one SAC expert per "
              "training task) beside ours (one task-conditioned SAC per family)",
        claim="the encoders' collapse under p_test contexts and BATI's lead (Table 4) come with the paper's "
              "per-task experts, whose behaviour differs from task to task",
        parts=(Part(("HalfCheetahDir", "AntDir"), EXPERTS_METHODS, settings=_settings(experts="conditioned")),
               Part(("HalfCheetahDir", "AntDir"), EXPERTS_METHODS, settings=_settings(experts="per-task"))),
        columns="family_experts",
        likelihood_split=True,
        by_task_value=True,
        paper=PaperTable("Table 4 (the paper's data: per-task experts)", {
            method: {f"{family} per-task": value for family, value in row.items() if family in ("HalfCheetahDir", "AntDir")}
            for method, row in {
                "experts (Pre-IQL)": {"AntDir": "58.7", "HalfCheetahDir": "291.2"},
                "bati": {"AntDir": "46.4 ± 2.9", "HalfCheetahDir": "286.1 ± 13.8"},
                "csro": {"AntDir": "28.9 ± 3.0", "HalfCheetahDir": "-340.0 ± 17.2"},
                "focal": {"AntDir": "-46.5 ± 2.2", "HalfCheetahDir": "-336.4 ± 8.5"},
                "recon": {"AntDir": "-18.3 ± 13.7", "HalfCheetahDir": "127.1 ± 258.5"},
                "unicorn": {"AntDir": "-32.0 ± 4.2", "HalfCheetahDir": "-362.9 ± 6.8"},
            }.items()}),
    ),
    Spec(
        name="noise",
        title="Noise ablation (Fig. 5, 7 on p_test; Fig. 9, 10 on p_train): AntDir and HalfCheetahDir at three eps",
        claim="as eps grows the baselines' p_test returns fall (flat or decreasing curves) while BATI's hold",
        parts=(Part(("AntDir",), NOISE_METHODS, noises=(0.0, 0.5, 1.0)),
               Part(("HalfCheetahDir",), NOISE_METHODS, noises=(0.0, 0.4, 0.8))),
        columns="family_noise",
        figures=("curves", "vs"),
        for_family=_noise_for,
        likelihood_split=True,
    ),
    Spec(
        name="context-length",
        title="Table 1: HalfCheetahDir, eps = 0.9, trained with contexts of C = 50, evaluated with C = 50, 200, 400",
        claim="BATI improves with longer contexts (-4.7 -> 1.8 -> 4.7); the baselines do not",
        parts=(Part(("HalfCheetahDir",), ABLATION_METHODS, noises=(0.9,), settings=_settings(context_length=50),
                    probes=tuple(Probe(eval_context_length=c) for c in (50, 200, 400))),),
        columns="context_length",
        for_family=_context_length_for,
        paper=PaperTable("Table 1", {
            "bati": {"50": "-4.7 ± 1.2", "200": "1.8 ± 0.5", "400": "4.7 ± 1.5"},
            "csro": {"50": "-23.8 ± 1.0", "200": "-24.7 ± 0.7", "400": "-25.3 ± 1.1"},
            "focal": {"50": "-25.2 ± 0.2", "200": "-25.6 ± 0.3", "400": "-26.6 ± 0.2"},
            "recon": {"50": "-11.4 ± 0.2", "200": "-12.2 ± 0.3", "400": "-12.0 ± 0.2"},
            "unicorn": {"50": "-22.8 ± 2.3", "200": "-24.0 ± 1.9", "400": "-24.8 ± 2.4"},
        }),
        figures=("vs",),
    ),
    Spec(
        name="ood-tasks",
        title="Table 2: AntDir trained on directions in [0, pi), tested on [pi, 2 pi) (OOD tasks and contexts)",
        claim="BATI is the only method with a positive return (12.1 ± 0.5)",
        parts=(Part(("AntDir",), ABLATION_METHODS,
                    settings=_settings(train_task_range=[0.0, PI], test_task_range=[PI, 2 * PI])),),
        columns="family",
        paper=PaperTable("Table 2", {
            "bati": {"AntDir": "12.1 ± 0.5"}, "csro": {"AntDir": "-45.8 ± 14.5"},
            "focal": {"AntDir": "-74.7 ± 6.1"}, "recon": {"AntDir": "-51.8 ± 37.0"},
            "unicorn": {"AntDir": "-104.6 ± 9.1"},
        }),
    ),
    Spec(
        name="splits",
        title="Table 5: AntDir's 40 tasks split 10/30, 20/20, 30/10 between training and test",
        claim="BATI is best and stable across the splits",
        parts=tuple(Part(("AntDir",), ABLATION_METHODS, settings=_settings(n_train_tasks=n, n_test_tasks=40 - n))
                    for n in (10, 20, 30)),
        columns="split",
        for_family=_splits_for,
        paper=PaperTable("Table 5", {
            "bati": {"10/30": "45.0 ± 6.0", "20/20": "46.4 ± 2.9", "30/10": "49.9 ± 4.6"},
            "csro": {"10/30": "4.7 ± 4.2", "20/20": "28.9 ± 3.0", "30/10": "46.2 ± 4.8"},
            "focal": {"10/30": "-33.2 ± 3.4", "20/20": "-46.5 ± 2.2", "30/10": "-33.9 ± 1.4"},
            "recon": {"10/30": "-6.7 ± 2.8", "20/20": "-18.3 ± 13.7", "30/10": "-4.3 ± 5.0"},
            "unicorn": {"10/30": "-22.2 ± 2.5", "20/20": "-32.0 ± 4.2", "30/10": "-9.4 ± 7.6"},
        }),
        figures=("vs",),
    ),
    Spec(
        name="interpolated-contexts",
        title="Fig. 6: HalfCheetahVel, contexts of N steps with N r from p_test and N (1 - r) from p_train",
        claim="Recon's latents drift towards the spurious task and its return drops as r grows; BATI's stay put",
        parts=(Part(("HalfCheetahVel",), ("bati", "bati-r", "recon"),
                    probes=tuple(Probe(context_mix=r) for r in (0.0, 0.25, 0.5, 0.75, 1.0))),),
        columns="context_mix",
        metric="mixed_return",
        figures=("vs", "tsne"),
    ),
    Spec(
        name="noiseless-hopper",
        title="Fig. 4f: HopperParam without noise (eps = 0)",
        claim="without noise the baselines still fall short of BATI (UNICORN gains a little)",
        parts=(Part(("HopperParam",), MAIN_METHODS, noises=(0.0,)),),
    ),
    Spec(
        name="kuhn",
        title="Table 6: Kuhn poker, the learner is player 1 and a task is player 2's policy (App. D.4)",
        claim="BATI comes closest to the oracle (-0.049 vs 0.0734); every encoder is far below it (-0.18 to -0.24)",
        parts=(Part(("KuhnPoker",), MAIN_METHODS),),
        paper=PaperTable("Table 6", {
            "oracle": {"KuhnPoker": "0.0734"}, "bati": {"KuhnPoker": "-0.049 ± 0.025"},
            "csro": {"KuhnPoker": "-0.180 ± 0.032"}, "focal": {"KuhnPoker": "-0.191 ± 0.020"},
            "recon": {"KuhnPoker": "-0.185 ± 0.052"}, "unicorn": {"KuhnPoker": "-0.243 ± 0.042"},
        }),
        seeds={"quick": (0, 1, 2)},  # minutes on the CPU: three seeds fit
    ),
    Spec(
        name="state-term",
        title="Beyond the paper: BATI-auto (Eq. 8's reward and state terms weighted by how well each identifies "
              "training tasks under another task's behaviour) beside BATI (full Eq. 8) and BATI-R (reward term)",
        claim="(ours) one BATI needs no choice: on every family its p_test inference error is at most "
              "min(bati, bati-r) + 10% and its return at least max(bati, bati-r) - 5%",
        parts=(Part(("PointGoal",) + MUJOCO, STATE_TERM_METHODS),),
        extra_metrics=("state_weight",),
        ours=True,
    ),
    Spec(
        name="unknown-tasks",
        title="Beyond the paper: does a context fit no known task? The best table entry's Eq. 8 NLL as a score, "
              "on AntDir with test tasks outside ([pi, 2 pi)) and inside the training range",
        claim="(ours) contexts of out-of-range tasks score above the training tasks' (AUROC near 1), "
              "contexts of in-range test tasks do not, whoever collected them",
        parts=(Part(("AntDir",), STATE_TERM_METHODS, probes=(Probe(novelty=True),),
                    settings=_settings(train_task_range=[0.0, PI], test_task_range=[PI, 2 * PI])),
               Part(("AntDir",), STATE_TERM_METHODS, probes=(Probe(novelty=True),))),
        columns="task_range",
        metric="p_train_auroc",
        extra_metrics=("p_test_auroc", "p_train_flagged", "p_test_flagged"),
        figures=(),
        ours=True,
    ),
    Spec(
        name="refined-inference",
        title="Beyond the paper: BATI-auto's final checkpoints evaluated with Eq. 8 over N = 10, 40, 160 table "
              "samples and with 10 or 50 refining gradient steps, on PointGoal and HopperParam (where quick runs learn)",
        claim="(ours) continuous refinement from the arg-min sample finds latents between the table's "
              "entries and improves the return on test tasks that lie between training tasks",
        parts=(Part(("PointGoal", "HopperParam"), ("bati-auto",),
                    probes=(Probe(), Probe(latent_samples=10), Probe(latent_samples=160), Probe(refine_steps=10),
                            Probe(refine_steps=50))),),
        rows="family",
        columns="probe",
        ours=True,
        figures=(),
    ),
    Spec(
        name="self-collected",
        title="Beyond the paper: no given context. Each test task's policy starts from a prior latent (a random "
              "training task's) and re-infers z from its own last C = 200 transitions every k = 10 or 200 steps, "
              "for 3 episodes (z carries over), beside the given p_test / p_train contexts; HopperParam and PointGoal",
        claim="(ours) BATI's likelihood does not care who acted, so its self-collected return approaches its "
              "given-context return; an encoder meets a behaviour it was not trained on (its own policy's)",
        parts=(Part(("HopperParam", "PointGoal"), SELF_COLLECT_METHODS,
                    probes=(Probe(),) + tuple(Probe(self_collect_every=k, self_collect_episodes=3)
                                              for k in (10, 200))),),
        columns="family_probe",
        metric="self_return",
        extra_metrics=("self_ep2_return", "self_ep3_return", "p_test_return", "p_train_return",
                       "self_prior_inference_error", "self_inference_error", "p_test_inference_error"),
        ours=True,
        figures=(),
    ),
)}


def get_spec(name: str) -> Spec:
    if name not in SPECS:
        raise ExperimentError(f"unknown experiment {name!r}; choose one of: {', '.join(SPECS)} (bati experiment list)")
    return SPECS[name]


def status_file(spec: Spec) -> str:
    """The experiment's sweep record in the shared results directory."""
    return f"{spec.name}.sweep.json"


def default_out_dir(scale: str) -> Path:
    """Where experiments keep their runs: one directory per scale, so cells two experiments share (main's
    AntDir runs are the 20/20 split and the default-noise runs of `noise`) are trained once. Under the ignored
    runs/: the committed studies under results/ are written only when asked (`--out-dir results/...`), so a run
    from a checkout never takes a committed cell for its own."""
    return Path("runs") / "experiments" / scale


def default_seeds(spec: Spec, scale: str) -> tuple[int, ...]:
    return spec.seeds.get(scale, DEFAULT_SEEDS[scale])


def describe(spec: Spec, scale: str = "quick") -> dict:
    """A spec's summary for `bati experiment list` (cell counts at its default seeds)."""
    seeds = default_seeds(spec, scale)
    n_cells = 0
    for part in spec.parts:
        n_cells += len(part.families) * len(part.methods) * max(1, len(part.noises)) * len(seeds)
    n_probes = sum(len(p.families) * len(p.methods) * max(1, len(p.noises)) * len(seeds) * len(p.probes)
                   for p in spec.parts)
    return {"name": spec.name, "title": spec.title, "cells": n_cells, "probes": n_probes, "seeds": len(seeds),
            "paper": "ours" if spec.ours else spec.paper.source if spec.paper else "figures only"}

