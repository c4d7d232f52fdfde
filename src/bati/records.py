"""Run records (a run directory's config.json, repeated in its eval.json) of any version, read into today's form.

A record names the version of its format (`record_version`, not part of the run's identity). Records without
it are version 1, written before the key existed, in the shapes of several older bati versions: IQL's
temperature was called `beta` and its hidden sizes were also recorded as `rl_hidden_dims`; settings added since
are absent, and a run without one had its old value (`LATER_FIELDS`, `LATER_METHOD_FIELDS`), which for some
method hyperparameters is not today's default (`CHANGED_METHOD_DEFAULTS`). `read_record` reads them all into
today's form; `digest_view` gives a sweep's digests (the names of run directories) the view older versions had,
so configs that they could express keep their directories.
"""

from __future__ import annotations

import json
from dataclasses import asdict, fields
from typing import Any

from bati.data.own import family_of
from bati.methods import method_config_key, method_sections

RECORD_VERSION = 2
"""The version of the records this bati writes."""
VERSION_KEY = "record_version"

RECORD_ONLY = frozenset({"runtime", "family_version", VERSION_KEY, "rl_hidden_dims"})
"""Keys a record holds that are not TrainConfig fields: what the run recorded about itself, and old names."""

LATER_FIELDS = {"n_train_tasks": 20, "n_test_tasks": 20, "train_task_range": None, "test_task_range": None,
                "datasets": [], "task_key": None, "held_out": 0.2, "eval_env": None, "family_version": 1,
                "zoo_dir": None, "eval_beside_training": False, "experts": "conditioned"}
"""Settings added after runs were recorded: a record without one had this value."""
LATER_METHOD_FIELDS = {"distance": "squared", "latent_activation": "none", "same_task": "index"}
"""Method hyperparameters added after runs were recorded (in every section whose Config has the field): a
section without one had this value. (csro.club_negatives is not one: its old value is not its default.)"""
CHANGED_METHOD_DEFAULTS = {("csro", "csro", "club_negatives"): "any-task", ("er-trl", "ertrl", "metric_weight"): 1.0,
                           ("er-trl", "ertrl", "latent_activation"): "none"}
"""Method hyperparameters added with a new default after runs were recorded: (method, section, field) -> the
value a run without the field had, which is not today's default (such runs are a setting of their own). CSRO
drew CLUB's negatives from any task (today "same-task"); ER-TRL weighted FOCAL's term 1 (today the code's 10)
and had unbounded latents (today "tanh")."""


def read_record(record: dict, *, compact: bool = False) -> dict:
    """`record`, of any version, in today's form: today's names, and today's version. compact: without the
    settings at the value runs had before the settings existed, and with the method's hyperparameters only where
    they differ from its defaults on its family (what tells runs apart: a report's tables)."""
    version = record.get(VERSION_KEY, 1)
    if isinstance(version, bool) or not isinstance(version, int):
        raise ValueError(f"{VERSION_KEY} must be an integer, got {version!r}")
    if version > RECORD_VERSION:
        raise ValueError(f"this record ({VERSION_KEY} {version}) was written by a newer bati, which reads records up "
                         f"to version {RECORD_VERSION} only: upgrade bati to read it")
    if version <= 1:
        record = _from_version_1(record)
    record = {**record, VERSION_KEY: RECORD_VERSION}
    return _compact(record) if compact else record


def differing_settings(saved: dict, current: dict, keys) -> list[str]:
    """The keys whose saved and current values differ (the saved record read into today's form first; a key
    that it lacks counts as the value runs had before the setting existed)."""
    saved = read_record(saved)

    def old(k):
        return saved[k] if k in saved else _value_before(k, current)

    return [k for k in keys if old(k) != current.get(k)]


def digest_view(record: dict) -> dict:
    """Today's record as the digest of a sweep cell sees it: settings added later at their old values are left
    out and renamed ones take their old names, so a config that an older version could express keeps its digest
    (and its run directory)."""
    view = _without_later_fields(record)
    for name in method_sections():
        if isinstance(view.get(name), dict):
            view[name] = _without_later_method_fields(view[name])
            default = default_method_record(record.get("family"), record.get("method"))
            if default is not None and view[name] == _without_later_method_fields(default):
                view.pop(name)
    iql = view.get("iql")
    if isinstance(iql, dict):
        view["iql"] = {("beta" if k == "temperature" else k): v for k, v in iql.items()}
        view["rl_hidden_dims"] = iql.get("hidden_dims")
    return view


def default_method_record(family: str | None, method: str | None) -> dict | None:
    """The default hyperparameters of `method` on `family`, as config.json records them."""
    key = method_config_key(method or "")
    if key is None:
        return None
    family_record = family_of(family).record if family else None  # an unknown family: its error, for every method
    section = method_sections()[key]()
    if hasattr(section, "for_family"):  # the family's Table 3 weights (no family: the record's defaults)
        section = section.for_family(family_record)
    return json.loads(json.dumps(asdict(section), default=str))


def _from_version_1(record: dict) -> dict:
    """A record without a version in today's names, holding the settings added since at the values it ran with
    (`LATER_FIELDS`; e.g. `experts`, whose default has changed since), its method section too."""
    record = {**LATER_FIELDS, **record}
    iql = record.get("iql")
    if isinstance(iql, dict) and "beta" in iql:
        record["iql"] = {("temperature" if k == "beta" else k): v for k, v in iql.items()}
    record.pop("rl_hidden_dims", None)
    for (method, key, name), old_value in CHANGED_METHOD_DEFAULTS.items():
        if record.get("method") == method and name not in (record.get(key) or {}):
            section = record.get(key) or default_method_record(record.get("family"), method)
            record[key] = {**section, name: old_value}
    for name, cls in method_sections().items():
        section = record.get(name)
        if isinstance(section, dict):
            names = {f.name for f in fields(cls)}
            record[name] = {**{k: v for k, v in LATER_METHOD_FIELDS.items() if k in names}, **section}
    return record


def _value_before(key: str, current: dict) -> Any:
    """What a record written before setting `key` existed had for it: LATER_FIELDS, or for a method's
    hyperparameters the defaults for the current record's family."""
    if key in LATER_FIELDS:
        return LATER_FIELDS[key]
    if key in method_sections():
        return default_method_record(current.get("family"), current.get("method"))
    return None


def _compact(record: dict) -> dict:
    """Today's `record` with only the settings that tell runs apart (`read_record`'s compact)."""
    record = _without_later_fields(record)
    for name in method_sections():
        if name in record:
            try:
                default = default_method_record(record.get("family"), record.get("method"))
            except (ImportError, ValueError):  # a family not available here (its extra is missing)
                continue
            changed = {k: v for k, v in record[name].items() if default is None or default.get(k) != v}
            if changed:
                record[name] = changed  # only what differs from the defaults: a table's title names it
            else:
                record.pop(name)
    return record


def _without_later_fields(record: dict) -> dict:
    """`record` without its version and the settings added later that are at their old values."""
    return {k: v for k, v in record.items() if not (k in LATER_FIELDS and v == LATER_FIELDS[k]) and k != VERSION_KEY}


def _without_later_method_fields(section: dict) -> dict:
    return {k: v for k, v in section.items() if not (k in LATER_METHOD_FIELDS and v == LATER_METHOD_FIELDS[k])}
