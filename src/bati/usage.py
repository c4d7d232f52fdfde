"""The `bati` command line parsed by tyro, whose usage-error panel (an unknown option, a value of the wrong
type, a missing value) becomes one line: its message, its first suggestion and where the help is, as the
CLI prints every error."""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Callable

import tyro


def parse(commands: dict[str, type], argv: list[str] | None, show_error: Callable[[str], object]):
    """The command tyro parses from `argv` (None: the program's arguments); a usage error goes to `show_error`
    as one line instead of tyro's panel, then SystemExit(2) as tyro does."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            command = tyro.extras.subcommand_cli_from_dict(
                commands, args=argv, prog="bati", config=(tyro.conf.OmitSubcommandPrefixes,)
            )
    except SystemExit as exit_:
        if exit_.code not in (0, None):
            show_error(usage_error_line(captured.getvalue()))
            raise SystemExit(2) from None
        sys.stderr.write(captured.getvalue())
        raise
    sys.stderr.write(captured.getvalue())  # whatever else tyro printed (warnings)
    return command


def usage_error_line(panel: str) -> str:
    """tyro's usage-error panel in one line: its message, its first suggestion, where the help is."""
    rows = [row.strip().strip("\u2502\u256d\u256e\u2570\u256f").strip() for row in panel.splitlines()]
    sections: list[list[str]] = [[]]
    for row in rows[1:]:  # after the title, rules (----) separate the message and the hints
        if row and set(row) <= set("-\u2500\u256d\u256e\u2570\u256f "):
            sections.append([])
        else:
            sections[-1].append(row)
    body = next((section for section in sections if any(section)), rows)
    message = " ".join(_first_paragraph(body))
    if not message:
        return "invalid arguments (see `bati --help`)"
    suggestion = _row_after(rows, "Perhaps you meant")
    if suggestion:
        message += f"; perhaps you meant {suggestion.split()[0]}"
    helps = [row.split(" run ", 1)[-1].split(" see ", 1)[-1] for row in rows if row.startswith("For full helptext")]
    return message + (f" (see `{helps[0]}`)" if helps else "")


def _row_after(rows: list[str], prefix: str) -> str:
    """The first non-empty row after the row that starts with `prefix` ("" if none)."""
    starts = [i for i, row in enumerate(rows) if row.startswith(prefix)]
    return next((row for row in rows[starts[0] + 1:] if row), "") if starts else ""


def _first_paragraph(rows: list[str]) -> list[str]:
    out = []
    for row in rows:
        if not row and out:
            break
        if row:
            out.append(row)
    return out
