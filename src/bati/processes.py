"""The one process pool of bati: data collection's rollout workers and a sweep's local jobs."""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager


@contextmanager
def spawned_pool(workers: int, initializer: Callable | None = None, initargs: tuple = ()) -> Iterator[ProcessPoolExecutor]:
    """`workers` spawned processes (JAX is not fork-safe). They inherit this environment, in which JAX does
    not take most of a GPU's memory up front, so that several may share one GPU. When the body raises
    (an error, an interrupt), the workers are stopped at once rather than after their current task:
    what they were writing is resumable by design (collections and runs checkpoint and write atomically)."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=initializer, initargs=initargs)
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
