"""The committed results, indexed: `bati results`.

Every folder of results/ that holds a report is a `Study`: the question it answers and how its runs were
made (an experiment at a scale with its settings, or `bati report` over a folder of runs). From the
studies and their records this module writes

- `results/README.md`: per study the command, the scale, cells finished of planned, seeds, commits,
  devices, summed wall time and the link to its report; then the folders that hold other records;
- `docs/results.md`: per experiment, at the largest scale with at least half its cells finished, its
  first table (from its report), the command, the link, and what it shows (hand-written, from
  `results/notes.md`, one `## <report folder>` section per study);
- the README's headline table (between `<!-- headline -->` and `<!-- /headline -->`): the IQM of the
  normalised p_test score with its 95% stratified-bootstrap interval, per method and family, of the
  `main` experiment at the largest scale where it is that complete.

`regenerate_reports` rewrites every experiment study's report from its cells (the same numbers, or the
diff shows what moved); `pack_results` packs finished runs' metrics.jsonl (bati.io.pack_jsonl);
`update_results` is the command, all three in turn.
"""

from __future__ import annotations

import os
import re
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from bati.envs import FamilyUnavailable
from bati.errors import PathError
from bati.experiments.specs import MAIN_METHODS, SCALES, SPECS, get_spec
from bati.experts.kinds import CONDITIONED_SETTING as CONDITIONED
from bati.experts.kinds import data_label
from bati.io import atomic_write_text, pack_jsonl, short_commit
from bati.report.runs import ReportWarning, RunResult, find_eval_files, jobs_wall_time, read_results
from bati.report.stored_plan import StoredPlan, read_plan

RESULTS = Path("results")
NOTES = RESULTS / "notes.md"
INDEX = RESULTS / "README.md"
RESULTS_PAGE = Path("docs/results.md")
README = Path("README.md")
HEADLINE = ("<!-- headline -->", "<!-- /headline -->")
ENOUGH = 0.5
"""The share of an experiment's planned cells that must be finished before its scale is the one shown."""


@dataclass(frozen=True)
class Study:
    """One report folder of results/: what it asks and how its runs were made."""

    report: Path
    """The folder holding report.md, relative to the project root."""
    question: str
    experiment: str | None = None
    """The experiment it reports (`bati experiment`); None: `bati report` over the runs in `runs`."""
    scale: str = "quick"
    settings: tuple[str, ...] = ()
    seeds: tuple[int, ...] | None = None
    methods: tuple[str, ...] = ()
    families: tuple[str, ...] = ()
    """The experiment's methods and families it ran (default: all of them)."""
    out_dir: Path | None = None
    """The experiment's results directory (default: the report folder's parent)."""
    runs: Path | None = None
    """`bati report` folders: where its runs are (default: the report folder's parent)."""
    command: str = ""
    """How its runs were made, where no experiment command says it."""
    data_root: str | None = None
    """The experiment's --data-root, where it is not the default (a collection of other sizes needs its own)."""
    store: bool = False
    """A scale's own experiments directory (results/<scale>/experiments): docs/results.md picks from these."""

    @property
    def cells_dir(self) -> Path:
        return self.out_dir or self.report.parent

    def plan(self, root: Path) -> StoredPlan | None:
        """The experiment's plan as its report stored it (None: a report written before reports stored it)."""
        return read_plan(root / self.report) if self.experiment is not None else None

    def job(self):
        """The `bati experiment` job that ran its cells (`command_line`)."""
        from bati.experiments.experiment import ExperimentJob

        return ExperimentJob(self.experiment, self.scale, seeds=self.seeds, methods=self.methods, families=self.families,
                             settings=self.settings, out_dir=self.cells_dir, data_root=Path(self.data_root or "data"))

    def command_line(self) -> str:
        if self.experiment is None:
            return self.command
        parts = ["bati experiment", self.experiment, "--scale", self.scale]
        for name in ("seeds", "methods", "families"):
            if getattr(self, name):
                parts += [f"--{name}", *map(str, getattr(self, name))]
        if self.settings:
            parts += ["--settings", *self.settings]
        if self.data_root:
            parts += ["--data-root", self.data_root]
        return " ".join(parts + ["--out-dir", str(self.cells_dir)])


STORES = {"quick": RESULTS / "quick/experiments", "cpu": RESULTS / "cpu/experiments",
          "paper": RESULTS / "paper/experiments"}
"""Each scale's experiments directory: a report folder named after an experiment there is that experiment."""
TWELVE_K = RESULTS / "quick/locomotion-12k"
"""The quick scale's data and networks with 4x its steps (12,000): the same experiments, one more scale."""

CLUB_ANY = "csro.club_negatives=any-task"
ERTRL_FIRST = ("ertrl.metric_weight=1.0", "ertrl.latent_activation=none")
BEFORE_PER_TASK_DEFAULT = {
    RESULTS / "quick/experiments": ("main", "noise", "context-length", "ood-tasks", "splits", "interpolated-contexts",
                                    "kuhn", "state-term", "unknown-tasks", "refined-inference", "self-collected"),
    TWELVE_K: ("main", "noise", "context-length", "ood-tasks", "splits", "interpolated-contexts", "noiseless-hopper"),
    RESULTS / "cpu/experiments": ("noise", "context-length", "ood-tasks"),
    RESULTS / "paper/experiments": ("kuhn",),
}
"""The experiments of each store that ran before per-task experts became the default data: on the task-conditioned
expert's. Their `main` reports moved to main-conditioned (`DECLARED`), as its per-task cells share the directory."""
_OLD_SETTINGS = {
    RESULTS / "quick/experiments/main": (CLUB_ANY, *ERTRL_FIRST),
    RESULTS / "quick/experiments/noise": (CLUB_ANY, *ERTRL_FIRST),
    RESULTS / "quick/experiments/kuhn": (CLUB_ANY, *ERTRL_FIRST),
    **{RESULTS / "quick/experiments" / name: (CLUB_ANY,)
       for name in ("self-collected", "ood-tasks", "context-length", "splits")},
    **{TWELVE_K / name: (CLUB_ANY,)
       for name in ("main", "noiseless-hopper", "noise", "ood-tasks", "context-length", "splits")},
}
DAY_DEFAULTS = {store / name: (*_OLD_SETTINGS.get(store / name, ()), CONDITIONED)
                for store, names in BEFORE_PER_TASK_DEFAULT.items() for name in names}
"""Report folders whose cells ran with the defaults of their day: the settings that plan those cells (the
task-conditioned expert's data, the default before 2026-12-06; CSRO's CLUB negatives drawn from any task, the
default before 2026-11-25; ER-TRL's first form: its FOCAL term at weight 1.0 and unbounded latents;
docs/methods.md)."""

DECLARED = (
    *(Study(RESULTS / f"{scale}/experiments/main-conditioned", SPECS["main"].title + " (one task-conditioned expert's "
            "data: the default before per-task experts)", "main", scale, (CONDITIONED,), out_dir=STORES[scale],
            store=True) for scale in ("cpu", "paper")),
    Study(RESULTS / "cpu/experts-40k/experts", "Table 4 on HalfCheetahDir with per-task experts of 40k transitions "
          "each (a third of the paper's Oracle; the experts since retrained; the conditioned cells are the experts "
          "study's)", "experts", "cpu", methods=("bati", "bati-r", "recon", "focal", "unicorn", "csro", "oracle"),
          families=("HalfCheetahDir",)),
    Study(RESULTS / "cpu/experiments/main-ertrl-unbounded", "ER-TRL without the tanh on its latent (the paper's "
          "form)", "main", "cpu", ("ertrl.latent_activation=none", CONDITIONED), methods=("er-trl",),
          out_dir=RESULTS / "cpu/experiments"),
    Study(RESULTS / "cpu/total-data/experts", "Table 3's dataset size read in total: 50 episodes per training "
          "task on HalfCheetahDir instead of 1,000 (per-task data: the 40k experts)", "experts", "cpu", ("episodes_per_task=50",),
          methods=("bati", "bati-r", "focal", "csro", "unicorn", "recon", "oracle"), families=("HalfCheetahDir",),
          data_root="data-total"),
    Study(RESULTS / "cpu/same-task-value/experts", "FOCAL with tasks of equal parameters as one task in its metric "
          "loss (HalfCheetahDir's same-direction tasks are not pushed apart; the 40k per-task experts' data)", "experts", "cpu",
          ("focal.same_task=value",), methods=("focal",), families=("HalfCheetahDir",)),
    Study(RESULTS / "cpu/focal-distance/main", "FOCAL with the root-mean distance in its metric loss", "main", "cpu",
          ("focal.distance=root-mean", CONDITIONED), methods=("focal",), families=("AntDir",), seeds=(0,)),
    Study(RESULTS / "cpu/tanh/main", "FOCAL with a tanh on its latent", "main", "cpu",
          ("focal.latent_activation=tanh", CONDITIONED), seeds=(0,), methods=("focal",), families=("AntDir",)),
    Study(RESULTS / "quick/convergence/main", "HopperParam at the quick scale with 4x its steps: converged?", "main",
          "quick", ("steps=12000", CLUB_ANY, CONDITIONED), families=("HopperParam",)),
    Study(RESULTS / "quick/convergence/kuhn", "Kuhn poker at the quick scale with 4x its steps: converged?", "kuhn",
          "quick", ("steps=12000", CLUB_ANY, CONDITIONED)),
    Study(RESULTS / "quick/hopper-data80/main", "HopperParam with 80 episodes per task instead of 20 (12k steps)",
          "main", "quick", ("steps=12000", "episodes_per_task=80", CONDITIONED), methods=("bati", "focal", "recon", "no-context",
          "oracle"), families=("HopperParam",)),
    Study(RESULTS / "quick/kuhn-context200/kuhn", "Kuhn poker with contexts of 200 transitions", "kuhn", "quick",
          ("eval_context_length=200", CLUB_ANY, CONDITIONED),
          methods=("bati", "bati-r", "recon", "unicorn", "csro", "focal", "oracle", "no-context")),
    Study(RESULTS / "quick/bati-run/report", "`bati run`'s default: BATI, BATI-R and Recon on PointGoal (per-task "
          "experts' data)", command="bati run --out-dir results/quick/bati-run"),
    Study(RESULTS / "quick/bati-run-conditioned/report", "`bati run` on one task-conditioned expert's data (its "
          "default before per-task experts)",
          command="bati run --settings experts=conditioned --out-dir results/quick/bati-run-conditioned"),
    Study(RESULTS / "quick/pointgoal-convergence/report", "PointGoal at 3k and 12k steps: converged?",
          command="bati sweep --methods bati bati-r recon no-context --settings experts=conditioned steps=3000|12000 "
                  "--out-dir results/quick/pointgoal-convergence; bati report results/quick/pointgoal-convergence"),
    Study(RESULTS / "own-data/goalline", "Your own data: GoalLine through the Minari path (docs/own-data.md)",
          command="python examples/own_data_goalline.py --out results/own-data/goalline --steps 3000 --episodes 30 "
                  "--seeds 0 1 2"),
)
"""The report folders that are not an experiment of a scale's experiments directory."""

OTHER_RECORDS = {
    RESULTS / "experts": "training logs of the shipped experts (`bati experts train`)",
    RESULTS / "diagnostics": "measurements of the benchmarks/ scripts (task sensitivity, latent scale, ER-TRL balance, "
                             "expert training)",
}


def studies(root: Path = Path(".")) -> list[Study]:
    """Every study: the experiments found in each scale's directory and in the 12k one, then the declared ones."""
    found = []
    for scale, store in [*STORES.items(), ("quick", TWELVE_K)]:
        for name in SPECS:
            if (root / store / name / "report.md").exists():
                settings = (("steps=12000",) if store == TWELVE_K else ()) + DAY_DEFAULTS.get(store / name, ())
                title = SPECS[name].title + (" (4x the quick scale's steps)" if store == TWELVE_K else "")
                found.append(Study(store / name, title, name, scale, settings, store=store != TWELVE_K))
    return found + [s for s in DECLARED if (root / s.report / "report.md").exists()]


def report_folders(root: Path = Path(".")) -> list[Path]:
    """Every folder under results/ that holds a report.md (relative to root)."""
    return sorted(p.parent.relative_to(root) for p in (root / RESULTS).rglob("report.md"))


@dataclass
class Summary:
    study: Study
    finished: int
    planned: int
    seeds: tuple[int, ...]
    commits: list[str]
    uncommitted: int
    """Runs whose code had uncommitted changes."""
    devices: Counter
    wall_min: float


def summarise(study: Study, root: Path = Path(".")) -> Summary:
    """The study's numbers from its records: finished cells (of planned), commits, devices, wall time."""
    plan = study.plan(root)
    if plan is not None:
        cells = plan.selected()  # the study's own cells (its methods and families), not the folder's others
        runs = [run for run in (cell.result() for cell in cells) if run is not None]
        planned, seeds = len(cells), plan.seeds
    elif study.experiment is not None:  # no stored plan: every run of its families in its folder
        families = {f for part in get_spec(study.experiment).parts for f in part.families}
        runs = [r for r in _read_runs(root / study.cells_dir) if r.family in families]
        planned, seeds = len(runs), tuple(sorted({r.seed for r in runs}))
    else:
        runs = _read_runs(root / (study.runs or study.report.parent))
        planned, seeds = len(runs), tuple(sorted({r.seed for r in runs}))
    commits = [r.commit for r in runs if r.commit]
    wall = jobs_wall_time(((r.path.parent.parent, r.method), r.total_wall_time()) for r in runs)
    return Summary(study, len(runs), planned, seeds, sorted({short_commit(c).removesuffix("-dirty") for c in commits}),
                   sum(r.uncommitted_changes for r in runs), Counter(_short_device(r.device) for r in runs if r.device),
                   wall / 60)


def _read_runs(directory: Path) -> list[RunResult]:
    """The results of every eval.json under `directory` (`read_results`); a damaged one is named (ReportWarning), not
    dropped silently."""
    runs = []
    for path in find_eval_files(directory):
        try:
            runs += read_results(path)
        except (OSError, ValueError, TypeError, AttributeError) as err:
            warnings.warn(f"skipping {path}: {err}", ReportWarning, stacklevel=2)
    return runs


def _short_device(device: str) -> str:
    """"cpu: 2-core Intel(R) Xeon(R) Processor, AVX-512 (x86_64) x1" -> "cpu: 2-core Intel Xeon"."""
    text = re.sub(r"\(R\)|\(TM\)|Processor|CPU @ [\d.]+GHz|@ [\d.]+GHz", "", device)
    text = re.sub(r",.*| \(x86_64\).*| x\d+$", "", text)
    return re.sub(r"\s+", " ", text).strip()


# --- results/README.md -----------------------------------------------------------------------------
def index_markdown(summaries: list[Summary], root: Path = Path(".")) -> str:
    lines = ["# Results", "",
             "Generated by `bati results` from the records under results/ (do not edit: rerun it). Every run "
             "directory keeps config.json, eval.json, eval.jsonl, likelihood.json where probed, and its training log "
             "packed as metrics.jsonl.gz (floats to 4 significant digits). What each study shows: "
             "[docs/results.md](../docs/results.md); the paper's claims decided: [docs/claims.md](../docs/claims.md).",
             ""]
    for scale in SCALES + ("other",):
        rows = [s for s in summaries if (s.study.scale if s.study.experiment else "other") == scale]
        if not rows:
            continue
        lines += [f"## {scale}" if scale != "other" else "## Runs reported by `bati report` and examples", "",
                  "| study | question | cells | seeds | commits | devices | wall time | command |",
                  "|---|---|---|---|---|---|---|---|"]
        for s in rows:
            link = f"[{s.study.report.relative_to(RESULTS)}]({s.study.report.relative_to(RESULTS)}/report.md)"
            commits = f"{len(s.commits)}" + (f" ({s.uncommitted} runs with uncommitted changes)" if s.uncommitted
                                             else "")
            devices = "; ".join(f"{d} ({n})" for d, n in sorted(s.devices.items())) or "unknown"
            seeds = " ".join(map(str, s.seeds)) or "–"
            lines.append(f"| {link} | {s.study.question} | {s.finished} / {s.planned} | {seeds} | {commits} | "
                         f"{devices} | {s.wall_min:.0f} min | `{s.study.command_line()}` |")
        lines.append("")
    lines += ["## Other records", ""]
    lines += [f"- [{p.relative_to(RESULTS)}]({p.relative_to(RESULTS)}/): {text}"
              for p, text in OTHER_RECORDS.items() if (root / p).exists()]
    return "\n".join(lines) + "\n"


# --- docs/results.md -----------------------------------------------------------------------------
def first_table(report: str) -> str:
    """The first Markdown table of a report, with the bold title above it."""
    lines = report.splitlines()
    start = next((i for i, line in enumerate(lines) if line.startswith("|")), None)
    if start is None:
        return ""
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    title = next((lines[i] for i in range(start - 1, max(start - 4, -1), -1) if lines[i].startswith("**")), "")
    return "\n".join(([title, ""] if title else []) + lines[start:end])


def read_notes(root: Path = Path(".")) -> dict[str, str]:
    """results/notes.md: the hand-written "what it shows", one `## <report folder>` section per study."""
    path = root / NOTES
    if not path.exists():
        return {}
    notes, key = {}, None
    for line in path.read_text().splitlines():
        if line.startswith("## "):
            key = line[3:].strip()
            notes[key] = ""
        elif key is not None:
            notes[key] += line + "\n"
    return {k: v.strip() for k, v in notes.items()}


def study_data(study: Study) -> str:
    """Which experts collected a study's data, in words (an experiment whose families fall back to the
    task-conditioned expert, docs/experiments.md, says so in its report)."""
    parts = get_spec(study.experiment).parts if study.experiment else ()
    if len({s for part in parts for s in part.settings if s.startswith("experts=")}) > 1:
        return "both kinds of experts' data"
    families = {family for part in parts for family in part.families}
    kind = "conditioned" if CONDITIONED in study.settings else "per-task"
    return data_label(kind, *families) if len(families) == 1 else data_label(kind)


_NUMBER = re.compile(r"(?<![\w.])[-+]?\d[\d,]*(?:\.\d+%?|%)(?!\d|\.\d)")
_CITED = re.compile(r"`(?:results/)?((?:quick|cpu|paper|own-data)/[\w./-]+?)`")


def _numbers(text: str) -> list[tuple[str, float]]:
    """The decimals and percentages of a text as (as written, value): 85% is 0.85."""
    found = []
    for token in _NUMBER.findall(text):
        value = float(token.replace(",", "").rstrip("%"))
        found.append((token, value / 100 if token.endswith("%") else value))
    return found


def unbacked_numbers(folder: str, note: str, root: Path = Path(".")) -> list[str]:
    """The numbers of a hand-written note that no file it cites holds: the note's report folder and every
    results folder it names in backticks (their report.md and table.csv). Values compare, not spellings: 0.49
    is the file's 0.490, and 85% its share 0.85."""
    held = set()
    for cited in [root / folder, *(root / RESULTS / path for path in _CITED.findall(note))]:
        for name in ("report.md", "table.csv"):
            if (cited / name).is_file():
                held.update(round(value, 6) for _, value in _numbers((cited / name).read_text()))
    return [token for token, value in _numbers(note) if round(value, 6) not in held]


def _size(study: Study) -> int:
    """Scales from the smallest: quick, quick with 4x its steps (12k), cpu, paper."""
    return {"quick": 0, "cpu": 2, "paper": 3}[study.scale] + (study.report.parent == TWELVE_K)


def shown(summaries: list[Summary]) -> list[tuple[Summary, list[Summary]]]:
    """Per experiment (in the experiments' order): its study at the largest scale with at least ENOUGH of its cells
    finished (at one scale, the paper's data before one task-conditioned expert's), and its other studies at that
    scale or larger (scales' own directories and the 12k one)."""
    candidates = [s for s in summaries if s.study.experiment is not None and s.planned
                  and (s.study.store or s.study.report.parent == TWELVE_K)]
    out = []
    for name in SPECS:
        mine = sorted((s for s in candidates if s.study.experiment == name),
                      key=lambda s: (_size(s.study), CONDITIONED not in s.study.settings))
        enough = [s for s in mine if s.finished >= ENOUGH * s.planned]
        if enough:  # beside it: the larger scales' studies and the same scale's other settings
            out.append((enough[-1], [s for s in mine if s is not enough[-1] and _size(s.study) >= _size(enough[-1].study)]))
    return out


def results_markdown(summaries: list[Summary], root: Path = Path(".")) -> str:
    notes = read_notes(root)
    lines = ["# Results", "",
             "Generated by `bati results` (do not edit: the notes are in results/notes.md). Per experiment, the "
             "largest scale at which at least half of its cells are finished; every other study, scale and command "
             "is in [results/README.md](../results/README.md), the verdicts on the paper's claims in "
             "[claims.md](claims.md). Numbers: mean ± std over seeds of each run's mean of its last 5 evaluations "
             "(the reports' convention); the reports add rliable's IQM and probability of improvement.", ""]
    for s, larger in shown(summaries):
        report = root / s.study.report / "report.md"
        spec = SPECS[s.study.experiment]
        scale = "quick scale, 4x its steps" if s.study.report.parent == TWELVE_K else f"{s.study.scale} scale"
        lines += [f"## {spec.name}: {spec.title} ({scale}, {study_data(s.study)})", "",
                  f"`{s.study.command_line()}`: {s.finished} of {s.planned} cells, seeds "
                  f"{' '.join(map(str, s.seeds))}; [report](../{s.study.report}/report.md)."
                  + "".join(f" At the {o.study.scale} scale{' (12k steps)' if _size(o.study) == 1 else ''}"
                            f"{'' if study_data(o.study) == study_data(s.study) else ' on ' + study_data(o.study)} "
                            f"so far: {o.finished} of {o.planned} cells, [report](../{o.study.report}/report.md)."
                            for o in larger), ""]
        note = notes.get(str(s.study.report))
        if note:
            lines += [note, ""]
        lines += [first_table(report.read_text()), ""]
    return "\n".join(lines)


# --- the README's headline -------------------------------------------------------------------------
def headline_markdown(root: Path = Path(".")) -> str:
    """The IQM of the normalised p_test score per method and family of `main`: on the paper's data (per-task
    experts), then on one task-conditioned expert's; each at the largest scale where at least ENOUGH of its cells
    are finished, else the largest with any (its missing families named)."""
    from bati.report.claim_records import CONDITIONED_DATA, SOURCES

    mains = {(s.cells_dir, s.scale, s.settings): s for s in studies(root) if s.experiment == "main"}
    tables = []
    for data, title in (("", "The paper's data (one SAC expert per training task, App. C.2)"),
                        (CONDITIONED_DATA, "One task-conditioned expert's data")):
        found = []
        for source in reversed([s for s in SOURCES if s.data == data and s.out_dir == STORES.get(s.scale)]):
            study = mains.get((source.out_dir, source.scale, source.settings))
            summary = summarise(study, root) if study is not None else None
            if summary is not None and summary.finished:
                found.append((source, study, summary))
        enough = [f for f in found if f[2].finished >= ENOUGH * f[2].planned]
        if found:
            tables.append(_headline_table(*(enough or found)[0], title, root))
    return "\n".join(tables) if tables else "No scale has the main experiment's cells finished yet.\n"


def _headline_table(source, study: Study, summary: Summary, title: str, root: Path) -> str:
    from bati.report.claim_records import gather

    records = [r for r in gather("main", source, root) if r.seed in summary.seeds]
    families = sorted({r.family for r in records})
    plan = study.plan(root)
    planned = dict.fromkeys(cell.family for cell in (plan.selected() if plan is not None else ()))
    missing = [f for f in planned if f not in families]
    lines = [f"**{title}**: p_test score (normalised: 0 = random policy, 1 = the experts), IQM [95% CI] over seeds "
             f"{' '.join(map(str, summary.seeds))}, {source.scale} scale ({summary.finished} of {summary.planned} "
             f"cells{'; not run yet: ' + ', '.join(missing) if missing else ''}; [report]({study.report}/report.md)).",
             "", "| method | " + " | ".join(families) + " |", "|---|" + "---|" * len(families)]
    for method in MAIN_METHODS:
        cells = [score_cell([r.p_test for r in records if r.method == method and r.family == family])
                 for family in families]
        if any(c != "–" for c in cells):
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def score_cell(scores: list[float]) -> str:
    """One headline cell: the IQM [95% CI] of the seeds' scores; under MIN_SEEDS seeds their mean and how many."""
    from bati.report.convergence import MIN_SEEDS
    from bati.report.stats import iqm_interval

    if not scores:
        return "–"
    if len(scores) < MIN_SEEDS:
        return f"{sum(scores) / len(scores):.2f} ({len(scores)} seed{'s' if len(scores) > 1 else ''})"
    iqm, low, high = iqm_interval([[x] for x in scores])
    return f"{iqm:.2f} [{low:.2f}, {high:.2f}]"


def with_headline(readme: str, headline: str) -> str:
    start, end = HEADLINE
    if start not in readme or end not in readme:
        raise ValueError(f"README.md has no {start} ... {end} block for the headline table")
    before, rest = readme.split(start, 1)
    _, after = rest.split(end, 1)
    return f"{before}{start}\n{headline}{end}{after}"


def write_results(root: Path = Path("."), readme: bool = True) -> list[Path]:
    """results/README.md, docs/results.md and (readme) the README's headline table; the files written."""
    from bati.io import check_directory

    summaries = [summarise(s, root) for s in studies(root)]
    pages = {root / INDEX: index_markdown(summaries, root), root / RESULTS_PAGE: results_markdown(summaries, root)}
    if readme:
        pages[root / README] = with_headline((root / README).read_text(), headline_markdown(root))
    for path in pages:  # all the pages or none: every place is checked before the first is written
        check_directory(path.parent, f"the folder of {path.name}", writable=True)
        if path.exists() and not os.access(path, os.W_OK):
            raise PathError(f"{path} is not writable: nothing was written")
    for path, text in pages.items():
        atomic_write_text(path, text)
    return list(pages)


def regenerate_reports(root: Path = Path(".")) -> list[Path]:
    """Every experiment study's report written again from its cells (report-only); the report folders."""
    from bati.experiments.experiment import job_plans
    from bati.experiments.report import experiment_report

    done = []
    for study in studies(root):
        if study.experiment is not None:
            try:  # as `bati experiment ... --report-only` writes it: its cells, and every cell in its folder
                plan, whole = job_plans(study.job(), root / study.cells_dir)
            except FamilyUnavailable as err:  # its report stays as it is: say so, do the others
                warnings.warn(f"{study.report}/report.md not rewritten: {err}", ReportWarning, stacklevel=2)
                continue
            experiment_report(whole, root / study.report, command=study.command_line(), selection=plan)
            done.append(study.report)
    return done


def pack_results(root: Path = Path(".")) -> tuple[int, int]:
    """Pack the metrics.jsonl of every finished run under results/ (one with eval.json); (files, bytes saved)."""
    files, saved = 0, 0
    for eval_file in find_eval_files(root / RESULTS):
        log = eval_file.parent / "metrics.jsonl"
        if log.exists():
            before = log.stat().st_size
            saved += before - pack_jsonl(log).stat().st_size
            files += 1
    return files, saved


def update_results(root: Path = Path("."), reports: bool = False, pack: bool = False, *, console) -> None:
    """`bati results`: first pack the runs' logs (`pack`) and write the studies' reports again (`reports`),
    then the index pages; each step's result on the rich `console`."""
    if not (root / "results").is_dir():
        raise PathError(f"{root / 'results'} is not a directory: --root names the project directory")
    if pack:
        files, saved = pack_results(root)
        console.print(f"packed {files} metrics.jsonl file(s), {saved / 2**20:.1f} MiB saved")
    if reports:
        for folder in regenerate_reports(root):
            console.print(f"report: {folder}/report.md")
    for path in write_results(root):
        console.print(f"written: {path}")
