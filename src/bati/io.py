"""Atomic file writes: a crash leaves either the old file or the new one, never half of one."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from bati.errors import BatiWarning, LockedError, PathError


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write to a temporary sibling, fsync, rename over `path`. An OS error (disk full, permission,
    a file where a directory should be) leaves the old file untouched and names `path`, not the
    temporary file."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise naming(err, path) from err
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp creates 0600 files
        os.replace(tmp, path)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise naming(err, path) from err
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def naming(err: OSError, path: Path) -> OSError:
    """`err` naming `path` (the file the user knows) when it names nothing or our temporary file.

    A failed write() reports no file name at all ("[Errno 28] No space left on device"), and
    mkstemp's errors name a `.<name>.XXXX.tmp` file the user never sees.
    """
    filename = None if err.filename is None else Path(str(err.filename))
    if filename is not None and not filename.name.startswith(f".{path.name}."):
        return err
    named = OSError(err.errno, err.strerror or str(err), str(path))  # errno picks the same subclass
    named.__cause__ = err
    return named


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    import io

    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def append_jsonl(path: str | Path, record: dict) -> None:
    """Append one JSON line (a crash can lose at most this line, never earlier ones)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as f:
            f.write(json.dumps(record, default=_json_default) + "\n")
    except OSError as err:  # e.g. disk full: at most a torn last line, dropped on resume (read_jsonl)
        raise naming(err, path) from err


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"cannot serialise {type(value).__name__} to JSON")


def git_commit(directory: Path | None = None) -> str:
    """Short commit of the code under `directory`; "unknown" outside a git checkout. Whether the files differ
    from it (edits not committed: the commit alone would not give the run back) is `uncommitted_changes`;
    records take both from `code_record`.

    Without `directory`: the running code's commit (the package's directory), read once per process, at the
    first call (`bati`'s commands make it at their start): a process runs the code it loaded, so a commit made
    while a long run trains must not be recorded as the code of its results."""
    return (_running_code_state() if directory is None else _read_state(Path(directory)))[0]


def uncommitted_changes(directory: Path | None = None) -> bool:
    """Whether the code under `directory` (default: the running package, read once) differs from its commit."""
    return (_running_code_state() if directory is None else _read_state(Path(directory)))[1]


def code_record() -> dict:
    """The running code as a record states it: {"commit": ...}, with "uncommitted_changes": true where the
    package's files differ from that commit (a report flags such runs)."""
    commit, changed = _running_code_state()
    return {"commit": commit, **({"uncommitted_changes": True} if changed else {})}


def short_commit(commit: str) -> str:
    """A recorded commit for a report line: its hash cut to 12 characters (older runs recorded full hashes;
    older records marked uncommitted changes with "-dirty", kept)."""
    head, dirty, _ = commit.partition("-dirty")
    return head[:12] + dirty


@functools.cache
def _running_code_state() -> tuple[str, bool]:
    return _read_state(Path(__file__).parent)


def _read_state(directory: Path) -> tuple[str, bool]:
    try:
        def git(*args):
            return subprocess.run(["git", *args], capture_output=True, text=True, cwd=directory, timeout=5).stdout.strip()

        head = git("rev-parse", "--short", "HEAD")
        if not head:
            return "unknown", False
        return head, bool(git("status", "--porcelain", "--", "."))
    except (OSError, subprocess.SubprocessError):
        return "unknown", False


def check_run_config(path: Path, config: dict, identity: tuple[str, ...], differing=None) -> None:
    """Write a run's config.json, or refuse to reuse a directory whose run differs in `identity` keys
    (`differing(saved, config, keys)` lists the keys that differ; default: plain inequality)."""
    if path.exists():
        try:
            saved = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{path} is not valid JSON ({err}); delete the run directory or use another one") from err
        if not isinstance(saved, dict):
            raise ValueError(f"{path} holds a {type(saved).__name__}, not a run's config; delete it or use another one")
        diffs = (differing(saved, config, identity) if differing is not None
                 else [k for k in identity if saved.get(k) != config.get(k)])
        if diffs:
            detail = ", ".join(f"{k}: {saved.get(k)!r} there, {config.get(k)!r} now" for k in diffs)
            raise ValueError(f"{path.parent} holds a run with another config ({detail}); use another --out-dir")
    else:
        atomic_write_json(path, config)


# --- JSONL logs ----------------------------------------------------------------------------------
def read_jsonl_lines(path: str | Path, require: tuple[str, ...] = ()) -> list[tuple[str, dict]]:
    """(line, record) for each line of a JSONL log, each record a JSON object with the `require` keys.

    A bad last line is what a kill or a full disk in the middle of `append_jsonl` leaves (a torn
    line): it is dropped with a BatiWarning naming the file. A bad line before the last cannot come
    from an interrupted append: ValueError naming the file and the line. Blank lines are skipped.
    """
    path = Path(path)
    lines = _log_bytes(path).decode("utf-8", errors="replace").split("\n")
    numbered = [(n, line) for n, line in enumerate(lines, 1) if line.strip()]
    out = []
    for i, (number, line) in enumerate(numbered):
        try:
            record = json.loads(line)
            if not isinstance(record, dict):
                raise ValueError(f"a JSON {type(record).__name__}, not a record")
            missing = [k for k in require if k not in record]
            if missing:
                raise ValueError(f"no {', '.join(missing)}")
        except ValueError as err:
            if i == len(numbered) - 1:
                warnings.warn(f"{path}: dropped its torn last line {number} ({_preview(line)}), left by an "
                              "interrupted write", BatiWarning, stacklevel=2)
                break
            raise ValueError(f"{path}, line {number}: not a valid record ({err}); the file is damaged: "
                             "fix or delete that line") from err
        out.append((line, record))
    return out


def _log_bytes(path: Path) -> bytes:
    """A log's bytes: the file, or its packed copy (`pack_jsonl`) where only that one is kept."""
    packed = path.with_name(path.name + ".gz")
    if not path.exists() and packed.exists():
        import gzip

        return gzip.decompress(packed.read_bytes())
    return path.read_bytes()


def log_exists(path: str | Path) -> bool:
    """Whether a JSONL log is there, plain or packed."""
    path = Path(path)
    return path.exists() or path.with_name(path.name + ".gz").exists()


PACK_DIGITS = 4
"""Significant digits a packed log keeps of each float (steps and other integers are kept whole)."""


def pack_jsonl(path: str | Path, digits: int = PACK_DIGITS) -> Path:
    """Replace a finished run's JSONL log by `<name>.gz`: its records with every float rounded to `digits`
    significant digits (a wall-time clock to 0.1 s), gzipped. `read_jsonl` reads the packed copy where the
    plain file is gone. For a results folder kept in version control (about 30x smaller); a log still being
    appended to must not be packed. The packed copy is written before the plain file is removed."""
    import gzip

    path = Path(path)

    def rounded(key, value):
        if isinstance(value, float) and np.isfinite(value):
            return round(value, 1) if key == "wall_time" else float(f"{value:.{digits}g}")
        return value

    text = "".join(json.dumps({k: rounded(k, v) for k, v in record.items()}) + "\n" for record in read_jsonl(path))
    packed = path.with_name(path.name + ".gz")
    atomic_write_bytes(packed, gzip.compress(text.encode(), compresslevel=9, mtime=0))
    path.unlink()
    return packed


def read_jsonl(path: str | Path, require: tuple[str, ...] = ()) -> list[dict]:
    """The records of a JSONL log (a torn last line dropped with a warning; see read_jsonl_lines)."""
    return [record for _, record in read_jsonl_lines(path, require)]


def _preview(line: str, width: int = 40) -> str:
    text = line.replace("\x00", "\\0")
    return repr(text if len(text) <= width else text[:width] + "...")


# --- directories ---------------------------------------------------------------------------------
PACKAGE_DIR = Path(__file__).resolve().parent


def check_outside_package(path: str | Path, what: str) -> None:
    """PathError for an output path inside the installed bati package (an editable install's src/bati too):
    runs, data and reports go to a run directory, a data root or an --out path, never into the package."""
    resolved = Path(path).resolve()
    if resolved == PACKAGE_DIR or PACKAGE_DIR in resolved.parents:
        raise PathError(f"{what} {path} lies inside the bati package ({PACKAGE_DIR}): give a path outside it")


def check_directory(path: str | Path, what: str, *, writable: bool = True, package: bool = False) -> None:
    """Refuse, before any work and with one line, a directory that is a file, lies under a file, or
    (`writable`) cannot be created or written, or lies inside the bati package (unless `package`: the
    shipped experts' zoo, `--into-package`); PathError. Found now rather than after minutes of
    collecting or training, and before anything was written elsewhere."""
    path = Path(path)
    if writable and not package:
        check_outside_package(path, what)
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    if path.exists() and not path.is_dir():
        raise PathError(f"{what} {path} is a file, not a directory")
    if existing is not None and not existing.is_dir():
        raise PathError(f"cannot create {what} {path}: {existing} is a file, not a directory")
    if writable and existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        detail = "" if existing == path else f" ({existing} is not)"
        raise PathError(f"{what} {path} is not writable{detail}: permission denied or a read-only file "
                        "system")


def make_dirs(path: str | Path) -> list[Path]:
    """mkdir -p `path`; returns the directories it created, outermost first (see remove_empty_dirs)."""
    path = Path(path)
    missing = []
    probe = path
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise naming(err, path) from err
    return missing[::-1]


def remove_empty_dirs(created: list[Path]) -> None:
    """Remove directories `make_dirs` created, innermost first, as long as they are empty: a command
    that fails before writing anything leaves no trace."""
    for directory in reversed(created):
        try:
            directory.rmdir()
        except OSError:
            return


# --- locks ---------------------------------------------------------------------------------------
LOCK_NAME = ".lock"


def pid_alive(pid: int) -> bool:
    """Whether a process with this id runs on this host (one we may not signal counts as running)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def hold_lock(path: str | Path, what: str) -> Iterator[Path]:
    """Hold the lock file `path` while this process writes `what` (a run directory, a collection).

    A second process that wants the same lock fails at once with LockedError naming the holder's pid,
    host and start time. The lock is an flock on the file, which the kernel drops when its holder
    dies however it dies (kill -9 included): a lock left by a dead process is simply taken over.
    Where the file system has no flock, the file's pid decides: a dead pid on this host is taken over,
    a live one or one on another host is not. Released (the file removed) on exit; directories
    created for it are removed again when they stayed empty.
    """
    path = Path(path)
    created = make_dirs(path.parent)
    try:
        fd = _acquire(path, what)
    except PermissionError as err:  # name what cannot be written, not the lock beside it
        remove_empty_dirs(created)
        raise PermissionError(err.errno, err.strerror, str(path.parent)) from err
    except BaseException:
        remove_empty_dirs(created)
        raise
    try:
        yield path
    finally:
        _release(path, fd)
        remove_empty_dirs(created)


def _holder() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": " ".join(sys.argv)[:300]}


def _acquire(path: Path, what: str) -> int:
    for _ in range(10):  # retried only while a releasing holder removes the file under us
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise naming(err, path) from err
        try:
            locked = _flock(fd)
            if locked is None:  # no flock on this file system: the pid in the file decides
                os.close(fd)
                return _acquire_by_pid(path, what)
            if not locked:
                raise LockedError(_held_message(path, what))
            if not _same_file(fd, path):  # its holder released (removed) it meanwhile: take the new one
                os.close(fd)
                continue
            _write_holder(fd)
            return fd
        except BaseException:
            with contextlib.suppress(OSError):
                os.close(fd)
            raise
    raise LockedError(f"{what}: could not take its lock {path} (it keeps changing hands)")


def _flock(fd: int) -> bool | None:
    """Try an exclusive flock without waiting: True (ours), False (held), None (not supported)."""
    import errno

    try:
        import fcntl
    except ImportError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        if err.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EINVAL, errno.ENOSYS):
            return None
        raise
    return True


def _same_file(fd: int, path: Path) -> bool:
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False


def _write_holder(fd: int) -> None:
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, (json.dumps(_holder()) + "\n").encode())
    os.fsync(fd)


def _read_holder(path: Path) -> dict:
    """The holder recorded in a lock file ({} if it cannot be read: being written, or gone)."""
    for _ in range(3):  # its holder may be between creating and filling it
        try:
            holder = json.loads(path.read_text())
            if isinstance(holder, dict):
                return holder
        except (OSError, ValueError):
            pass
        time.sleep(0.05)
    return {}


def _held_message(path: Path, what: str) -> str:
    h = _read_holder(path)
    who = (f"pid {h.get('pid', '?')} on {h.get('host', '?')} since {h.get('since', '?')}" if h
           else "another process")
    return (f"{what} is in use by {who} (lock {path}); wait for it to finish or stop it "
            "(a lock whose process died is taken over by itself)")


def _acquire_by_pid(path: Path, what: str) -> int:
    """The lock without flock: create the file exclusively; take over a dead process's file on this host."""
    for _ in range(3):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            h = _read_holder(path)
            dead_here = h.get("host") == socket.gethostname() and not pid_alive(int(h.get("pid", 0) or 0))
            if not dead_here:
                raise LockedError(_held_message(path, what) + f"; if it is gone, delete {path}") from None
            path.unlink(missing_ok=True)
            continue
        except OSError as err:
            raise naming(err, path) from err
        _write_holder(fd)
        return fd
    raise LockedError(f"{what}: could not take its lock {path} (it keeps changing hands)")


def _release(path: Path, fd: int) -> None:
    """Remove the lock file if it is still ours, then drop the lock (closing the file drops the flock)."""
    try:
        if _same_file(fd, path):
            path.unlink(missing_ok=True)
    finally:
        os.close(fd)


def rules_evaluated(run_dir: Path) -> frozenset[str] | None:
    """The test-time rules (bati-r, bati-auto in a bati run) that every evaluation in the run's eval.jsonl holds
    under "rules"; None before its first evaluation."""
    path = Path(run_dir) / "eval.jsonl"
    records = read_jsonl(path, require=("step",)) if path.exists() else []
    return frozenset.intersection(*(frozenset(r.get("rules") or ()) for r in records)) if records else None


def read_run_config(out: Path) -> dict:
    """A run directory's config.json as a dict; one-line errors naming what is wrong (not a directory,
    no config, not JSON, not an object)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} is a file, not a run directory")
    path = out / "config.json"
    if not path.is_file():
        raise ValueError(f"{out} is not a run directory: it has no config.json")
    try:
        config = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON ({err})") from err
    if not isinstance(config, dict):
        raise ValueError(f"{path} holds a JSON {type(config).__name__}, not a run's config")
    return config
