"""A probe's settings and its saved result, read without JAX (`bati.experiments.probes` runs probes).

A probe evaluates a finished run's final checkpoint under test-time settings other than the run's own
(Table 1's context lengths, Fig. 6's interpolated contexts, ...) and saves `<run>/probes/<name>.json` (one of
its test-time rules': `<run>/probes/<rule>/<name>.json`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from bati.errors import BatiError


class ProbeError(BatiError, ValueError):
    """A probe that cannot run (no finished run, bad setting): nothing was written."""


@dataclass(frozen=True)
class Probe:
    """Test-time settings that differ from the run's own evaluation."""

    eval_context_length: int | None = None
    """Transitions per context (default: the run's eval_context_length)."""
    context_mix: float | None = None
    """Share r of p_test transitions in an interpolated context (None: plain p_test and p_train)."""
    repeats: int = 5
    """Evaluations averaged (the runs' own numbers average their last 5)."""
    novelty: bool = False
    """Instead of returns: unknown-task detection (`bati.inference.novelty`: AUROC, flagged shares)."""
    refine_steps: int | None = None
    """BATI's refined inference: gradient steps after Eq. 8's arg-min (default: the method's, 0)."""
    latent_samples: int | None = None
    """BATI's N, the table samples Eq. 8 scores (default: the method's, 40)."""
    self_collect_every: int | None = None
    """Instead of given contexts: self-collected ones, z re-inferred every this many steps (`bati.online`)."""
    self_collect_episodes: int = 1
    """Consecutive episodes per task of a self-collected evaluation (z and the transitions carry over)."""

    @property
    def name(self) -> str:
        if self.novelty:
            return "novelty"
        parts = []
        if self.eval_context_length is not None:
            parts.append(f"C{self.eval_context_length}")
        if self.context_mix is not None:
            parts.append(f"mix{self.context_mix:g}")
        if self.latent_samples is not None:
            parts.append(f"N{self.latent_samples}")
        if self.refine_steps is not None:
            parts.append(f"refine{self.refine_steps}")
        if self.self_collect_every is not None:
            episodes = f"x{self.self_collect_episodes}" if self.self_collect_episodes != 1 else ""
            parts.append(f"self{self.self_collect_every}{episodes}")
        return "-".join(parts) or "final"

    def check(self) -> Probe:
        if self.eval_context_length is not None and (isinstance(self.eval_context_length, bool) or
                                                     not isinstance(self.eval_context_length, int) or
                                                     self.eval_context_length < 1):
            raise ProbeError(f"eval_context_length must be an integer >= 1, got {self.eval_context_length!r}")
        if self.context_mix is not None and not 0.0 <= float(self.context_mix) <= 1.0:
            raise ProbeError(f"context_mix must be in [0, 1], got {self.context_mix!r}")
        if isinstance(self.repeats, bool) or not isinstance(self.repeats, int) or self.repeats < 1:
            raise ProbeError(f"repeats must be an integer >= 1, got {self.repeats!r}")
        for name, low in (("refine_steps", 0), ("latent_samples", 1), ("self_collect_every", 1),
                          ("self_collect_episodes", 1)):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < low):
                raise ProbeError(f"{name} must be an integer >= {low}, got {value!r}")
        if self.self_collect_every is None and self.self_collect_episodes != 1:
            raise ProbeError("self_collect_episodes needs self_collect_every (the re-inference interval)")
        if self.self_collect_every is not None and (self.context_mix is not None or self.novelty):
            raise ProbeError("self_collect_every replaces the given contexts: leave context_mix and novelty unset")
        return self


def probe_path(run_dir: Path, probe: Probe, rule: str | None = None) -> Path:
    """Where the probe of the run in `run_dir` is saved; `rule`: the probe of one of its test-time rules."""
    return Path(run_dir) / "probes" / (rule or "") / f"{probe.name}.json"


def read_probe(run_dir: Path, probe: Probe, rule: str | None = None) -> dict | None:
    """The probe's saved result, None if it is missing, unreadable or for other settings."""
    try:
        saved = json.loads(probe_path(run_dir, probe, rule).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or not isinstance(saved.get("probe"), dict):
        return None
    # settings added to Probe later take their defaults in probes saved before them
    return saved if {**asdict(Probe()), **saved["probe"]} == asdict(probe) else None
