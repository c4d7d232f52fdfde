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

import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from bati.envs import MUJOCO_FAMILIES as MUJOCO
from bati.envs import FamilyUnavailable, get_family
from bati.experts.kinds import data_label, named_expert
from bati.io import short_commit
from bati.report import verdicts
from bati.report.claim_records import CONDITIONED_DATA, SOURCES, Record, Source, gather
from bati.report.convergence import NEGLIGIBLE, drift_interval, drift_verdict
from bati.report.runs import jobs_wall_time
from bati.report.stats import require_rliable
from bati.report.verdicts import (
    BASELINES,
    MIN_SEEDS,
    Tally,
    best_on_p_test,
    fall_on_p_test,
    longer_contexts_help,
    noise_hurts_baselines,
    only_bati_positive,
    recon_below,
)


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
    methods: list[str] = field(default_factory=list)
    """The claim's methods with runs at this scale (its subject first, where it has runs; empty: not recorded)."""


def counted(finding: Finding) -> str:
    """A verdict's comparisons counted (holds, undecided, against) where the verdict alone would say less: a
    "partly", and a "not reproduced" whose intervals include chance somewhere (so it does not read as decided
    against the claim); "" for the others."""
    tally = finding.tally
    short_of_against = finding.verdict == "not reproduced" and (tally.holds or tally.undecided)
    if finding.verdict == "partly" or short_of_against:
        return tally.counts()
    return ""


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
                                    [f for f in compared if f not in ranked], tally,
                                    [m for m in claim.methods if any(r.method == m for r in records)]))
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
        mean, low, high = drift_interval(list(drifts.values()), reps=verdicts.REPS)
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
        counts = counted(finding)
        return f"comparisons: {counts}; " if counts else ""

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
             f"95% stratified-bootstrap percentile intervals through rliable ({verdicts.REPS:,} replicates, seed 0). A "
             f"ranking is called only with >= {MIN_SEEDS} seeds per method; P(X > Y) decides when its interval "
             "excludes 1/2; a verdict short of 'reproduced' counts the comparisons that hold, are undecided "
             "and go against. The verdict of a claim is the one at the largest scale that tests it on the "
             "paper's data (one SAC expert per training task; Kuhn poker: its exact best responses), and where "
             "no cells of those test it yet, on one task-conditioned expert's data (named so). Converged: "
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
        counts = counted(tested[-1]) if tested else ""
        verdict = f"{verdict} ({counts})" if counts else verdict
        if tested and 1 < len(claim.families) and len(tested[-1].families) < len(claim.families):
            scale += f" ({', '.join(tested[-1].families)}: {len(tested[-1].families)} of {len(claim.families)} families)"
        if tested and claim.needs_baseline and 0 < len(tested[-1].methods) < len(claim.methods):
            others = [m for m in tested[-1].methods if m != claim.methods[0]]
            scale += f" ({len(others)} of {len(claim.methods) - 1} compared methods: {', '.join(others) or 'none'})"
        lines.append(f"| {claim.name}: {claim.text} | {claim.source} | **{verdict}** | {scale} | "
                     f"{converged_text(tested[-1], short=True) if tested else '-'} | {every_scale(findings, claim)} |")
    for claim in CLAIMS:
        lines += ["", f"## {claim.name}: {claim.text} ({claim.source}; experiment `{claim.experiment}`)", ""]
        mine = [f for f in findings if f.claim is claim]
        named = {named_expert(family) for family in claim.families}
        collectors = data_label(None, claim.families[0]) if len(named) == 1 and "" not in named else ""
        if collectors:
            lines += [f"{', '.join(claim.families)}: its {named.pop()} collect its data at every scale (it has no "
                      "SAC experts)", ""]
        if not mine:
            lines.append("No finished runs at any scale.")
        for f in mine:
            lines.append(f"**{f.source.heading(collectors)}**: {f.verdict} ({f.runs} run(s); commit(s) {', '.join(f.commits) or '?'}; "
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
