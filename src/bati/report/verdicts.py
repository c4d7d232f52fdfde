"""The verdict rules of the paper's claims: each a function of a claim's records (bati.report.claim_records) and
families that returns the evidence (numbers with 95% stratified-bootstrap intervals through rliable), a verdict
and the tally of its comparisons. A ranking is called only with at least `MIN_SEEDS` seeds per method; P(X > Y)
decides when its interval excludes 1/2."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from bati.report.claim_records import Record
from bati.report.stats import BOOTSTRAP_REPS, improvement_interval, iqm_interval

MIN_SEEDS = 3
REPS = BOOTSTRAP_REPS
"""Bootstrap replicates of every interval on the page."""
BASELINES = ("focal", "csro", "unicorn", "recon", "dpt")
"""The paper's baselines (Table 4); the oracle, no-context and our BATI variants are not compared."""



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

