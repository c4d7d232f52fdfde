"""The paper's claims, each decided by rliable intervals over the committed runs: `bati claims`.

A claim names the experiment whose cells test it and a test: a function of those cells' records at
one scale that returns the evidence (numbers with 95% stratified-bootstrap intervals) and a verdict.
Every scale present under `results/` is read (`SOURCES`): the quick scale, 4x its steps, the cpu
scale and the paper scale. A ranking is called only with at least `MIN_SEEDS` seeds per method; with
fewer, the numbers are shown and the verdict is "not tested". The claim's verdict is the one at the
largest scale that tests it on the paper's data (per-task experts; `deciding`), or, where none does yet, on
one task-conditioned expert's. Scores are normalised returns, (return - random) / (experts - random),
where the runs record the references (the MuJoCo families and Kuhn poker), else raw returns.

Verdicts: `reproduced` (every interval decides for the paper, on every family the claim names), `partly`
(some do, or all do on only some of the families), `not reproduced` (none does: the intervals include chance or
decide against it), `not tested`. The page's table gives the verdict at every tested scale beside the largest's,
and whether the cells a claim compares are converged there (how many still move); the claim's section names
each cell whose p_test still drifts over its scored window (bati.report.convergence), since a verdict that rests
on it may change with more steps.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bati.envs import FamilyUnavailable, get_family
from bati.experiments.specs import CONDITIONED, MUJOCO
from bati.experts.kinds import data_label
from bati.io import short_commit
from bati.report.convergence import NEGLIGIBLE, drift_interval, drift_verdict, run_drift
from bati.report.probes import read_probe
from bati.report.runs import jobs_wall_time
from bati.report.stats import BOOTSTRAP_REPS, improvement_interval, iqm_interval, require_rliable
from bati.report.stored_plan import PLAN_FILE, StoredPlan, read_plan

MIN_SEEDS = 3
REPS = BOOTSTRAP_REPS
"""Bootstrap replicates of every interval on the page."""
BASELINES = ("focal", "csro", "unicorn", "recon", "dpt")
"""The paper's baselines (Table 4); the oracle, no-context and our BATI variants are not compared."""


@dataclass(frozen=True)
class Source:
    """One scale's results: where its experiments ran and the settings they ran with."""

    label: str
    out_dir: Path
    scale: str
    settings: tuple[str, ...] = ()
    data: str = ""
    """Short name of data other than the default (the paper's: per-task experts where the family has them,
    docs/data.md): the task-conditioned expert's (`CONDITIONED_DATA`), which decides a claim only where the
    default data has no cells for it, or another setting, whose verdicts only stand beside (`every_scale`)."""
    reports: tuple[tuple[str, str], ...] = ()
    """(a claim's experiment, the experiment whose report holds its cells here) where they differ: a folder that
    ran the `experts` study holds `main`'s cells of its families."""
    experts: str = ""
    """Keep only the cells of this experts kind (a study of both kinds' data: `experts`)."""


CONDITIONED_DATA = data_label("conditioned")  # "one task-conditioned expert's data"
"""`Source.data` of the task-conditioned expert's cells: they decide a claim only where no cells of the default
data do (`overall`)."""

SOURCES = (
    Source("quick (3k steps, 20 episodes per task, one task-conditioned expert's data)", Path("results/quick/experiments"),
           "quick", (CONDITIONED,), data=CONDITIONED_DATA),
    Source("12k (4x quick steps, quick data: one task-conditioned expert's)", Path("results/quick/locomotion-12k"), "quick",
           ("steps=12000", CONDITIONED), data=CONDITIONED_DATA),
    Source("cpu (one task-conditioned expert's data at the paper's sizes, 100k steps, batch 16 x 64, IQL 128x128)",
           Path("results/cpu/experiments"), "cpu", (CONDITIONED,), data=CONDITIONED_DATA),
    Source("paper (one task-conditioned expert's data at the paper's sizes, 100k steps, batch 16 x 256, IQL 256x256)",
           Path("results/paper/experiments"), "paper", (CONDITIONED,), data=CONDITIONED_DATA),
    # the default data, the paper's (App. C.2): one SAC expert per training task where the family has them
    Source("cpu (the paper's data: one SAC expert per training task, App. C.2; 100k steps, batch 16 x 64, IQL 128x128)",
           Path("results/cpu/experiments"), "cpu"),
    Source("paper (the paper's data: one SAC expert per training task, App. C.2; 100k steps, batch 16 x 256, "
           "IQL 256x256)", Path("results/paper/experiments"), "paper"),
    # HalfCheetahDir's per-task cells on its first experts (40k transitions each, a third of the paper's Oracle)
    Source("cpu, per-task experts of 40k transitions (HalfCheetahDir's first experts, since retrained)",
           Path("results/cpu/experts-40k"), "cpu", data="per-task experts, 40k", reports=(("main", "experts"),),
           experts="per-task"),
    Source("cpu, Table 3's dataset size read in total (50 episodes per training task), our expert's data",
           Path("results/cpu/total-data"), "cpu", ("episodes_per_task=50",), data="total size",
           reports=(("main", "experts"),), experts="conditioned"),
    Source("cpu, Table 3's dataset size read in total (50 episodes per training task), per-task experts' data "
           "(HalfCheetahDir's 40k experts)",
           Path("results/cpu/total-data"), "cpu", ("episodes_per_task=50",),
           data="total size, per-task experts, 40k", reports=(("main", "experts"),), experts="per-task"),
)


@dataclass
class Record:
    """One finished cell (or one probe of it): normalised scores where the run has references."""

    method: str
    family: str
    noise: float
    seed: int
    p_test: float
    p_train: float
    p_test_return: float
    context_length: int | None
    commit: str | None
    device: str | None
    wall_time_s: float
    job: str = ""
    """What shares its wall time: the seeds of one training job (one setting and method), or one probe."""
    drift: float = math.nan
    """The run's p_test drift over its scored window (bati.report.convergence): ~0 when converged."""
    normalised: bool = False
    """Whether its scores (and drift) are normalised: the run records reference returns."""

    @property
    def change(self) -> float:
        """p_test - p_train: how much the score falls when another policy collected the context."""
        return self.p_test - self.p_train


def source_plan(spec_name: str, source: Source, root: Path) -> StoredPlan | None:
    """The experiment's plan at a source's scale and data, as its report stored it (`bati.report.stored_plan`): of
    the report folders in the source's directory, the one whose plan has the source's settings, a method's own
    settings (`csro.club_negatives=...`) aside; of several, the one with the fewest of those (the experiment's
    report before a variant's, e.g. ER-TRL with an unbounded latent)."""
    experiment = dict(source.reports).get(spec_name, spec_name)
    found = []
    for path in sorted((root / source.out_dir).glob(f"*/{PLAN_FILE}")):
        plan = read_plan(path.parent)
        if plan.experiment == experiment and plan.scale == source.scale and \
                _data_settings(plan.settings) == _data_settings(source.settings):
            found.append(plan)
    return min(found, key=lambda plan: len(plan.settings), default=None)


def _raw(value):
    """A score where the run records no reference returns: its return as it is."""
    return value


def _data_settings(settings: tuple[str, ...]) -> tuple[str, ...]:
    """The settings that apply to every method (a method's own, `section.key=value`, aside), sorted."""
    return tuple(sorted(s.replace(" ", "") for s in settings if "." not in s.partition("=")[0]))


def gather(spec_name: str, source: Source, root: Path) -> list[Record]:
    """The records of the experiment's finished cells (and of their probes) at one scale and data."""
    plan = source_plan(spec_name, source, root)
    records = []
    for cell in plan.cells if plan is not None else ():
        if source.experts and cell.experts != source.experts:
            continue
        run = cell.result()
        if run is None:
            continue
        score = run.normalised if run.reference_returns else _raw
        training = (run.total_wall_time(), f"{cell.run_dir.parent}/{cell.method}")
        results = [(run.p_test_return, run.p_train_return, cell.eval_context_length, run.commit, *training)]
        if cell.probes:
            results = [(p["p_test_return"], p["p_train_return"], p["context_length"], p.get("commit"),
                        p.get("wall_time_s"), f"{cell.run_dir}/{p['context_length']}")
                       for p in (read_probe(cell.run_dir, probe) for probe in cell.probes)
                       if p is not None and "p_test_return" in p]
            if results:  # the first probe's record carries the run's training (its own seconds are ~1% of it)
                results[0] = (*results[0][:4], *training)
        drift = run_drift(run)  # a probe evaluates its cell's training run: the cell's drift
        for p_test, p_train, length, commit, wall, job in results:
            records.append(Record(cell.method, cell.family, cell.noise, cell.seed, score(p_test), score(p_train),
                                  p_test, length, commit, run.machine, wall or 0.0, job, drift,
                                  bool(run.reference_returns)))
    return records


# --- the tests ----------------------------------------------------------------------------------
def _scores(records: list[Record], method: str, family: str, key: str = "p_test", **where) -> np.ndarray:
    return np.array([getattr(r, key) for r in records if r.method == method and r.family == family
                     and all(getattr(r, k) == v for k, v in where.items()) and math.isfinite(getattr(r, key))])


def _seeds_ok(*arrays) -> bool:
    return all(len(a) >= MIN_SEEDS for a in arrays)


def _p(x, y) -> tuple[float, float, float]:
    return improvement_interval(x, y, reps=REPS)


def _fmt_p(p: tuple[float, float, float]) -> str:
    return f"{p[0]:.2f} [{p[1]:.2f}, {p[2]:.2f}]"


def _decides(p: tuple[float, float, float]) -> int:
    """+1 when the interval lies above 1/2 (X better), -1 below (Y better), 0 when it holds 1/2."""
    return 1 if p[1] > 0.5 else -1 if p[2] < 0.5 else 0


@dataclass
class Tally:
    """Which of a claim's comparisons decide for the paper (`holds`), which intervals hold chance (`undecided`)
    and which decide against it: a "partly" names them."""

    holds: list[str] = field(default_factory=list)
    undecided: list[str] = field(default_factory=list)
    against: list[str] = field(default_factory=list)

    def add(self, name: str, decision: int) -> int:
        {1: self.holds, 0: self.undecided, -1: self.against}[decision].append(name)
        return decision

    def text(self) -> str:
        parts = [(label, names) for label, names in (("holds", self.holds), ("undecided", self.undecided),
                                                    ("against", self.against)) if names]
        return "; ".join(f"{label}: {', '.join(names)}" for label, names in parts)

    def counts(self) -> str:
        return ", ".join(f"{len(names)} {label}" for label, names in (
            ("hold", self.holds), ("undecided", self.undecided), ("against", self.against)) if names)


def _verdict(decisions: list[int], wanted: int) -> str:
    if not decisions:
        return "not tested"
    hits = sum(d == 1 for d in decisions)
    return "reproduced" if hits == wanted else "partly" if hits else "not reproduced"


def _stratified(records, method, families, key="p_test", **where) -> np.ndarray | None:
    """A (runs, families) matrix (the first n runs of each family, n the fewest), None without runs."""
    columns = [_scores(records, method, f, key, **where) for f in families]
    n = min((len(c) for c in columns), default=0)
    return np.stack([c[:n] for c in columns], axis=1) if n else None


def best_on_p_test(records: list[Record], families: tuple[str, ...],
                   baselines: tuple[str, ...] = BASELINES, method: str = "bati") -> tuple[list[str], str]:
    """C1 / C7 / C8 / C9: per family, P(method > baseline) on p_test for every baseline that ran (method: BATI,
    or C9's BATI-R)."""
    name = method.upper()
    lines, decisions, tested, tally = [], [], 0, Tally()
    for family in families:
        subject = _scores(records, method, family)
        parts, family_decisions = [], []
        for baseline in baselines:
            other = _scores(records, baseline, family)
            if not len(other) or not len(subject):
                continue
            if not _seeds_ok(subject, other):
                parts.append(f"{baseline} {other.mean():.2f} ({len(other)} seed(s))")
                continue
            p = _p(subject, other)
            family_decisions.append(tally.add(f"{baseline} on {family}", _decides(p)))
            parts.append(f"P({name} > {baseline}) {_fmt_p(p)}")
        if not parts:
            continue
        lead = f"{name} {subject.mean():.2f}" if len(subject) else f"{name}: no run"
        lines.append(f"{family}: {lead} ({len(subject)} seed(s)); " + "; ".join(parts))
        if family_decisions:
            tested += 1
            decisions.append(1 if all(d == 1 for d in family_decisions) else -1 if -1 in family_decisions else 0)
    if tested < len(families):
        return lines, "not tested" if not tested else _partial(decisions), tally
    return lines, _verdict(decisions, len(families)), tally


def _partial(decisions: list[int]) -> str:
    return "partly" if any(d == 1 for d in decisions) else "not reproduced"


def fall_on_p_test(records: list[Record], families: tuple[str, ...]) -> tuple[list[str], str]:
    """C2: a baseline's p_test - p_train (normalised) against BATI's, stratified over the families where both have
    MIN_SEEDS seeds (a family with fewer is named, not pooled: it would cut every family to its seeds)."""
    lines, decisions, covered, tally = [], [], set(), Tally()
    for baseline in BASELINES:
        ran = _both(records, ("bati", baseline), families)
        both = _both(records, ("bati", baseline), families, MIN_SEEDS) or ran
        if not both:
            continue
        bati, other = _stratified(records, "bati", both, "change"), _stratified(records, baseline, both, "change")
        counted = f"{len(both)} {'family' if len(both) == 1 else 'families'}"
        if len(both) < len(families):
            counted += ": " + ", ".join(both)
        levels = {m: tuple(_stratified(records, m, both, key).mean() for key in ("p_train", "p_test"))
                  for m in ("bati", baseline)}
        head = (f"{baseline} ({counted}): p_train {levels[baseline][0]:.2f} -> p_test {levels[baseline][1]:.2f} "
                f"(change {other.mean():+.2f}) vs BATI {levels['bati'][0]:.2f} -> {levels['bati'][1]:.2f} "
                f"({bati.mean():+.2f})")
        if not _seeds_ok(bati, other):
            lines.append(head + f" ({min(len(bati), len(other))} seed(s) per family)")
            continue
        if len(both) < len(ran):
            head += f" (not pooled, fewer than {MIN_SEEDS} seeds: {', '.join(f for f in ran if f not in both)})"
        p = _p(bati, other)
        decisions.append(tally.add(baseline if len(both) == len(families) else f"{baseline} on {', '.join(both)}",
                                   _decides(p)))
        covered.update(both)
        train = _p(_stratified(records, "bati", both, "p_train"), _stratified(records, baseline, both, "p_train"))
        lines.append(head + f"; P(BATI falls less) {_fmt_p(p)}; on p_train P(BATI > {baseline}) {_fmt_p(train)}")
    if decisions and len(covered) < len(families):  # a claim about every family holds at most partly on some
        return lines, _partial(decisions), tally
    return lines, _verdict(decisions, len(decisions)), tally


def _both(records: list[Record], methods: tuple[str, ...], families: tuple[str, ...], seeds: int = 1) -> tuple[str, ...]:
    """The families on which every one of `methods` has runs of at least `seeds` seeds."""
    return tuple(f for f in families if all(len(_scores(records, m, f)) >= seeds for m in methods))


def recon_below(records: list[Record], families: tuple[str, ...]) -> tuple[list[str], str]:
    """C3: P(BATI > Recon) on p_test family by family, as C1 and C8 decide theirs (Table 4 ranks per family), and
    the pooled figure over the families where both have MIN_SEEDS seeds (stratified) as one more line; the
    per-family intervals decide."""
    lines, verdict, tally = best_on_p_test(records, families, ("recon",))
    both = _both(records, ("bati", "recon"), families, MIN_SEEDS)
    if len(both) > 1:
        bati, recon = _stratified(records, "bati", both), _stratified(records, "recon", both)
        lines.append(f"pooled over {', '.join(both)}: BATI {bati.mean():.2f}, Recon {recon.mean():.2f}; "
                     f"stratified P(BATI > Recon) {_fmt_p(_p(bati, recon))}")
    return lines, verdict, tally


def noise_hurts_baselines(records: list[Record], families: tuple[str, ...]) -> tuple[list[str], str]:
    """C4: the change of p_test from eps = 0 to the largest eps, BATI's against each baseline's."""
    lines, decisions, bati_holds, covered, tally = [], [], [], set(), Tally()
    for family in families:
        levels = sorted({r.noise for r in records if r.family == family})
        if len(levels) < 2:
            continue
        low, high = levels[0], levels[-1]

        def change(method):
            a = {r.seed: r.p_test for r in records if (r.method, r.family, r.noise) == (method, family, low)}
            b = {r.seed: r.p_test for r in records if (r.method, r.family, r.noise) == (method, family, high)}
            return np.array([b[s] - a[s] for s in sorted(a.keys() & b.keys())])

        bati = change("bati")
        if not len(bati):
            continue
        parts = []
        if _seeds_ok(bati):
            value, lo, hi = iqm_interval(bati, reps=REPS)
            bati_holds.append(hi >= 0.0)
            tally.add(f"BATI holds on {family}", 1 if hi >= 0.0 else -1)
            parts.append(f"BATI eps {low:g} -> {high:g}: {value:+.2f} [{lo:+.2f}, {hi:+.2f}]")
        else:
            parts.append(f"BATI eps {low:g} -> {high:g}: {bati.mean():+.2f} ({len(bati)} seed(s))")
        reward_only = change("bati-r")  # BATI's reward-only likelihood: beside BATI, not a verdict input
        if _seeds_ok(reward_only):
            value, lo, hi = iqm_interval(reward_only, reps=REPS)
            parts.append(f"(BATI-R, not a baseline: {value:+.2f} [{lo:+.2f}, {hi:+.2f}])")
        for baseline in BASELINES:
            other = change(baseline)
            if not len(other):
                continue
            if _seeds_ok(bati, other):
                p = _p(bati, other)
                decisions.append(tally.add(f"{baseline} on {family}", _decides(p)))
                covered.add(family)
                parts.append(f"{baseline} {other.mean():+.2f}, P(BATI changes less) {_fmt_p(p)}")
            else:
                parts.append(f"{baseline} {other.mean():+.2f} ({len(other)} seed(s))")
        lines.append(f"{family}: " + "; ".join(parts))
    if not decisions:
        return lines, "not tested", tally
    wins = sum(d == 1 for d in decisions)
    if wins == len(decisions) and all(bati_holds) and len(covered) == len(families):
        return lines, "reproduced", tally
    return lines, "partly" if wins or any(bati_holds) else "not reproduced", tally


def longer_contexts_help(records: list[Record], families: tuple[str, ...]) -> tuple[list[str], str]:
    """C5: P(return at the longest context > at the shortest) for BATI, beside the baselines."""
    lengths = sorted({r.context_length for r in records if r.context_length is not None})
    if len(lengths) < 2:
        return [], "not tested", Tally()
    short, long = lengths[0], lengths[-1]
    lines, verdict, tally = [], "not tested", Tally()
    for method in ("bati",) + BASELINES:
        a = _scores(records, method, families[0], "p_test_return", context_length=short)
        b = _scores(records, method, families[0], "p_test_return", context_length=long)
        if not len(a) or not len(b):
            continue
        means = " -> ".join(f"{_scores(records, method, families[0], 'p_test_return', context_length=n).mean():.2f}"
                            for n in lengths)
        if _seeds_ok(a, b):
            p = _p(b, a)
            lines.append(f"{method} C = {' / '.join(map(str, lengths))}: {means}; P(C={long} > C={short}) {_fmt_p(p)}")
            if method == "bati":
                decision = tally.add(f"BATI C={long} > C={short}", _decides(p))
                verdict = {1: "reproduced", 0: "not reproduced", -1: "not reproduced"}[decision]
        else:
            lines.append(f"{method} C = {' / '.join(map(str, lengths))}: {means} ({len(a)} seed(s))")
    return lines, verdict, tally


def only_bati_positive(records: list[Record], families: tuple[str, ...]) -> tuple[list[str], str, Tally]:
    """C6: the IQM p_test return (raw: its sign is the claim) of BATI above 0 and of every other method that ran
    below it. BATI's own test-time rules (BATI-R, BATI-auto) and the oracle (it is told the task) are shown, not
    counted. A counted method whose interval lies above 0 refutes "only"; one whose interval holds 0, or with
    fewer than MIN_SEEDS seeds, is undecided."""
    lines, signs, tally = [], {}, Tally()
    ran = sorted({r.method for r in records if r.family == families[0]},
                 key=lambda m: (m != "bati", m not in BASELINES, m))
    for method in ran:
        returns = _scores(records, method, families[0], "p_test_return")
        if not len(returns):
            continue
        shown = " (shown, not counted)" if method in NOT_COUNTED_IN_C6 else ""
        if _seeds_ok(returns):
            value, lo, hi = iqm_interval(returns, reps=REPS)
            signs[method] = 1 if lo > 0 else -1 if hi < 0 else 0
            lines.append(f"{method}: IQM {value:.2f} [{lo:.2f}, {hi:.2f}]{shown}")
        else:
            signs[method] = None
            lines.append(f"{method}: {returns.mean():.2f} ({len(returns)} seed(s)){shown}")
    others = {k: v for k, v in signs.items() if k != "bati" and k not in NOT_COUNTED_IN_C6}
    if signs.get("bati") is None or not any(v is not None for v in others.values()):
        return lines, "not tested", tally  # BATI alone: "only BATI" compares with nothing
    tally.add("BATI positive", signs["bati"])
    for method, sign in others.items():  # the paper's side of a method is "not positive": below 0
        name = {None: f"{method} (fewer than {MIN_SEEDS} seeds)", 1: f"{method} positive", -1: f"{method} negative",
                0: f"{method}'s sign"}[sign]
        tally.add(name, 0 if sign is None else -sign)
    if signs["bati"] == 1 and all(v == -1 for v in others.values()):
        return lines, "reproduced", tally
    if signs["bati"] != 1 or any(v == 1 for v in others.values()):
        return lines, "not reproduced", tally
    return lines, "partly", tally


NOT_COUNTED_IN_C6 = ("bati-r", "bati-auto", "oracle")
"""Methods C6 shows beside BATI without counting them: BATI's own test-time rules, and the oracle, which is told
the task."""


@dataclass(frozen=True)
class Claim:
    name: str
    text: str
    source: str
    experiment: str
    families: tuple[str, ...]
    test: Callable[[list[Record], tuple[str, ...]], tuple[list[str], str, Tally]]
    methods: tuple[str, ...] = ("bati",) + BASELINES
    """The methods it compares, its subject first: their runs' convergence is reported beside the verdict."""
    levels: int = 1
    """At how many noise levels BATI and a compared method must both have run for a family to count as tested
    (C4 compares eps 0 with the largest eps: 2)."""
    needs_baseline: bool = True
    """Whether a family counts as tested only where a compared method ran beside BATI (C5 is about BATI's own gain
    with the context's length: its runs alone decide it)."""


CLAIMS = (
    Claim("C1", "BATI has the best p_test return on all five MuJoCo families", "Table 4, Fig. 4", "main", MUJOCO,
          best_on_p_test),
    Claim("C2", "the baselines match BATI on p_train contexts and fall on p_test contexts", "Fig. 8 vs Fig. 4",
          "main", MUJOCO, fall_on_p_test),
    Claim("C3", "Recon (BATI's model, an encoder for z) stays below BATI", "Table 4", "main", MUJOCO, recon_below,
          ("bati", "recon")),
    Claim("C4", "noise in the collecting policy hurts the baselines, not BATI", "Fig. 5, 7", "noise",
          ("AntDir", "HalfCheetahDir"), noise_hurts_baselines, levels=2),
    Claim("C5", "BATI improves with longer contexts (HalfCheetahDir, eps 0.9, trained with C = 50)", "Table 1",
          "context-length", ("HalfCheetahDir",), longer_contexts_help, needs_baseline=False),
    Claim("C6", "only BATI has a positive return on out-of-distribution tasks (AntDir)", "Table 2", "ood-tasks",
          ("AntDir",), only_bati_positive),
    Claim("C7", "BATI is the best method on Kuhn poker", "Table 6", "kuhn", ("KuhnPoker",), best_on_p_test),
    Claim("C8", "BATI's p_test return is above ER-TRL's on all five MuJoCo families (ours: ER-TRL, AAAI 2025, "
          "is not in the paper)", "beyond the paper", "main", MUJOCO,
          lambda records, families: best_on_p_test(records, families, ("er-trl",)), ("bati", "er-trl")),
    Claim("C9", "BATI-R, BATI's reward-only likelihood, has the best p_test return on all five MuJoCo families "
          "(ours: not in the paper; the families' tasks differ in the reward, HopperParam's and WalkerParam's in "
          "the dynamics too)", "docs/methods.md", "main", MUJOCO,
          lambda records, families: best_on_p_test(records, families, BASELINES, method="bati-r"),
          ("bati-r",) + BASELINES),
)


@dataclass
class Finding:
    claim: Claim
    source: Source
    lines: list[str]
    verdict: str
    runs: int
    families: list[str]
    """The claim's families with runs of the methods it compares at this scale."""
    commits: list[str]
    devices: list[str]
    wall_time_s: float
    moving: list[tuple[str, str]]
    """The compared cells whose p_test still drifts over the scored window: ("focal on AntDir rising", its drift
    with the interval)."""
    flat: int
    """The compared cells with >= MIN_SEEDS seeds whose drift interval holds 0."""
    thin: list[str] = field(default_factory=list)
    """Those of `families` where no compared pair has MIN_SEEDS seeds yet: runs, but no ranking."""
    tally: Tally = field(default_factory=Tally)
    """Which comparisons hold, are undecided or go against the claim (what a "partly" rests on)."""


def decide(root: Path = Path("."), sources: tuple[Source, ...] = SOURCES) -> list[Finding]:
    """Every claim at every scale present under `root`."""
    require_rliable()
    findings = []
    for claim in CLAIMS:
        seen = set()
        for source in sorted(sources, key=lambda s: bool(s.data)):  # the default data's first: a cell is theirs
            records = gather(claim.experiment, source, Path(root))
            records = [r for r in records if r.family in claim.families]
            cells = frozenset((r.job, r.seed, r.context_length) for r in records)
            if not records or cells in seen:  # (Kuhn poker's and the ood splits' default data: conditioned)
                continue
            seen.add(cells)
            lines, verdict, tally = claim.test(records, claim.families)
            compared = compared_families(records, claim)
            ranked = compared_families(records, claim, seeds=MIN_SEEDS)
            moving, flat = convergence([r for r in records if r.family in compared], claim.methods)
            findings.append(Finding(claim, source, lines, verdict, len(records), compared,
                                    sorted({short_commit(r.commit) for r in records if r.commit}),
                                    sorted({r.device for r in records if r.device}),
                                    jobs_wall_time((r.job, r.wall_time_s) for r in records), moving, flat,
                                    [f for f in compared if f not in ranked], tally))
    return findings


def compared_families(records: list[Record], claim: Claim, seeds: int = 1) -> list[str]:
    """The claim's families where BATI and at least one method it is compared with ran (at `claim.levels` noise
    levels, with at least `seeds` seeds at each): a family with BATI alone (or the Oracle alone, or, for C4, one
    eps) tests nothing, and its cells are not the verdict's. The claim's subject is the first of its methods
    (BATI, or C9's BATI-R)."""
    subject, *others = claim.methods

    def levels(method, family):
        runs = Counter(noise for noise, _ in {(r.noise, r.seed) for r in records
                                              if r.family == family and r.method == method})
        return {noise for noise, n in runs.items() if n >= seeds}

    if not claim.needs_baseline:
        return [f for f in claim.families if len(levels(subject, f)) >= claim.levels]
    return [f for f in claim.families
            if any(len(levels(subject, f) & levels(m, f)) >= claim.levels for m in others)]


def convergence(records: list[Record], methods: tuple[str, ...]) -> tuple[list[tuple[str, str]], int]:
    """Of the cells (method, family, eps) of `methods` with >= MIN_SEEDS seeds: those whose p_test still drifts
    over the scored window (its 95% interval excludes 0), as (cell, drift) text, and how many are flat."""
    moving, flat = [], 0
    cells = sorted({(r.method, r.family, r.noise) for r in records if r.method in methods},
                   key=lambda cell: (methods.index(cell[0]), cell[1:]))
    for method, family, noise in cells:
        drifts = {r.seed: r.drift for r in records if (r.method, r.family, r.noise) == (method, family, noise)}
        if len(drifts) < MIN_SEEDS:
            continue
        mean, low, high = drift_interval(list(drifts.values()), reps=REPS)
        negligible = NEGLIGIBLE if all(r.normalised for r in records if r.method == method) else 0.0
        verdict = drift_verdict(mean, low, high, negligible)
        if verdict == "flat":
            flat += 1
        elif verdict:
            eps = f" eps {noise:g}" if len({r.noise for r in records}) > 1 else ""
            moving.append((f"{method} on {family}{eps} {verdict}", f"{mean:+.2f} [{low:+.2f}, {high:+.2f}]"))
    return moving, flat


def _tested(findings: list[Finding], claim: Claim) -> list[Finding]:
    """The claim's findings that decide something, smallest scale first."""
    return sorted((f for f in findings if f.claim is claim and f.verdict != "not tested"),
                  key=lambda f: SOURCES.index(f.source) if f.source in SOURCES else -1)


def on_paper_data(source: Source, claim: Claim) -> bool:
    """Whether a source's cells are, for the claim's families, the data the paper collects: the default data,
    or the task-conditioned expert's where none of the families has per-task experts (Kuhn poker's exact best
    responses are its experts either way)."""
    if not source.data:
        return True
    return source.data == CONDITIONED_DATA and not any(_has_per_task_experts(f) for f in claim.families)


def _has_per_task_experts(name: str) -> bool:
    try:
        return get_family(name).record.per_task_expert_steps is not None
    except FamilyUnavailable:  # (KuhnPoker without OpenSpiel: it has none)
        return False


def _scale_name(finding: Finding) -> str:
    scale = finding.source.label.split(" ")[0].rstrip(",")
    return scale if on_paper_data(finding.source, finding.claim) else f"{scale}, {finding.source.data}"


def deciding(findings: list[Finding], claim: Claim) -> list[Finding]:
    """The claim's findings that decide it, smallest scale first: those on the paper's data (`on_paper_data`),
    else, where none tests it, the task-conditioned expert's (named as such wherever the verdict is shown)."""
    tested = _tested(findings, claim)
    return ([f for f in tested if on_paper_data(f.source, claim)]
            or [f for f in tested if f.source.data == CONDITIONED_DATA])


def overall(findings: list[Finding], claim: Claim) -> tuple[str, str]:
    """The verdict at the largest scale that decides the claim (`deciding`) and that scale's label; the other
    scales and data have their verdicts beside it (`every_scale`)."""
    tested = deciding(findings, claim)
    return (tested[-1].verdict, _scale_name(tested[-1])) if tested else ("not tested", "-")


def every_scale(findings: list[Finding], claim: Claim) -> str:
    """The verdict at each scale that tests the claim, smallest first: a thin slice at a large scale (one
    family on a GPU, say) stands beside the wider evidence of a smaller one instead of hiding it."""

    def coverage(finding: Finding) -> str:
        """The families with a ranking (>= MIN_SEEDS seeds), then those whose runs are too few to rank."""
        families = [f for f in finding.families if f not in finding.thin]
        if not families:
            text = ""
        elif len(families) == len(claim.families) > 1:
            text = f"all {len(families)} families"
        else:
            text = ", ".join(families) + (f"; {len(families)} of {len(claim.families)} families"
                                          if len(families) < len(claim.families) else "")
        thin = f"fewer than {MIN_SEEDS} seeds: {', '.join(finding.thin)}" if finding.thin else ""
        return "; ".join(part for part in (text, thin) if part)

    def moving(finding: Finding) -> str:  # which cells: the claim's section below
        count = len(finding.moving)
        return f"; {count} cell{'s' if count > 1 else ''} still moving" if count else ""

    def decided(finding: Finding) -> str:
        counts = finding.tally.counts()
        return f"comparisons: {counts}; " if finding.verdict == "partly" and counts else ""

    return "; ".join(f"{_scale_name(f)}: {f.verdict} ({decided(f)}{coverage(f)}{moving(f)})"
                     for f in _tested(findings, claim)) or "-"


def converged_text(finding: Finding, short: bool = False) -> str:
    """Whether the compared cells of a finding have stopped moving (see `convergence`)."""
    cells = finding.flat + len(finding.moving)
    if not cells:
        return "-" if short else f"no compared cell has {MIN_SEEDS} seeds"
    if not finding.moving:
        plural = "s" if cells > 1 else ""
        return f"yes ({cells} of {cells} cell{plural} flat)" if short else f"yes: {cells} compared cell{plural}, flat"
    if short:  # the summary row; the claim's section names the cells
        return f"no: {len(finding.moving)} of {cells} cells still moving"
    moving = "; ".join(f"{cell} ({drift})" for cell, drift in finding.moving)
    return f"no: {finding.flat} of {cells} compared cells flat; still moving: {moving}"


def claims_markdown(findings: list[Finding], command: str) -> str:
    lines = ["# The paper's claims, decided", "",
             f"Generated by `{command}` from the committed result files under results/ (docs/claims.md is this "
             "command's output; rerun it after new cells land). Scores: normalised returns where the runs "
             "record random and expert returns (C6: raw returns, the claim is about their sign). Intervals: "
             f"95% stratified-bootstrap percentile intervals through rliable ({REPS:,} replicates, seed 0). A "
             f"ranking is called only with >= {MIN_SEEDS} seeds per method; P(X > Y) decides when its interval "
             "excludes 1/2. The verdict of a claim is the one at the largest scale that tests it on the paper's data "
             "(one SAC expert per training task; Kuhn poker: its exact best responses), and where no cells of "
             "those test it yet, on one task-conditioned expert's data (named so). Converged: "
             "the p_test drift over the scored window (the change across the evaluations a run's number averages, "
             "of the least-squares line through them; mean over seeds with its 95% interval) of every compared "
             f"cell with >= {MIN_SEEDS} seeds holds 0 (or is under {NEGLIGIBLE}); a cell whose interval excludes 0 "
             "is still rising or falling, "
             "and a verdict that rests on it may change with more steps.", "",
             "| claim | paper | verdict | at scale | converged there | every tested scale |",
             "| --- | --- | --- | --- | --- | --- |"]
    for claim in CLAIMS:
        verdict, scale = overall(findings, claim)
        tested = deciding(findings, claim)  # the verdict's own scale
        counts = tested[-1].tally.counts() if tested and verdict == "partly" else ""
        verdict = f"{verdict} ({counts})" if counts else verdict
        if tested and 1 < len(claim.families) and len(tested[-1].families) < len(claim.families):
            scale += f" ({', '.join(tested[-1].families)}: {len(tested[-1].families)} of {len(claim.families)} families)"
        lines.append(f"| {claim.name}: {claim.text} | {claim.source} | **{verdict}** | {scale} | "
                     f"{converged_text(tested[-1], short=True) if tested else '-'} | {every_scale(findings, claim)} |")
    for claim in CLAIMS:
        lines += ["", f"## {claim.name}: {claim.text} ({claim.source}; experiment `{claim.experiment}`)", ""]
        mine = [f for f in findings if f.claim is claim]
        if not mine:
            lines.append("No finished runs at any scale.")
        for f in mine:
            lines.append(f"**{f.source.label}**: {f.verdict} ({f.runs} run(s); commit(s) {', '.join(f.commits) or '?'}; "
                         f"device(s) {', '.join(f.devices) or '?'}; summed wall time {f.wall_time_s / 60:.1f} min)")
            lines.append("")
            lines += [f"- {line}" for line in f.lines] or ["- (no comparison possible)"]
            if f.verdict in ("partly", "not reproduced") and f.tally.text():
                lines.append(f"- decided: {f.tally.text()}")
            lines.append(f"- converged: {converged_text(f)}")
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def write_claims(root: Path = Path("."), out: Path | None = None) -> tuple[Path, list[tuple[Claim, str, str]]]:
    """`bati claims`: decide every claim from the result files under `root`, write the page (default
    ROOT/docs/claims.md, atomically) and return its path and (claim, verdict, scale) per claim."""
    from bati.errors import PathError
    from bati.io import atomic_write_text

    if not (Path(root) / "results").is_dir():  # a mistyped --root would give a page of "not tested" claims
        raise PathError(f"no results/ directory under {root}: --root is the project directory whose results/ "
                        "holds the experiments")
    from bati.io import check_directory

    out = out or Path(root) / "docs" / "claims.md"
    check_directory(out.parent, "the claims page's folder")  # before minutes of intervals, not after
    if out.exists() and not os.access(out, os.W_OK):
        raise PathError(f"{out} is not writable")
    findings = decide(root)
    command = "bati claims" + (f" --root {root}" if Path(root) != Path(".") else "")
    atomic_write_text(out, claims_markdown(findings, command))
    return out, [(claim, *overall(findings, claim)) for claim in CLAIMS]


def write_and_show_claims(root: Path = Path("."), out: Path | None = None, *, console) -> None:
    """`bati claims`: write the page, then each claim's verdict and where the page is on the rich `console`."""
    out, verdicts = write_claims(root, out)
    for claim, verdict, scale in verdicts:
        console.print(f"{claim.name} {verdict} (at {scale}): {claim.text}", soft_wrap=True)
    console.print(f"claims page: {out}")
