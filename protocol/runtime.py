"""Process plumbing shared by every Argus process: stop signals and logging."""

from __future__ import annotations

import logging
import signal
import sys
import threading


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
