"""`bati claims`: each claim's verdict from result files laid out as the experiments write them."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import pytest

from bati.cli import main
from bati.experiments.pipeline import plan_experiment
from bati.experiments.specs import get_spec
from bati.report import claims as claims_module
from bati.report import verdicts as verdict_rules
from bati.report.claim_records import CONDITIONED_DATA, SOURCES
from bati.report.claims import CLAIMS, claims_markdown, decide, overall
from bati.report.probes import probe_path

CPU = next(s for s in SOURCES if s.scale == "cpu" and not s.data)  # the paper's data: per-task experts
CPU_CONDITIONED = next(s for s in SOURCES if s.scale == "cpu" and s.data == CONDITIONED_DATA)


@pytest.fixture(autouse=True)
def fewer_replicates(monkeypatch):
    """50 bootstrap replicates instead of the page's 2,000: the verdicts of these clear-cut cases do not
    depend on it, and the suite stays fast."""
    monkeypatch.setattr(verdict_rules, "REPS", 50)
QUICK = SOURCES[0]


def store_plan(root: Path, source, experiment: str):
    """The experiment planned in the source's folder for seeds 0-4 and stored as its report stores it (plan.json
    in a report folder of its own): what `bati claims` reads."""
    name = dict(source.reports).get(experiment, experiment)
    plan = plan_experiment(get_spec(name), source.scale, root / source.out_dir, seeds=(0, 1, 2, 3, 4),
                           settings=source.settings)
    folder = root / source.out_dir / "-".join([name, *sorted(s.replace("=", "_") for s in source.settings)])
    folder.mkdir(parents=True, exist_ok=True)
    plan.stored().write(folder)
    return plan


def write_cells(root: Path, source, experiment: str, scores: dict, seeds=(0, 1, 2)) -> None:
    """An eval.json in each planned cell of `experiment` (of the source's experts kind) for `seeds`:
    scores[(method, family)] = (p_train, p_test) per seed (random 0 and experts 1, so the normalised score is the
    return)."""
    for cell in sorted(store_plan(root, source, experiment).cells, key=lambda cell: bool(cell.host)):  # runs first
        c = cell.config
        if (c.method, c.family) not in scores or c.seed not in seeds or source.experts not in ("", c.experts):
            continue
        p_train, p_test = scores[(c.method, c.family)]
        c.out_dir.mkdir(parents=True, exist_ok=True)
        scored = {"p_train_return": p_train[c.seed], "p_test_return": p_test[c.seed], "wall_time_s": 60.0}
        path = c.out_dir / "eval.json"
        if cell.host:  # a test-time rule of its host's run: that run's "rules" entry
            record = json.loads(path.read_text()) if path.exists() else {
                "family": c.family, "method": cell.host, "seed": c.seed, "p_train_return": 0.0, "p_test_return": 0.0,
                "reference_returns": {"random": 0.0, "expert": 1.0}, "commit": "abc", "device": "cpu"}
            record.setdefault("rules", {})[c.method] = scored
        else:
            record = {"family": c.family, "method": c.method, "seed": c.seed, **scored,
                      "reference_returns": {"random": 0.0, "expert": 1.0}, "commit": "abc", "device": "cpu"}
        path.write_text(json.dumps(record))


FAMILIES = ("AntDir", "HalfCheetahVel", "HalfCheetahDir", "HopperParam", "WalkerParam")
HIGH, LOW = (0.80, 0.85, 0.90), (0.20, 0.25, 0.30)


def verdicts(root: Path) -> dict[str, tuple[str, str]]:
    findings = decide(root)
    return {claim.name: overall(findings, claim) for claim in CLAIMS}


def test_the_paper_data_decide_and_the_conditioned_data_only_where_it_has_no_cells(tmp_path):
    everywhere = {("bati", f): (HIGH, HIGH) for f in FAMILIES}
    everywhere |= {(m, f): (HIGH, LOW) for f in FAMILIES for m in ("focal", "csro", "unicorn", "recon")}
    write_cells(tmp_path, CPU_CONDITIONED, "main", everywhere)
    assert verdicts(tmp_path)["C1"] == ("reproduced", "cpu, one task-conditioned expert's data")
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, LOW), ("focal", "AntDir"): (HIGH, HIGH)})
    findings = decide(tmp_path)
    c1 = next(c for c in CLAIMS if c.name == "C1")
    assert overall(findings, c1) == ("not reproduced", "cpu")  # one family of the paper's data decides
    assert "cpu (AntDir: 1 of 5 families)" in claims_markdown(findings, "bati claims")


def test_bati_above_every_baseline_everywhere_reproduces_c1_to_c3(tmp_path):
    scores = {("bati", f): (HIGH, HIGH) for f in FAMILIES}
    scores |= {(m, f): (HIGH, LOW) for f in FAMILIES for m in ("focal", "csro", "unicorn", "recon")}
    write_cells(tmp_path, CPU, "main", scores)
    found = verdicts(tmp_path)
    assert found["C1"] == ("reproduced", "cpu") and found["C3"] == ("reproduced", "cpu")
    assert found["C2"] == ("reproduced", "cpu")  # same p_train, baselines fall on p_test
    assert found["C4"] == ("not tested", "-")


def test_one_family_lost_is_partly_and_a_reversal_is_not_reproduced(tmp_path):
    scores = {("bati", f): (HIGH, HIGH) for f in FAMILIES}
    scores |= {(m, f): (HIGH, LOW) for f in FAMILIES for m in ("focal", "recon")}
    scores[("focal", "AntDir")] = (HIGH, (0.95, 0.96, 0.97))  # FOCAL beats BATI on one family
    write_cells(tmp_path, CPU, "main", scores)
    assert verdicts(tmp_path)["C1"][0] == "partly"
    reversed_ = {("bati", f): (HIGH, LOW) for f in FAMILIES} | {("recon", f): (HIGH, HIGH) for f in FAMILIES}
    write_cells(tmp_path / "r", CPU, "main", reversed_)
    assert verdicts(tmp_path / "r")["C3"][0] == "not reproduced"


def test_fewer_than_three_seeds_call_no_ranking(tmp_path):
    scores = {("bati", f): (HIGH, HIGH) for f in FAMILIES} | {("recon", f): (HIGH, LOW) for f in FAMILIES}
    write_cells(tmp_path, QUICK, "main", scores, seeds=(0,))
    findings = decide(tmp_path)
    c3 = next(f for f in findings if f.claim.name == "C3")
    assert c3.verdict == "not tested" and "(1 seed(s))" in c3.lines[0]


def test_overlapping_intervals_do_not_decide(tmp_path):
    same = (0.5, 0.6, 0.7)
    write_cells(tmp_path, CPU, "main", {("bati", f): (same, same) for f in FAMILIES}
                | {("recon", f): (same, same) for f in FAMILIES})
    c3 = next(f for f in decide(tmp_path) if f.claim.name == "C3")
    assert c3.verdict == "not reproduced" and "P(BATI > recon) 0.50" in c3.lines[0]
    assert c3.lines[-1].startswith("pooled over AntDir, HalfCheetahVel") and "P(BATI > Recon) 0.50" in c3.lines[-1]


def test_recon_is_judged_family_by_family_like_the_other_baselines(tmp_path):
    """BATI far above Recon on one family and level on another: C3 holds on one family ('partly', as C1 would say of
    a baseline), although the pooled probability, shown beside, averages a decided family with a tie."""
    level = (0.5, 0.6, 0.7)
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("recon", "AntDir"): (LOW, LOW),
                                        ("bati", "WalkerParam"): (level, level), ("recon", "WalkerParam"): (level, level)})
    c3 = next(f for f in decide(tmp_path) if f.claim.name == "C3")
    assert c3.verdict == "partly"
    assert c3.lines[0] == "AntDir: BATI 0.85 (3 seed(s)); P(BATI > recon) 1.00 [1.00, 1.00]"
    assert c3.lines[1].startswith("WalkerParam: BATI 0.60 (3 seed(s)); P(BATI > recon) 0.50")
    assert c3.lines[2].startswith("pooled over AntDir, WalkerParam: BATI 0.72, Recon 0.42; "
                                 "stratified P(BATI > Recon) 0.75")  # (1 + 1/2) / 2


def test_cli_writes_the_page(tmp_path, capsys):
    write_cells(tmp_path, CPU, "main", {("bati", f): (HIGH, HIGH) for f in FAMILIES}
                | {("recon", f): (HIGH, LOW) for f in FAMILIES})
    out = tmp_path / "claims.md"
    assert main(["claims", "--root", str(tmp_path), "--out", str(out)]) == 0
    page = out.read_text()
    assert "| C3: Recon (BATI's model, an encoder for z) stays below BATI | Table 4 | **reproduced** | cpu |" in page
    assert "C3 reproduced (at cpu)" in capsys.readouterr().out


def test_a_root_without_results_is_one_line_and_writes_nothing(tmp_path, capsys):
    assert main(["claims", "--root", str(tmp_path / "typo")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no results/ directory under") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "typo").exists()


@pytest.mark.parametrize("claim", [c.name for c in CLAIMS])
def test_every_claim_is_not_tested_without_results(tmp_path, claim):
    assert verdicts(tmp_path)[claim] == ("not tested", "-")


def test_er_trl_is_judged_apart_from_the_papers_baselines(tmp_path):
    scores = {("bati", f): (HIGH, LOW) for f in FAMILIES} | {("er-trl", f): (HIGH, HIGH) for f in FAMILIES}
    write_cells(tmp_path, CPU, "main", scores)
    found = verdicts(tmp_path)
    assert found["C8"] == ("not reproduced", "cpu")  # ER-TRL above BATI on every family
    assert found["C1"] == ("not tested", "-")  # C1 is about the paper's baselines, none of which ran


def test_bati_r_is_judged_as_its_own_claim_where_full_bati_falls(tmp_path):
    """C9 asks of BATI-R what C1 asks of BATI: full BATI below the baselines on p_test does not touch it."""
    scores = {("bati", f): (HIGH, LOW) for f in FAMILIES} | {("bati-r", f): (HIGH, HIGH) for f in FAMILIES}
    scores |= {("focal", f): (HIGH, (0.5, 0.55, 0.6)) for f in FAMILIES}
    write_cells(tmp_path, CPU, "main", scores)
    found = verdicts(tmp_path)
    assert found["C9"] == ("reproduced", "cpu") and found["C1"] == ("not reproduced", "cpu")
    c9 = next(f for f in decide(tmp_path) if f.claim.name == "C9")
    assert c9.families == list(FAMILIES) and "P(BATI-R > focal) 1.00" in c9.lines[0]


def test_bati_r_alone_tests_nothing(tmp_path):
    write_cells(tmp_path, CPU, "main", {("bati-r", f): (HIGH, HIGH) for f in FAMILIES})
    assert verdicts(tmp_path)["C9"] == ("not tested", "-")


def test_every_tested_scale_stands_beside_the_largest(tmp_path):
    """A thin slice at a larger scale decides the headline verdict, and the smaller scale's verdict stays on
    the page beside it."""
    paper = next(s for s in SOURCES if s.scale == "paper" and not s.data)
    write_cells(tmp_path, CPU, "main", {("bati", f): (HIGH, HIGH) for f in FAMILIES}
                | {("recon", f): (HIGH, LOW) for f in FAMILIES})
    write_cells(tmp_path, paper, "main", {("bati", "AntDir"): (HIGH, LOW), ("recon", "AntDir"): (HIGH, HIGH)})
    findings = decide(tmp_path)
    c3 = next(c for c in CLAIMS if c.name == "C3")
    assert overall(findings, c3) == ("not reproduced", "paper")
    assert claims_module.every_scale(findings, c3) == ("cpu: reproduced (all 5 families); "
                                                       "paper: not reproduced (AntDir; 1 of 5 families)")


def test_a_family_with_fewer_seeds_is_named_not_pooled(tmp_path):
    """FOCAL at 3 seeds on AntDir and 2 on WalkerParam: C2 pools AntDir alone (pooling both would cut AntDir to
    2 seeds and decide nothing) and names WalkerParam."""
    write_cells(tmp_path, CPU, "main", {("bati", f): (HIGH, HIGH) for f in ("AntDir", "WalkerParam")}
                | {("focal", "AntDir"): (HIGH, LOW)})
    write_cells(tmp_path, CPU, "main", {("focal", "WalkerParam"): (HIGH, LOW)}, seeds=(0, 1))
    c2 = next(f for f in decide(tmp_path) if f.claim.name == "C2" and f.source is CPU)
    assert c2.verdict == "partly"
    assert c2.lines[0].startswith("focal (1 family: AntDir): p_train 0.85 -> p_test 0.25 (change -0.60) vs BATI 0.85 -> "
                                  "0.85 (+0.00) (not pooled, fewer than 3 seeds: WalkerParam); P(BATI falls less) "
                                  "1.00 [1.00, 1.00]")


def test_a_claim_about_every_family_holds_at_most_partly_on_some(tmp_path):
    """C2 decided on AntDir alone is 'partly': the claim is about all five families."""
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW)})
    assert verdicts(tmp_path)["C2"] == ("partly", "cpu")


def test_a_verdict_names_the_compared_methods_that_ran_where_some_did_not(tmp_path):
    """C1 compares BATI with five baselines: decided where FOCAL alone ran beside it, the summary says so."""
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW)})
    findings = decide(tmp_path)
    c1 = next(f for f in findings if f.claim.name == "C1" and f.source is CPU)
    assert c1.methods == ["bati", "focal"]
    row = next(line for line in claims_markdown(findings, "bati claims").splitlines() if line.startswith("| C1:"))
    assert "(1 of 5 compared methods: focal)" in row
    c5 = next(line for line in claims_markdown(findings, "bati claims").splitlines() if line.startswith("| C5:"))
    assert "compared methods" not in c5  # BATI's runs alone decide it


def test_a_compared_cell_still_rising_over_its_scored_window_is_named_beside_the_verdict(tmp_path):
    """FOCAL's p_test climbs through its last five evaluations on AntDir (+0.4 normalised): the page says the
    verdict rests on a cell that has not converged; BATI's flat curves count as converged."""
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW)})
    for cell in store_plan(tmp_path, CPU, "main").cells:
        path = cell.config.out_dir / "eval.json"
        if not path.exists():
            continue
        record = json.loads(path.read_text())
        rise = 0.1 if record["method"] == "focal" else 0.0
        record |= {"evaluations_averaged": 5, "curve": [
            {"step": 10_000 * (i + 6), "p_test_return": record["p_test_return"] + rise * (i - 2) + 0.01 * record["seed"],
             "p_train_return": record["p_train_return"]} for i in range(5)]}
        path.write_text(json.dumps(record))
    findings = decide(tmp_path)
    c2 = next(f for f in findings if f.claim.name == "C2" and f.source is CPU)
    assert c2.flat == 1 and c2.moving == [("focal on AntDir rising", "+0.40 [+0.40, +0.40]")]
    assert claims_module.converged_text(c2, short=True) == "no: 1 of 2 cells still moving"
    assert "still moving: focal on AntDir rising (+0.40" in claims_module.converged_text(c2)  # the section names it
    assert "; 1 cell still moving)" in claims_module.every_scale(findings, c2.claim)
    c3 = next(f for f in findings if f.claim.name == "C3")  # compares BATI with Recon only, which has no run:
    assert c3.families == [] and c3.moving == [] and claims_module.converged_text(c3, short=True) == "-"


def test_a_family_where_only_the_oracle_ran_does_not_count_as_tested(tmp_path):
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW),
                                        ("oracle", "HalfCheetahVel"): (HIGH, HIGH)})
    c1 = next(f for f in decide(tmp_path) if f.claim.name == "C1" and f.source is CPU)
    assert c1.families == ["AntDir"]


def test_a_family_where_bati_ran_without_the_compared_method_does_not_count_as_tested(tmp_path):
    """C8 compares BATI with ER-TRL: BATI's HalfCheetahVel cells, without an ER-TRL run there, are not its
    evidence, nor is their convergence (it was listed as C8's "still moving" cell)."""
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("er-trl", "AntDir"): (HIGH, LOW),
                                        ("bati", "HalfCheetahVel"): (HIGH, HIGH),
                                        ("focal", "HalfCheetahVel"): (HIGH, LOW)})
    for path in (tmp_path / CPU.out_dir).rglob("eval.json"):  # every cell flat but BATI's on HalfCheetahVel
        record = json.loads(path.read_text())
        rise = 0.1 if (record["method"], record["family"]) == ("bati", "HalfCheetahVel") else 0.0
        record |= {"evaluations_averaged": 5, "curve": [
            {"step": 10_000 * (i + 6), "p_test_return": record["p_test_return"] + rise * (i - 2) + 0.01 * record["seed"],
             "p_train_return": record["p_train_return"]} for i in range(5)]}
        path.write_text(json.dumps(record))
    found = {f.claim.name: f for f in decide(tmp_path) if f.source is CPU}
    assert found["C8"].families == ["AntDir"] and (found["C8"].flat, found["C8"].moving) == (2, [])
    assert found["C1"].families == ["HalfCheetahVel"]  # ER-TRL is not one of the paper's baselines
    assert [cell for cell, _ in found["C1"].moving] == ["bati on HalfCheetahVel rising"]


def test_a_family_at_one_noise_level_does_not_count_for_the_noise_claim(tmp_path):
    """C4 compares eps 0 with the largest eps: HalfCheetahDir's eps-0.8 cells (the main table's), without its
    eps-0 ones, are not its evidence (the page said "all 2 families" with AntDir's alone deciding)."""
    cells = {(m, f): (HIGH, HIGH) for m in ("bati", "focal") for f in ("AntDir", "HalfCheetahDir")}
    write_cells(tmp_path, CPU, "noise", cells)
    for run in (tmp_path / CPU.out_dir / "HalfCheetahDir").glob("cpu-eps0-*/*"):  # HalfCheetahDir at eps 0.8 only
        (run / "eval.json").unlink()
    for run in (tmp_path / CPU.out_dir / "HalfCheetahDir").glob("cpu-eps0.4-*/*"):
        (run / "eval.json").unlink()
    c4 = next(f for f in decide(tmp_path) if f.claim.name == "C4" and f.source is CPU)
    assert c4.families == ["AntDir"]
    assert claims_module.every_scale([c4], c4.claim).startswith("cpu: ") and "AntDir; 1 of 2 families" in \
        claims_module.every_scale([c4], c4.claim)


def test_the_noise_claim_shows_bati_r_beside_bati_without_counting_it(tmp_path):
    cells = {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, HIGH), ("bati-r", "AntDir"): (HIGH, HIGH)}
    write_cells(tmp_path, CPU, "noise", cells)
    for run in (tmp_path / CPU.out_dir / "AntDir").glob("cpu-eps1-*/bati-seed*"):  # BATI-R loses 0.5 at eps 1
        record = json.loads((run / "eval.json").read_text())
        record["rules"]["bati-r"]["p_test_return"] -= 0.5  # (a rule of BATI's run)
        (run / "eval.json").write_text(json.dumps(record))
    c4 = next(f for f in decide(tmp_path) if f.claim.name == "C4" and f.source is CPU)
    line = next(line for line in c4.lines if line.startswith("AntDir: "))
    assert "BATI eps 0 -> 1: +0.00 [+0.00, +0.00]; (BATI-R, not a baseline: -0.50 [-0.50, -0.50]); focal +0.00" in line
    write_cells(tmp_path / "without", CPU, "noise", {k: v for k, v in cells.items() if k[0] != "bati-r"})
    without = next(f for f in decide(tmp_path / "without") if f.claim.name == "C4" and f.source is CPU)
    assert c4.verdict == without.verdict  # BATI-R's fall is no evidence about the baselines


def test_bati_alone_decides_whether_longer_contexts_help(tmp_path):
    """C5 is about BATI's own gain with the context's length: its runs count without a baseline beside them."""
    plan = store_plan(tmp_path, CPU, "context-length")
    for cell in plan.cells:
        c = cell.config
        if c.method != "bati" or c.seed > 2:
            continue
        c.out_dir.mkdir(parents=True, exist_ok=True)
        record = {"family": c.family, "method": c.method, "seed": c.seed, "p_train_return": 0.5,
                  "p_test_return": 0.5, "reference_returns": {"random": 0.0, "expert": 1.0}, "commit": "abc",
                  "device": "cpu", "wall_time_s": 60.0}
        (c.out_dir / "eval.json").write_text(json.dumps(record))
        for probe in plan.probes[cell.id]:  # longer contexts, higher returns on every seed
            n = probe.eval_context_length
            path = probe_path(c.out_dir, probe)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"probe": asdict(probe), "context_length": n, "p_train_return": 0.5,
                                        "p_test_return": n / 100 + c.seed / 1000, "commit": "abc",
                                        "wall_time_s": 1.0}))
    c5 = next(f for f in decide(tmp_path) if f.claim.name == "C5" and f.source is CPU)
    assert c5.families == ["HalfCheetahDir"] and c5.verdict == "reproduced"
    assert claims_module.every_scale([c5], c5.claim) == "cpu: reproduced (HalfCheetahDir)"


def test_bati_alone_positive_out_of_distribution_tests_nothing(tmp_path):
    """C6 says only BATI is positive: BATI's 3 seeds without any baseline's are no verdict (the page said
    "reproduced" with BATI's cells alone); with FOCAL's 3 seeds negative, it is."""
    write_cells(tmp_path, CPU, "ood-tasks", {("bati", "AntDir"): (HIGH, HIGH)})
    assert verdicts(tmp_path)["C6"][0] == "not tested"
    write_cells(tmp_path, CPU, "ood-tasks", {("focal", "AntDir"): (HIGH, (-0.3, -0.2, -0.25))})
    assert verdicts(tmp_path)["C6"][0] == "reproduced"


def test_a_family_whose_runs_are_too_few_to_rank_is_named_apart(tmp_path):
    """ER-TRL with 3 seeds on AntDir and 2 on HopperParam: C8's summary names AntDir as its evidence and
    HopperParam as runs without a ranking (it listed both as "2 of 5 families")."""
    write_cells(tmp_path, CPU, "main", {("bati", f): (HIGH, HIGH) for f in ("AntDir", "HopperParam")}
                | {("er-trl", "AntDir"): (HIGH, LOW)})
    write_cells(tmp_path, CPU, "main", {("er-trl", "HopperParam"): (HIGH, LOW)}, seeds=(0, 1))
    findings = decide(tmp_path)
    c8 = next(f for f in findings if f.claim.name == "C8" and f.source is CPU)
    assert c8.families == ["AntDir", "HopperParam"] and c8.thin == ["HopperParam"] and c8.verdict == "partly"
    assert claims_module.every_scale(findings, c8.claim) == ("cpu: partly (comparisons: 1 hold; AntDir; 1 of 5 families; "
                                                             "fewer than 3 seeds: HopperParam)")


def test_the_summary_row_reads_convergence_at_the_verdicts_own_data(tmp_path):
    """The task-conditioned expert's source, tested beside the default one, must not lend its convergence to
    the row."""
    c1 = next(c for c in CLAIMS if c.name == "C1")

    def finding(source, moving):
        return claims_module.Finding(c1, source, [], "partly", 3, ["AntDir"], ["abc"], ["cpu"], 60.0, moving, 1)

    findings = [finding(CPU, []), finding(CPU_CONDITIONED, [("bati on HalfCheetahDir falling", "-0.3")])]
    row = next(line for line in claims_module.claims_markdown(findings, "bati claims").splitlines()
               if line.startswith("| C1"))
    assert "| cpu (AntDir: 1 of 5 families) | yes (1 of 1 cell flat) |" in row  # the default data's cell


def test_other_data_stands_beside_the_default_data_and_never_decides(tmp_path):
    """Table 3's size read in total (its own results directory) is judged on its own line; the headline verdict
    stays the default data's, even where only the other data test the claim."""
    total = next(s for s in SOURCES if "episodes_per_task=50" in s.settings and s.experts == "per-task")
    assert total.out_dir != CPU.out_dir and total.data
    write_cells(tmp_path, total, "main", {("bati", "HalfCheetahDir"): (HIGH, LOW),
                                          ("focal", "HalfCheetahDir"): (HIGH, HIGH)})
    c1 = next(c for c in CLAIMS if c.name == "C1")
    findings = decide(tmp_path)
    assert overall(findings, c1) == ("not tested", "-")
    assert claims_module.every_scale(findings, c1) == (
        "cpu, total size, per-task experts, 40k: not reproduced (HalfCheetahDir; 1 of 5 families)")
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW)})
    assert overall(decide(tmp_path), c1) == ("partly", "cpu")


def test_a_partly_names_the_comparisons_that_hold_are_undecided_and_go_against(tmp_path):
    """C2 with FOCAL falling, CSRO level with BATI's fall (undecided) and Recon falling less than BATI: "partly"
    with each named, in the claim's section and counted in the summary row."""
    fall = (0.0, 0.05, 0.1)
    scores = {("bati", f): (HIGH, tuple(h - 0.3 for h in HIGH)) for f in FAMILIES}
    scores |= {("focal", f): (HIGH, LOW) for f in FAMILIES}
    scores |= {("csro", f): (HIGH, tuple(h - 0.3 + d for h, d in zip(HIGH, (-0.2, 0.0, 0.2)))) for f in FAMILIES}
    scores |= {("recon", f): (HIGH, tuple(h - d for h, d in zip(HIGH, fall))) for f in FAMILIES}
    write_cells(tmp_path, CPU, "main", scores)
    c2 = next(f for f in decide(tmp_path) if f.claim.name == "C2" and f.source is CPU)
    assert c2.verdict == "partly"
    assert (c2.tally.holds, c2.tally.undecided, c2.tally.against) == (["focal"], ["csro"], ["recon"])
    page = claims_module.claims_markdown([c2], "bati claims")
    assert "**partly (1 hold, 1 undecided, 1 against)**" in page
    assert "- decided: holds: focal; undecided: csro; against: recon" in page


def test_a_not_reproduced_counts_its_comparisons_so_undecided_does_not_read_as_against(tmp_path):
    """C7 with BATI above FOCAL and level with Recon: BATI is not shown to be the best ("not reproduced"),
    and the summary row counts the comparisons: one holds, one is undecided, none goes against."""
    write_cells(tmp_path, CPU, "kuhn", {("bati", "KuhnPoker"): (HIGH, HIGH),
                                        ("focal", "KuhnPoker"): (HIGH, LOW),
                                        ("recon", "KuhnPoker"): (HIGH, HIGH)})
    c7 = next(f for f in decide(tmp_path) if f.claim.name == "C7" and f.source is CPU)
    assert c7.verdict == "not reproduced"
    assert c7.tally.holds == ["focal on KuhnPoker"] and c7.tally.undecided == ["recon on KuhnPoker"]
    assert not c7.tally.against
    page = claims_module.claims_markdown([c7], "bati claims")
    assert "**not reproduced (1 hold, 1 undecided)**" in page
    assert "cpu: not reproduced (comparisons: 1 hold, 1 undecided; KuhnPoker)" in page


def test_kuhn_pokers_headings_name_its_own_data_not_the_sac_experts(tmp_path):
    """Kuhn poker has no SAC experts: C7's headings name its exact best responses' data at every scale, where the
    other claims' headings name one SAC expert per training task or the task-conditioned expert."""
    write_cells(tmp_path, CPU, "kuhn", {("bati", "KuhnPoker"): (HIGH, HIGH), ("focal", "KuhnPoker"): (HIGH, LOW)})
    write_cells(tmp_path, QUICK, "kuhn", {("bati", "KuhnPoker"): (HIGH, HIGH), ("focal", "KuhnPoker"): (HIGH, LOW)})
    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH), ("focal", "AntDir"): (HIGH, LOW)})
    findings = decide(tmp_path)
    page = claims_module.claims_markdown(findings, "bati claims")
    c7 = page[page.index("## C7"):page.index("## C8")]
    assert "**cpu (exact best responses' data; 100k steps" in c7
    assert "**quick (3k steps, 20 episodes per task, exact best responses' data)**" in c7
    assert "SAC expert per training task" not in c7 and "task-conditioned" not in c7
    c1 = page[page.index("## C1"):page.index("## C2")]
    assert "**cpu (the paper's data: one SAC expert per training task, App. C.2; 100k steps" in c1


def test_only_bati_positive_fails_where_another_method_is_positive_too(tmp_path):
    """C6 checks the sign of every method that ran: FOCAL positive refutes "only BATI" (the page said "partly"),
    CSRO's sign undecided leaves it "partly"; BATI-R and the oracle are shown, never counted."""
    negative = (-0.3, -0.2, -0.25)
    write_cells(tmp_path, CPU, "ood-tasks", {("bati", "AntDir"): (HIGH, HIGH), ("unicorn", "AntDir"): (HIGH, negative),
                                            ("csro", "AntDir"): (HIGH, (-0.3, 0.0, 0.3))})
    assert verdicts(tmp_path)["C6"][0] == "partly"
    write_cells(tmp_path, CPU, "ood-tasks", {("focal", "AntDir"): (HIGH, (0.2, 0.25, 0.3))})
    c6 = next(f for f in decide(tmp_path) if f.claim.name == "C6" and f.source is CPU)
    assert c6.verdict == "not reproduced" and "focal positive" in c6.tally.against
    assert "csro's sign" in c6.tally.undecided and "unicorn negative" in c6.tally.holds


def test_an_unwritable_page_is_refused_before_any_interval_is_computed(tmp_path, monkeypatch):
    import os

    from bati.errors import PathError

    write_cells(tmp_path, CPU, "main", {("bati", "AntDir"): (HIGH, HIGH)})
    computed = []
    monkeypatch.setattr(claims_module, "decide", lambda root: computed.append(root) or [])
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if mode & os.W_OK else real(path, mode, **kw))
    with pytest.raises(PathError, match="not writable"):
        claims_module.write_claims(tmp_path, tmp_path / "out" / "claims.md")
    assert computed == [] and not (tmp_path / "out").exists()
