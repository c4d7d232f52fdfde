"""The one process pool (bati.processes): spawned workers, stopped at once when the body fails, when the
command is terminated (SIGTERM) and, by themselves, when their parent is killed outright."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from bati.processes import Terminated, sigterm_as_interrupt, spawned_pool

# A parent that prints its one worker's pid, then waits on a 120 s task in it; on SIGTERM it exits 143.
PARENT = """
import os, sys, time
from bati.processes import Terminated, sigterm_as_interrupt, spawned_pool
try:
    with sigterm_as_interrupt(), spawned_pool(1) as pool:
        print(pool.submit(os.getpid).result(), flush=True)
        pool.submit(time.sleep, 120).result()
except Terminated:
    sys.exit(143)
"""
needs_proc = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def gone(pid: int) -> bool:
    """No such process, or a zombie (an orphan that exited, not reaped by a container's init)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def wait_until_gone(pid: int, within_s: float = 30.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if gone(pid):
            return True
        time.sleep(0.2)
    return gone(pid)


def start_parent() -> tuple[subprocess.Popen, int]:
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    assert worker != parent.pid and not gone(worker)
    return parent, worker


def test_a_spawned_pool_runs_tasks_in_other_processes():
    with spawned_pool(2) as pool:
        pids = {pool.submit(os.getpid).result() for _ in range(4)}
    assert os.getpid() not in pids


def test_a_failing_body_stops_the_workers_at_once():
    start = time.perf_counter()
    with pytest.raises(RuntimeError, match="interrupted"):
        with spawned_pool(1) as pool:
            pool.submit(os.getpid).result()  # the worker is up
            pool.submit(time.sleep, 120)
            time.sleep(0.5)  # ... and sleeping
            raise RuntimeError("interrupted")
    assert time.perf_counter() - start < 60  # not after the 120 s task


@needs_proc
def test_sigterm_to_the_parent_stops_its_workers_at_once():
    parent, worker = start_parent()
    start = time.monotonic()
    parent.send_signal(signal.SIGTERM)
    assert parent.wait(timeout=60) == 143  # Terminated reached the script: the pool's clean-up ran
    assert wait_until_gone(worker), "the worker outlived its terminated parent"
    assert time.monotonic() - start < 60  # not after the 120 s task


@needs_proc
def test_a_worker_exits_by_itself_when_its_parent_is_killed_outright():
    parent, worker = start_parent()
    parent.kill()  # SIGKILL: no clean-up runs in the parent
    parent.wait(timeout=30)
    assert wait_until_gone(worker), "an orphaned worker went on with its task"


def test_sigterm_as_interrupt_raises_terminated_and_restores_the_handler():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(10)  # interrupted by the handler
    assert signal.getsignal(signal.SIGTERM) is before
    assert issubclass(Terminated, KeyboardInterrupt)  # every Ctrl-C clean-up path covers SIGTERM too


# A SIGTERM whose Terminated is raised inside a finaliser, where Python prints and ignores it (as in JAX's gc
# callback): without the grace timer the body would sleep on for its 120 s.
SWALLOWED = """
import os, signal, sys, time
from bati.processes import sigterm_as_interrupt

class TerminatedInAFinaliser:
    def __del__(self):
        signal.raise_signal(signal.SIGTERM)  # the handler runs here; its exception is ignored


with sigterm_as_interrupt(grace_s=1.0):
    TerminatedInAFinaliser()
    print("went on", flush=True)
    time.sleep(120)
"""


def test_a_sigterm_lost_inside_a_finaliser_still_ends_the_process():
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", SWALLOWED], capture_output=True, text=True, timeout=60, check=False)
    assert "Exception ignored" in done.stderr and "went on" in done.stdout  # the interrupt was lost ...
    assert done.returncode == 143  # ... and the process ended all the same, after the grace
    assert done.stderr.strip().splitlines()[-1] == \
        "error: terminated, and still running 1 s later: exiting now; run the same command again to resume"
    assert time.perf_counter() - start < 30


# Reports progress for 1.5 s under a 0.5 s watchdog, then stalls in wait_forever.
STALLING = """
import time
from bati.processes import stall_watchdog

def wait_forever():
    time.sleep(60)

with stall_watchdog(0.5) as alive:
    for _ in range(10):
        time.sleep(0.15)
        alive()
    print("progressed", flush=True)
    wait_forever()
"""


def test_stall_watchdog_ends_a_stalled_loop_with_its_stacks():
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-c", STALLING], capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1
    assert done.stdout == "progressed\n"  # alive() kept it going past the timeout
    assert "Timeout (0:00:00.500000)!" in done.stderr and "wait_forever" in done.stderr
    assert time.monotonic() - started < 30


def test_stall_watchdog_is_off_after_its_body():
    script = ("import time\nfrom bati.processes import stall_watchdog\n"
              "with stall_watchdog(0.3):\n    pass\ntime.sleep(1.0)\nprint('done')")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout, done.stderr) == (0, "done\n", "")


def test_an_interrupted_bati_program_leaves_at_once_whatever_threads_are_still_busy():
    """Ctrl-C during the first compilation crashed the interpreter's shutdown (exit 139) under XLA's busy threads:
    after its clean-up the program leaves with 130 without waiting for them (here a thread busy for 60 s)."""
    import subprocess
    import sys
    import time

    code = """
import sys, threading, time
from bati import cli
threading.Thread(target=time.sleep, args=(60,)).start()  # busy, not a daemon: shutdown would wait for it
class Command:
    def run(self):
        raise KeyboardInterrupt
cli.parse = lambda commands, argv, error: Command()
sys.argv = ["bati", "envs"]
sys.exit(cli.main())
"""
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=50)
    assert done.returncode == 130 and "interrupted; run the same command again to resume" in done.stderr
    assert time.monotonic() - start < 30 and "Traceback" not in done.stderr
