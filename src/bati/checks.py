"""Checks of the settings a user gives (CLI options, a config.json, sweep settings): a bad value is one
line naming the setting, raised before any work. One place for what a count, a rate and a network's
hidden sizes may be, whichever command takes them."""

from __future__ import annotations

import math

MAX_COUNT = 10**9
"""The largest step count, batch size, length or seed a setting accepts (beyond it: a typo, not a plan)."""


def check_integer(name: str, value, low: int = 1, *, hint: str = "", error: type[Exception] = ValueError) -> int:
    """`value` if it is an integer in [low, MAX_COUNT]; else `error` naming the setting (`hint` appended:
    e.g. what leaving the setting out gives). 0 never silently stands for a default."""
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise error(f"{name} must be an integer >= {low}, got {value!r}{hint}")
    if value > MAX_COUNT:
        raise error(f"{name} must be at most {MAX_COUNT:,}, got {value:,}")
    return value


def check_number(name: str, value, *, positive: bool = True, at_most: float | None = None,
                 below: float | None = None) -> float:
    """`value` if it is a finite real number, > 0 (`positive`) or >= 0, at most `at_most` and below `below`;
    else ValueError."""
    low = "> 0" if positive else ">= 0"
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
        value > 0 if positive else value >= 0) and (at_most is None or value <= at_most) and (
        below is None or value < below)
    if not ok:
        bound = f" and at most {at_most:g}" if at_most is not None else f" and below {below:g}" if below is not None else ""
        raise ValueError(f"{name} must be a finite number {low}{bound}, got {value!r}")
    return float(value)


def check_finite_fields(section: str, config) -> None:
    """Every real-valued setting of a dataclass of settings is a finite number (NaN or inf: one line now,
    not a non-finite loss minutes into training)."""
    from dataclasses import fields

    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{section}.{f.name} must be a finite number, got {value!r}")


def check_hidden_dims(name: str, dims) -> tuple[int, ...]:
    """A network's hidden-layer sizes: one or more integers >= 1 (none would make it linear; 0 has no layer)."""
    if not (isinstance(dims, (tuple, list)) and dims and all(
            isinstance(d, int) and not isinstance(d, bool) and 1 <= d <= MAX_COUNT for d in dims)):
        raise ValueError(f"{name} must be one or more integers >= 1 (the hidden layers' sizes), got {dims!r}")
    return tuple(dims)
