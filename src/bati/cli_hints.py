"""How the command line shows a setting's default (tyro reads these from the dataclasses' annotations)."""

from __future__ import annotations

import tyro

DEFAULT_IN_DOC = tyro.conf.arg(help_behavior_hint="")
"""A setting whose docstring says its default, "(default: the family's ...)": the help shows that once, without
tyro's own "(default: None)" after it."""
