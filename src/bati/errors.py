"""Errors the CLI reports as one line instead of a traceback (exit code 2; a partial failure 1)."""


class BatiError(Exception):
    """Base class of bati's user-facing errors that are not plain ValueErrors."""


class PartialFailure(BatiError):
    """Part of a command's work failed or was found damaged while the rest is done (exit code 1, not 2)."""


class BatiWarning(UserWarning):
    """Something was repaired or skipped (e.g. a torn log line dropped): the CLI shows it as one line."""


class PathError(BatiError):
    """A directory a command needs is a file, lies under a file, or cannot be written (found up front)."""


class LockedError(BatiError):
    """Another live process is writing the same run directory or collection (its lock names it)."""


def describe_os_error(err: OSError) -> str:
    """One line for an OS error: the path it concerns and why, in words (no errno numbers).

    Errors bati raises itself with a full sentence (no `filename`, e.g. "no PointGoal data at ...;
    collect it with ...") are returned as they are.
    """
    import errno

    if err.filename is None:
        return str(err)
    reasons = {
        errno.ENOSPC: "no space left on device",
        errno.EDQUOT: "disk quota exceeded",
        errno.EACCES: "permission denied",
        errno.EPERM: "operation not permitted",
        errno.EROFS: "read-only file system",
        errno.ENOTDIR: "not a directory (a file stands where the path needs a directory)",
        errno.EISDIR: "is a directory, not a file",
        errno.EEXIST: "exists and is not a directory",
        errno.ENOENT: "no such file or directory",
    }
    reason = reasons.get(err.errno) or err.strerror or str(err)
    where = str(err.filename) + (f" -> {err.filename2}" if getattr(err, "filename2", None) else "")
    return f"{where}: {reason}"
