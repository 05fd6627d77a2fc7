"""Process plumbing shared by every Argus process: stop signals, logging, child processes."""

from __future__ import annotations

import ctypes
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable

_PR_SET_PDEATHSIG = 1


def install_stop_handlers() -> threading.Event:
    """Return an event set on SIGINT or SIGTERM, so a main loop can shut down cleanly.

    Call from the main thread. A second signal while stopping restores the default behaviour.
    """
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        if stop.is_set():
            signal.signal(signum, signal.SIG_DFL)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def setup_logging(name: str, level: str = "INFO") -> logging.Logger:
    """Plain line logging to stderr, prefixed with the process name."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s {name} %(levelname)s %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )
    return logging.getLogger(name)


def kill_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` for ``subprocess.Popen`` that makes the child get SIGKILL when its parent dies
    (Linux ``PR_SET_PDEATHSIG``), so a parent killed without cleaning up leaves no orphan; ``None``
    where prctl is not available. The function is resolved here, in the parent: between fork and exec
    the child only calls it.
    """
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux
        return None

    def preexec() -> None:
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))

    return preexec


def release_free_heap() -> bool | None:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim(0)``, every arena): after a burst
    of large temporary arrays (a planner decision, a keyframe) glibc keeps freed memory mapped (its mmap
    threshold rises with each large free, so later arrays come from the heap, and a live object near the top
    of a heap pins everything below it), and a process's resident memory creeps up in plateaus without a leak.
    True when memory was released, False when there was none to release, None where there is no glibc.
    Costs well under 10 ms after a decision's burst; call it after a burst, not in a tight loop."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None
    return bool(trim(0))


class HeapReleaser:
    """:func:`release_free_heap` at most once per ``period_s`` (0: never), for a loop that calls it after work."""

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s, self.clock = period_s, clock
        self.releases = 0
        self._last: float | None = None

    def __call__(self) -> bool:
        """Release now if the period has passed since the last release; True when it did."""
        if self.period_s <= 0:
            return False
        now = self.clock()
        if self._last is not None and now - self._last < self.period_s:
            return False
        self._last = now
        if release_free_heap() is None:
            return False
        self.releases += 1
        return True
