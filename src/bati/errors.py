"""Errors the CLI reports as one line (exit code 2) instead of a traceback."""


class BatiError(Exception):
    """Base class of bati's user-facing errors that are not plain ValueErrors."""
