"""The one process pool of bati: data collection's rollout workers and a sweep's local jobs; SIGTERM
turned into an interrupt, so that a terminated command cleans up as after Ctrl-C; and a watchdog that ends
a training loop which has stopped making progress."""

from __future__ import annotations

import faulthandler
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's KeyboardInterrupt: the same clean-up runs (a pool's
    workers stopped, locks released, the run resumable), where Python's default would die at once."""


TERMINATED_EXIT_CODE = 128 + signal.SIGTERM

STALL_SECONDS = 1800.0
"""A training loop that reports no progress (a logged chunk, an episode, a finished evaluation) for this long
is taken to hang: the longest gap between two reports, a paper-scale compilation or evaluation, is minutes."""


def _exit_unless_handled(handled: threading.Event, grace_s: float) -> None:
    if not handled.wait(grace_s):
        print(f"error: terminated, and still running {grace_s:g} s later: exiting now; run the same command again to "
              "resume", file=sys.stderr, flush=True)
        os._exit(TERMINATED_EXIT_CODE)  # what bati writes is atomic and resumable: stopping anywhere is safe


@contextmanager
def sigterm_as_interrupt(grace_s: float = 30.0) -> Iterator[None]:
    """Within the body SIGTERM raises Terminated in the main thread (elsewhere: nothing changes).

    Python swallows an exception raised where it cannot propagate (a finaliser, a gc callback such as JAX's,
    printed as "Exception ignored in ..."): a SIGTERM landing there would be lost and the command would go on
    for hours. So each SIGTERM also starts a timer: unless the body has ended `grace_s` seconds later, the
    process exits with code 143 outright. That also bounds the clean-up, as a scheduler's grace period would (an
    evaluation in flight beside training is not waited for: the run resumes from its last checkpoint)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handled = threading.Event()

    def raise_terminated(signum, frame):
        threading.Thread(target=_exit_unless_handled, args=(handled, grace_s), daemon=True,
                         name="bati-sigterm-grace").start()
        raise Terminated(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        handled.set()
        signal.signal(signal.SIGTERM, previous)


def _exit_when_orphaned(parent: int, every_s: float = 1.0) -> None:
    while os.getppid() == parent:  # a dead parent's children are handed to another process
        time.sleep(every_s)
    os._exit(1)  # what a worker writes is atomic and resumable: stopping anywhere is safe


def _start_worker(parent: int, initializer: Callable | None, initargs: tuple) -> None:
    """A worker's first act: follow its parent. A parent killed outright (SIGKILL, a machine's session end)
    cannot stop its workers, which would go on training and hold their runs' locks for hours."""
    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True, name="bati-orphan-watch").start()
    if initializer is not None:
        initializer(*initargs)


@contextmanager
def spawned_pool(workers: int, initializer: Callable | None = None, initargs: tuple = ()) -> Iterator[ProcessPoolExecutor]:
    """`workers` spawned processes (JAX is not fork-safe). They inherit this environment, in which JAX does
    not take most of a GPU's memory up front, so that several may share one GPU. When the body raises
    (an error, an interrupt), the workers are stopped at once rather than after their current task:
    what they were writing is resumable by design (collections and runs checkpoint and write atomically).
    A worker whose parent dies without that clean-up (kill -9) exits by itself within a second or two."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_worker, initargs=(os.getpid(), initializer, initargs))
    finished = False
    try:
        yield executor
        finished = True
    finally:
        if not finished:
            for process in list((getattr(executor, "_processes", None) or {}).values()):
                if process.is_alive():
                    process.terminate()
        executor.shutdown(wait=True, cancel_futures=True)


@contextmanager
def stall_watchdog(seconds: float = STALL_SECONDS) -> Iterator[Callable[[], None]]:
    """Within the body, a process whose loop has not called the yielded `alive()` for `seconds` prints every
    thread's stack to stderr (after a line "Timeout (h:mm:ss)!") and exits with code 1.

    A process can wait forever at 0% CPU with no error (JAX's CPU backend, on rare occasions, never delivers
    a result: jax-ml/jax#25861); a chained script would wait with it for the rest of a session. The timer is
    faulthandler's, a C thread that needs no GIL, so it fires whatever the waiting thread holds. Stopping there
    is safe: what a run writes is atomic, and the same command resumes it from its last checkpoint."""
    stream = sys.__stderr__  # the real one: a progress bar swaps sys.stderr for a proxy without a file descriptor

    def alive() -> None:
        faulthandler.dump_traceback_later(seconds, repeat=False, file=stream, exit=True)

    alive()
    try:
        yield alive
    finally:
        faulthandler.cancel_dump_traceback_later()
