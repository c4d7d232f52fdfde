"""`bati results`: the index of the committed results, packed training logs, the generated pages."""

import gzip
import json
from collections import Counter
from pathlib import Path

import pytest

from bati.cli import main
from bati.experiments.index import (
    INDEX,
    Study,
    Summary,
    _short_device,
    first_table,
    read_notes,
    report_folders,
    score_cell,
    shown,
    studies,
    unbacked_numbers,
    with_headline,
)
from bati.experts.kinds import CONDITIONED_SETTING
from bati.io import log_exists, pack_jsonl, read_jsonl
from bati.report.runs import earlier_sessions_time

ROOT = Path(__file__).resolve().parents[1]


def test_every_report_folder_is_a_study_and_listed_in_the_index():
    folders = report_folders(ROOT)
    assert folders, "results/ holds no report"
    declared = {s.report for s in studies(ROOT)}
    assert [f for f in folders if f not in declared] == [], "declare the folder in bati.experiments.index"
    index = (ROOT / INDEX).read_text()
    missing = [f for f in folders if f"]({f.relative_to('results')}/report.md)" not in index]
    assert missing == [], "results/README.md is stale: run `bati results`"


def test_results_folder_names_carry_no_device_or_date():
    names = [p.name for p in (ROOT / "results").rglob("*") if p.is_dir()]
    assert [n for n in names if any(t in n for t in ("h100", "h200", "2026-", "-v1", "-v2"))] == []


def test_committed_runs_keep_their_training_log_packed():
    runs = [p.parent for p in (ROOT / "results").rglob("eval.json")]
    assert runs
    assert [r for r in runs if (r / "metrics.jsonl").exists()] == [], "run `bati results --pack` before committing"


def test_pack_rounds_floats_keeps_integers_and_reads_back(tmp_path):
    log = tmp_path / "metrics.jsonl"
    records = [{"step": 100, "wall_time": 12.345678, "loss": 0.123456789, "nan": float("nan"), "n": 7},
               {"step": 200, "wall_time": 3.04, "loss": -1234.56789, "nan": 1.0, "n": 8}]
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    packed = pack_jsonl(log)
    assert packed.name == "metrics.jsonl.gz" and not log.exists() and log_exists(log)
    back = read_jsonl(log)
    assert [r["step"] for r in back] == [100, 200] and back[0]["n"] == 7
    assert back[0]["loss"] == 0.1235 and back[1]["loss"] == -1235.0
    assert back[0]["wall_time"] == 12.3
    assert back[0]["nan"] != back[0]["nan"]  # NaN stays NaN
    assert gzip.decompress(packed.read_bytes()).count(b"\n") == 2
    # a resumed run's earlier session (its clock restarted) is still counted from the packed log
    assert earlier_sessions_time(tmp_path) == pytest.approx(12.3)


def test_at_one_scale_the_paper_data_study_is_shown_before_the_conditioned_one():
    def summary(folder, settings, finished):
        study = Study(Path("results/cpu/experiments") / folder, "q", "main", "cpu", settings, store=True)
        return Summary(study, finished, 165, (0, 1, 2), [], 0, Counter(), 0.0)

    conditioned = summary("main-conditioned", (CONDITIONED_SETTING,), 157)
    per_task, few = summary("main", (), 85), summary("main", (), 40)
    for order in ([conditioned, per_task], [per_task, conditioned]):
        assert [s.study.report.name for s, _ in shown(order)] == ["main"]
        assert [s.study.report.name for s in shown(order)[0][1]] == ["main-conditioned"]
    assert [s.study.report.name for s, _ in shown([few, conditioned])] == ["main-conditioned"]  # under half


def test_first_table_takes_the_title_and_the_rows():
    report = "# R\n\n- a\n\n**p test return**\n\n| m | x |\n|---|---|\n| bati | 1 |\n\n**second**\n\n| y |\n"
    assert first_table(report) == "**p test return**\n\n| m | x |\n|---|---|\n| bati | 1 |"
    assert first_table("no table") == ""


def test_a_headline_cell_gives_an_interval_only_from_three_seeds():
    assert score_cell([]) == "–"
    assert score_cell([0.5]) == "0.50 (1 seed)"
    assert score_cell([0.5, 0.7]) == "0.60 (2 seeds)"
    cell = score_cell([0.5, 0.6, 0.7])
    assert cell.startswith("0.60 [") and cell.endswith("]")


def test_headline_replaces_only_its_block():
    readme = "top\n<!-- headline -->\nold\n<!-- /headline -->\nbottom\n"
    assert with_headline(readme, "new\n") == "top\n<!-- headline -->\nnew\n<!-- /headline -->\nbottom\n"
    with pytest.raises(ValueError, match="headline"):
        with_headline("no block", "new\n")


def test_notes_are_read_per_report_folder(tmp_path):
    (tmp_path / "results").mkdir()
    (tmp_path / "results/notes.md").write_text("# Notes\n\n## results/cpu/experiments/main\n\nIt shows x.\n\n"
                                               "## results/quick/experiments/kuhn\nKuhn.\n")
    assert read_notes(tmp_path) == {"results/cpu/experiments/main": "It shows x.",
                                    "results/quick/experiments/kuhn": "Kuhn."}


def test_every_number_of_the_notes_is_in_a_file_it_cites():
    unbacked = {folder: numbers for folder, note in read_notes(ROOT).items()
                if (numbers := unbacked_numbers(folder, note, ROOT))}
    assert unbacked == {}, "results/notes.md: numbers no cited report or table holds"


def test_a_note_number_is_backed_by_the_value_not_the_spelling(tmp_path):
    (tmp_path / "results/a").mkdir(parents=True)
    (tmp_path / "results/cpu/b").mkdir(parents=True)
    (tmp_path / "results/a/report.md").write_text("| bati | 0.490 | 1,234.5 |\n")
    (tmp_path / "results/cpu/b/table.csv").write_text("method,share\nbati,0.85\n")
    note = "BATI 0.49 and 1234.5; its state term on 85% (`results/cpu/b`); FOCAL 0.48, 12%."
    assert unbacked_numbers("results/a", note, tmp_path) == ["0.48", "12%"]
    assert unbacked_numbers("results/a", "on 85%.", tmp_path) == ["85%"]  # cpu/b is not cited


def test_every_experiment_study_has_its_stored_plan():
    """`bati claims` and `bati results` read the plans the reports stored: a report without one is stale."""
    missing = [s.report for s in studies(ROOT) if s.experiment is not None and s.plan(ROOT) is None]
    assert missing == [], "write the reports again: `bati results --reports`"


def test_study_command_names_what_plans_its_cells():
    study = Study(Path("results/quick/x/main"), "q", "main", "quick", ("steps=12000",), seeds=(0,),
                  families=("HopperParam",))
    assert study.command_line() == ("bati experiment main --scale quick --seeds 0 --families HopperParam "
                                    "--settings steps=12000 --out-dir results/quick/x")


def test_short_device_names():
    assert _short_device("cpu: 2-core Intel(R) Xeon(R) Processor @ 2.80GHz, AVX-512 (x86_64) x1") == \
        "cpu: 2-core Intel Xeon"
    assert _short_device("gpu: NVIDIA H200") == "gpu: NVIDIA H200"


def test_results_refuses_a_root_without_results(tmp_path, capsys):
    assert main(["results", "--root", str(tmp_path)]) == 2
    assert "not a directory" in capsys.readouterr().err


def _kuhn_study_tree(root: Path) -> Study:
    """A results tree with one KuhnPoker study: two finished runs and one damaged eval.json."""
    from bati.experiments.index import STORES

    (root / STORES["quick"] / "kuhn").mkdir(parents=True)
    (root / STORES["quick"] / "kuhn" / "report.md").write_text("# kuhn\n")
    for seed, text in ((0, None), (1, None), (2, "{not json")):
        run = root / STORES["quick"] / "KuhnPoker" / "abc" / f"bati-seed{seed}"
        run.mkdir(parents=True)
        record = {"family": "KuhnPoker", "method": "bati", "seed": seed, "p_test_return": 0.1, "p_train_return": 0.1,
                  "commit": "abc", "device": "cpu", "wall_time_s": 60.0}
        (run / "eval.json").write_text(text or json.dumps(record))
    return next(s for s in studies(root) if s.experiment == "kuhn")


def test_the_index_reads_a_study_without_a_stored_plan_and_names_a_damaged_cell(tmp_path):
    """A report written before reports stored their plan (no plan.json): its cells are counted from its files,
    and a damaged eval.json is named, not dropped without a word."""
    from bati.experiments.index import summarise
    from bati.report.runs import ReportWarning

    study = _kuhn_study_tree(tmp_path)
    assert study.plan(tmp_path) is None
    with pytest.warns(ReportWarning, match=r"bati-seed2/eval.json"):
        summary = summarise(study, tmp_path)
    assert (summary.finished, summary.seeds) == (2, (0, 1))


def test_results_writes_all_its_pages_or_none(tmp_path, monkeypatch):
    import os

    from bati.errors import PathError
    from bati.experiments.index import RESULTS_PAGE, write_results

    _kuhn_study_tree(tmp_path)
    (tmp_path / "docs").mkdir()
    (tmp_path / INDEX).write_text("old index\n")
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if Path(path).name == "docs" and mode & os.W_OK
                        else real(path, mode, **kw))
    with pytest.raises(PathError, match="docs"):
        write_results(tmp_path, readme=False)
    assert (tmp_path / INDEX).read_text() == "old index\n" and not (tmp_path / RESULTS_PAGE).exists()
