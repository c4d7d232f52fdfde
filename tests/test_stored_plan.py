"""The plan an experiment's report stores (plan.json): what `bati claims` and `bati results` read instead of
planning again, without JAX."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bati.report.probes import Probe
from bati.report.runs import ReportWarning
from bati.report.stored_plan import PLAN_FILE, PlanFileError, PlannedCell, StoredPlan, read_plan


def _plan(root: Path) -> StoredPlan:
    cells = tuple(PlannedCell(f"id{seed}", f"AntDir/bati/seed{seed}", "AntDir", "bati", seed, 1.0, 200, "per-task",
                              root / "results" / "AntDir" / "cpu-eps1-abc" / f"bati-seed{seed}",
                              (Probe(eval_context_length=50),) if seed == 0 else ())
                  for seed in (0, 1, 2))
    return StoredPlan("main", "cpu", (0, 1, 2), ("steps=12000",), cells, selection=("id0", "id2"))


def test_a_stored_plan_reads_back_with_run_dirs_relative_to_its_report(tmp_path):
    plan = _plan(tmp_path)
    path = plan.write(tmp_path / "results" / "main")
    record = json.loads(path.read_text())
    assert record["cells"][0]["run_dir"] == "../AntDir/cpu-eps1-abc/bati-seed0"
    assert read_plan(tmp_path / "results" / "main") == plan
    (tmp_path / "results").rename(tmp_path / "moved")  # a results tree moved or cloned reads the same
    moved = read_plan(tmp_path / "moved" / "main")
    assert moved.cells[2].run_dir == tmp_path / "moved" / "AntDir" / "cpu-eps1-abc" / "bati-seed2"
    assert moved.cells[0].probes == (Probe(eval_context_length=50),)
    assert [c.seed for c in moved.selected()] == [0, 2]


def test_no_plan_is_none_and_a_damaged_one_is_one_clear_error(tmp_path):
    assert read_plan(tmp_path) is None
    (tmp_path / PLAN_FILE).write_text("{not json")
    with pytest.raises(PlanFileError, match=r"plan.json is unreadable .*bati results --reports"):
        read_plan(tmp_path)
    (tmp_path / PLAN_FILE).write_text(json.dumps({"format": 99}))
    with pytest.raises(PlanFileError, match="format 99"):
        read_plan(tmp_path)


def test_a_cell_result_is_its_eval_json_none_while_unfinished_and_a_damaged_one_is_named(tmp_path):
    cell = _plan(tmp_path).cells[0]
    assert cell.result() is None
    cell.run_dir.mkdir(parents=True)
    (cell.run_dir / "eval.json").write_text("{")
    with pytest.warns(ReportWarning, match="bati-seed0/eval.json"):
        assert cell.result() is None
    (cell.run_dir / "eval.json").write_text(json.dumps({"family": "AntDir", "method": "bati", "seed": 0,
                                                        "p_test_return": 1.5, "p_train_return": 2.0}))
    assert cell.result().p_test_return == 1.5


def test_a_finished_cell_reads_its_run_probes_and_likelihood_split_in_one_place(tmp_path):
    from bati.report.likelihood import LIKELIHOOD_FILE, SOURCES, TERMS
    from bati.report.probes import probe_path

    cell = _plan(tmp_path).cells[0]
    assert cell.read() is None  # not finished
    cell.run_dir.mkdir(parents=True)
    (cell.run_dir / "eval.json").write_text(json.dumps({"family": "AntDir", "method": "bati", "seed": 0,
                                                        "p_test_return": 1.5, "p_train_return": 2.0,
                                                        "diagnostics": {"state_weight": 0.25}}))
    finished = cell.read()
    assert (finished.run.p_test_return, finished.run.diagnostics) == (1.5, {"state_weight": 0.25})
    assert finished.probes == () and finished.likelihood_split is None  # none saved yet
    probe = cell.probes[0]
    saved = {"probe": {"eval_context_length": 50}, "p_test_return": 0.5, "context_length": 50}
    probe_path(cell.run_dir, probe).parent.mkdir()
    probe_path(cell.run_dir, probe).write_text(json.dumps(saved))
    split = {f"{s}_{t}_{k}": 0.1 for s in SOURCES for t in TERMS for k in ("error", "picks_collector")}
    (cell.run_dir / LIKELIHOOD_FILE).write_text(json.dumps(split))
    finished = cell.read()
    assert finished.probes == ((probe, saved),) and finished.likelihood_split == split


def test_the_report_stores_the_plan_its_tables_cover(tmp_path):
    from bati.experiments.pipeline import plan_experiment
    from bati.experiments.report import experiment_report
    from bati.experiments.specs import get_spec

    spec = get_spec("context-length")
    whole = plan_experiment(spec, "quick", tmp_path, seeds=(0, 1))
    chosen = plan_experiment(spec, "quick", tmp_path, seeds=(0, 1), methods=("bati",))
    experiment_report(whole, tmp_path / spec.name, selection=chosen)
    stored = read_plan(tmp_path / spec.name)
    assert stored == whole.stored(chosen)
    assert len(stored.cells) == len(whole.cells) and {c.method for c in stored.selected()} == {"bati"}
    assert all(c.probes for c in stored.cells)  # Table 1's context lengths, probed on every cell
    assert {c.run_dir for c in stored.cells} == {cell.config.out_dir for cell in whole.cells}


def test_the_commands_that_read_results_import_no_jax(tmp_path):
    (tmp_path / "results").mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("<!-- headline -->\n<!-- /headline -->\n")
    code = ("import sys\nfrom bati.cli import main\n"
            f"codes = [main(['claims', '--root', {str(tmp_path)!r}]), main(['results', '--root', {str(tmp_path)!r}]),"
            f" main(['report', {str(tmp_path / 'results')!r}])]\n"
            "print(codes, sorted(m for m in ('jax', 'flax', 'optax') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert out.stdout.strip().splitlines()[-1] == "[0, 0, 2] []", out.stdout + out.stderr
