"""Reading training results: every `eval.json` under a directory, tolerant of old and broken files."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from bati.errors import BatiWarning
from bati.io import read_jsonl

# Config keys that do not make two runs' settings different: what a table compares, and what is not part of
# a run's identity (bati.config.NOT_IDENTITY: where files went, how many processes evaluated). Keys starting
# with "method_" are ignored as well.
COMPARED_CONFIG_KEYS = frozenset({"method", "seed", "method_config"})
REQUIRED_KEYS = ("family", "method", "seed", "p_test_return", "p_train_return")
# A run on your own datasets (family "own") has no p_train / p_test returns but these held-out metrics
# (evaluate.OfflineEvaluator); it needs the first of them instead of the returns.
HELD_OUT_KEYS = ("held_out_inference_accuracy", "held_out_representation_loss", "held_out_return")
# A run that evaluated test-time rules beside its own inference (bati-r and bati-auto in a bati run) holds each
# rule's evaluations under eval.json's "rules" (rule -> these keys); the rest of the file is shared.
RULE_KEYS = ("p_test_return", "p_train_return", "p_test_inference_error", "p_train_inference_error",
             "p_test_task_returns", "p_train_task_returns", "evaluations_averaged", "curve", "diagnostics",
             "wall_time_s")


def _comparable(config: dict) -> dict:
    """A run's recorded config in today's form (older records read by `bati.records`), without the settings at
    the value runs had before they existed and its method's hyperparameters only where they differ from the
    defaults on its family: runs of different methods at the same setting share a table, and a non-default one
    (e.g. csro.club_weight) is a setting of its own, named in the table's title."""
    from bati.records import read_record

    return read_record(config, compact=True)


class ReportWarning(BatiWarning):
    """A result file that was skipped or a group that is incomplete (one of bati's warnings: the CLI prints
    it as one `warning:` line as it happens)."""


def _float(value) -> float:
    """A JSON number, null or missing as a float (NaN for null / missing / not a number)."""
    try:
        return float(value) if value is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


@dataclass
class RunResult:
    """One training run's `eval.json` (fields absent from older files are None / empty)."""

    path: Path
    family: str
    method: str
    seed: int
    p_test_return: float
    p_train_return: float
    p_test_inference_error: float = math.nan
    p_train_inference_error: float = math.nan
    scale: str | None = None
    steps: int | None = None
    evaluations_averaged: int | None = None
    p_test_task_returns: list[float] = field(default_factory=list)
    p_train_task_returns: list[float] = field(default_factory=list)
    curve: list[dict] = field(default_factory=list)
    config: dict | None = None
    reference_returns: dict | None = None
    data: dict | None = None
    device: str | None = None
    cpu_cores: int | None = None
    """The CPU cores the run could use (its affinity; older records: None)."""
    jax_version: str | None = None
    commit: str | None = None
    uncommitted_changes: bool = False
    """Its code differed from `commit` (older records: a commit ending in "-dirty")."""
    wall_time_s: float | None = None
    held_out: dict[str, float] = field(default_factory=dict)
    """A run on your own datasets: its HELD_OUT_KEYS (no p_train / p_test returns, which are NaN)."""
    diagnostics: dict[str, float] = field(default_factory=dict)
    """A method's own numbers, averaged like the returns (e.g. BATI-auto's calibrated state weight)."""

    @property
    def own_data(self) -> bool:
        return bool(self.held_out)

    @classmethod
    def from_dict(cls, raw: dict, path: Path, rule: str | None = None) -> RunResult:
        """The run's own results in its eval.json `raw`, or with `rule` those of a test-time rule it evaluated
        (ValueError where it holds none of it)."""
        if rule is not None and rule != raw.get("method"):
            raw = rule_view(raw, rule)
        own_data = "p_test_return" not in raw and HELD_OUT_KEYS[0] in raw
        required = REQUIRED_KEYS[:3] + (HELD_OUT_KEYS[:1] if own_data else REQUIRED_KEYS[3:])
        missing = [k for k in required if k not in raw]
        if missing:
            raise ValueError(f"missing key(s) {', '.join(missing)}")
        held_out = {k: raw[k] for k in HELD_OUT_KEYS if k in raw} if own_data else {}
        for key in ("p_test_return", "p_train_return") if not own_data else held_out:
            # a damaged value must not stand in for a run
            if isinstance(raw[key], bool) or not isinstance(raw[key], (int, float)) or not math.isfinite(raw[key]):
                raise ValueError(f"{key} is {raw[key]!r}, not a finite number")
        curve = raw.get("curve") or []
        if not isinstance(curve, list) or not all(isinstance(p, dict) and isinstance(p.get("step"), int)
                                                  for p in curve):
            raise ValueError("its curve is not a list of evaluations with integer steps")
        for key in ("p_test_task_returns", "p_train_task_returns"):
            if not isinstance(raw.get(key) or [], list):
                raise ValueError(f"{key} is not a list")
        refs = raw.get("reference_returns")
        if refs is not None:
            refs = {"random": _float(refs.get("random")), "expert": _float(refs.get("expert"))}
            finite = math.isfinite(refs["random"]) and math.isfinite(refs["expert"])
            if not finite or refs["random"] == refs["expert"]:
                refs = None  # unusable for normalisation
        config = raw.get("config")
        return cls(
            path=path, family=str(raw["family"]), method=str(raw["method"]), seed=int(raw["seed"]),
            p_test_return=_float(raw.get("p_test_return")), p_train_return=_float(raw.get("p_train_return")),
            p_test_inference_error=_float(raw.get("p_test_inference_error")),
            p_train_inference_error=_float(raw.get("p_train_inference_error")),
            scale=raw.get("scale"), steps=None if raw.get("steps") is None else int(raw["steps"]),
            evaluations_averaged=(None if raw.get("evaluations_averaged") is None
                                  else int(raw["evaluations_averaged"])),
            p_test_task_returns=list(raw.get("p_test_task_returns") or []),
            p_train_task_returns=list(raw.get("p_train_task_returns") or []),
            curve=list(raw.get("curve") or []), config=config if isinstance(config, dict) else None,
            reference_returns=refs, data=raw.get("data") if isinstance(raw.get("data"), dict) else None,
            device=raw.get("device"),
            cpu_cores=raw["cpu_cores"] if isinstance(raw.get("cpu_cores"), int) and raw["cpu_cores"] > 0 else None,
            jax_version=raw.get("jax_version"), commit=raw.get("commit"),
            uncommitted_changes=bool(raw.get("uncommitted_changes")) or "-dirty" in str(raw.get("commit")),
            wall_time_s=None if raw.get("wall_time_s") is None else _float(raw["wall_time_s"]),
            held_out={k: float(v) for k, v in held_out.items()},
            diagnostics=dict(raw["diagnostics"]) if isinstance(raw.get("diagnostics"), dict) else {},
        )

    @property
    def machine(self) -> str | None:
        """The device as reports name it: on a CPU with the cores the run used where its record has them, since
        one machine gives other numbers on one core than on two (docs/reliability.md)."""
        if self.device and self.cpu_cores is not None and self.device.startswith("cpu"):
            return f"{self.device}, {self.cpu_cores} core{'s' if self.cpu_cores > 1 else ''} used"
        return self.device

    def total_wall_time(self) -> float:
        """Seconds the run's job took over all its sessions (eval.json holds the last session's)."""
        return (self.wall_time_s or 0.0) + earlier_sessions_time(self.path.parent)

    def settings(self) -> dict:
        """The flattened config that decides the run's table (methods, seeds and paths left out).

        Without a saved config (older files) the settings are the summary's family, scale and steps.
        """
        if self.config is None:
            return {"family": self.family, "scale": self.scale, "steps": self.steps}
        from bati.config import NOT_IDENTITY

        ignored = COMPARED_CONFIG_KEYS | set(NOT_IDENTITY)
        flat = _flatten({k: v for k, v in _comparable(self.config).items()
                         if k not in ignored and not k.startswith("method_")})
        flat.setdefault("family", self.family)
        return flat

    def settings_key(self) -> str:
        return json.dumps(self.settings(), sort_keys=True, default=str)

    def normalised(self, value: float) -> float:
        """(value - random) / (expert - random); NaN without reference returns."""
        if self.reference_returns is None:
            return math.nan
        low, high = self.reference_returns["random"], self.reference_returns["expert"]
        return (value - low) / (high - low)


def rules_in(raw: dict) -> tuple[str, ...]:
    """The test-time rules whose evaluations an eval.json holds beside the run's own (none: ())."""
    rules = raw.get("rules")
    return tuple(rules) if isinstance(rules, dict) else ()


def rule_view(raw: dict, rule: str) -> dict:
    """An eval.json as the rule's own: its RULE_KEYS from `rules[rule]`, its method (in the config too) the rule."""
    rules = raw.get("rules")
    entry = rules.get(rule) if isinstance(rules, dict) else None
    if not isinstance(entry, dict):
        raise ValueError(f"it holds no evaluations of the test-time rule {rule!r}")
    shared = {k: v for k, v in raw.items() if k not in RULE_KEYS and k != "rules"}
    config = raw.get("config")
    return {**shared, **{k: entry[k] for k in RULE_KEYS if k in entry}, "method": rule,
            **({"config": {**config, "method": rule}} if isinstance(config, dict) else {})}


def read_results(path: Path) -> list[RunResult]:
    """The results in one eval.json: the run's own, then each test-time rule's it evaluated (`rules`)."""
    raw = json.loads(Path(path).read_text())
    if not isinstance(raw, dict):
        raise ValueError("not a JSON object")
    return [RunResult.from_dict(raw, path)] + [RunResult.from_dict(raw, path, rule) for rule in rules_in(raw)]


def _flatten(config: dict, prefix: str = "") -> dict:
    """Nested config dicts as dotted keys (e.g. iql.expectile); lists become tuples' JSON text."""
    flat = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{name}."))
        elif isinstance(value, list):
            flat[name] = json.dumps(value)
        else:
            flat[name] = value
    return flat


def earlier_sessions_time(run_dir: Path) -> float:
    """Seconds of a resumed run's earlier sessions (eval.json's wall_time_s is its last session's): each
    session's clock in metrics.jsonl (`wall_time`) restarts at 0, so the value before each restart counts."""
    try:
        clock = [r["wall_time"] for r in read_jsonl(Path(run_dir) / "metrics.jsonl") if "wall_time" in r]
    except (OSError, ValueError):
        return 0.0
    return float(sum(before for before, after in zip(clock, clock[1:]) if after < before))


def jobs_wall_time(times) -> float:
    """Seconds of the jobs behind (job, seconds) pairs, each job counted once: seeds trained as one vmapped
    job each record the job's time. A job is its key (a setting and method) and its time: seeds of one setting
    trained one per job (the cpu queue) record different times and count each (seconds rounded to 0.1 s)."""
    return float(sum({(job, round(seconds, 1)): seconds for job, seconds in times}.values()))


def find_eval_files(directory: Path) -> list[Path]:
    return sorted(Path(directory).rglob("eval.json"))


def load_runs(directory: Path) -> list[RunResult]:
    """The results of every readable `eval.json` under `directory` (recursively), sorted by path: each run's own,
    then its test-time rules' (`read_results`).

    A file that cannot be read or parsed, or lacks a required key, is skipped with a ReportWarning
    naming it. So is a second run with the same settings, method and seed (the first path is kept).
    """
    runs, seen = [], {}
    for path in find_eval_files(directory):
        try:
            found = read_results(path)
        except (OSError, ValueError, TypeError, AttributeError) as err:
            warnings.warn(f"skipping {path}: {err}", ReportWarning, stacklevel=2)
            continue
        for run in found:
            key = (run.settings_key(), run.method, run.seed)
            if key in seen:
                warnings.warn(f"skipping {path}{'' if run is found[0] else f' ({run.method})'}: same settings, "
                              f"method and seed as {seen[key]}", ReportWarning, stacklevel=2)
                continue
            seen[key] = path
            runs.append(run)
    return runs
