"""Keyframe workers the mapper starts on its own machine: the embedded default (``[workers] local``).

Each is an ordinary ``argus worker`` (:mod:`mapper.work.worker`) in a child process, joined to the mapper's own
Zenoh endpoints, so the offloader treats it exactly like a worker on another machine (liveliness, acks,
re-issue, quarantine). The mapper's thread then only ingests frames, fuses and publishes while the child
computes keyframes; with no worker alive (the child still starting, or restarting) the mapper does every
keyframe itself, as before.

The child reads its settings as one JSON line on its stdin and then keeps reading it: end of file (the mapper
closed the pipe, or died, even by SIGKILL) stops it, so no local worker outlives its mapper. A child that exits
on its own is started again after a back-off (counter ``local_worker_restarts``).
"""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from mapper.work.config import WorkerConfig
from protocol.session import ZenohSettings
from protocol.transport import Counters

log = logging.getLogger(__name__)
WILDCARD_HOSTS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}  # noqa: S104 - mapped to loopback, never bound
RESTART_BACKOFF_S = (2.0, 60.0)
"""A child that exits is started again after the first figure, doubling per exit up to the second; one that
ran longer than the second before it exited starts the doubling afresh."""


def local_endpoints(z: ZenohSettings) -> list[str]:
    """Where a local worker joins the mapper's Zenoh network: the router a client mapper connects to; for a
    peer or router mapper, its own listen endpoints (a wildcard host made loopback), else what it connects to.
    Empty when there is nowhere to go (a peer listening on a random port with nothing to connect to)."""
    if z.mode != "client":
        fixed = [e for e in z.listen if not e.endswith(":0")]
        if fixed:
            return [_loopback(e) for e in fixed]
    return list(z.connect)


def _loopback(endpoint: str) -> str:
    proto, sep, rest = endpoint.partition("/")
    host, colon, port = rest.rpartition(":")
    return f"{proto}{sep}{WILDCARD_HOSTS.get(host, host)}{colon}{port}" if sep and colon else endpoint


def local_worker_config(mapper_id: str, site: str, key_prefix: str, zenoh: ZenohSettings, index: int,
                        torch_threads: int, log_level: str) -> WorkerConfig | None:
    """The settings of local worker ``index`` of a mapper (None: no endpoint to reach the mapper on)."""
    endpoints = local_endpoints(zenoh)
    if not endpoints:
        return None
    z = zenoh.model_copy(update={"mode": "client", "connect": endpoints, "listen": []})
    return WorkerConfig(id=f"{mapper_id}-local{index}", site=site, key_prefix=key_prefix, zenoh=z,
                        torch_threads=torch_threads, log_level=log_level)  # type: ignore[arg-type]


@dataclass
class _Child:
    config: WorkerConfig
    popen: subprocess.Popen[bytes] | None = None
    exits: int = 0  # exits in a row (reset by a long run)
    start_after: float = 0.0  # time.monotonic() before which it is not started again
    started: float = 0.0  # time.monotonic() of its last start


class LocalWorkers:
    """The mapper's local worker processes: started, watched (:meth:`check`, from the mapper's loop), stopped."""

    def __init__(self, configs: list[WorkerConfig], counters: Counters, stop_timeout_s: float = 10.0) -> None:
        self.children = [_Child(c) for c in configs]
        self.counters = counters
        self.stop_timeout_s = stop_timeout_s
        self._closed = False

    def start(self) -> None:
        for child in self.children:
            self._spawn(child)

    def _spawn(self, child: _Child) -> None:
        argv = [sys.executable, "-m", "mapper.work.local"]
        popen = None
        try:
            popen = subprocess.Popen(argv, stdin=subprocess.PIPE)
            assert popen.stdin is not None
            popen.stdin.write(child.config.model_dump_json().encode() + b"\n")
            popen.stdin.flush()
        except OSError as e:
            if popen is not None:  # started but its settings did not get through: not left running
                _close_stdin(popen)
                popen.kill()
                popen.wait()
            self.counters.add("local_worker_start_errors")
            log.warning("local worker %s could not start: %s", child.config.id, e)
            child.exits += 1
            child.start_after = time.monotonic() + _backoff(child.exits)
            return
        child.popen, child.started = popen, time.monotonic()
        self.counters.add("local_workers_started")
        log.info("local worker %s started (pid %d)", child.config.id, popen.pid)

    def check(self, now: float | None = None) -> None:
        """Start again, after the back-off, the children that exited."""
        if self._closed:
            return
        now = time.monotonic() if now is None else now
        for child in self.children:
            if child.popen is not None:
                code = child.popen.poll()
                if code is None:
                    continue
                _close_stdin(child.popen)
                child.popen = None
                child.exits = 1 if now - child.started > RESTART_BACKOFF_S[1] else child.exits + 1
                child.start_after = now + _backoff(child.exits)
                self.counters.add("local_worker_exits")
                log.warning("local worker %s exited with status %s; starting it again in %.0f s", child.config.id,
                            code, child.start_after - now)
            elif now >= child.start_after:
                self.counters.add("local_worker_restarts")
                self._spawn(child)

    def alive(self) -> int:
        return sum(c.popen is not None and c.popen.poll() is None for c in self.children)

    def close(self) -> None:
        """Stop every child: its stdin closes (it stops by itself), then SIGTERM, then SIGKILL."""
        self._closed = True
        running = [c.popen for c in self.children if c.popen is not None]
        for p in running:
            _close_stdin(p)
        deadline = time.monotonic() + self.stop_timeout_s
        for p in running:
            for signal_it in (None, p.terminate, p.kill):
                if signal_it is not None:
                    signal_it()
                try:
                    p.wait(timeout=max(0.1, deadline - time.monotonic()) if signal_it is None else 3.0)
                    break
                except subprocess.TimeoutExpired:
                    continue
        for c in self.children:
            c.popen = None


def _backoff(exits: int) -> float:
    first, most = RESTART_BACKOFF_S
    return min(most, first * 2 ** max(0, exits - 1))


def _close_stdin(p: subprocess.Popen[bytes]) -> None:
    try:
        if p.stdin is not None:
            p.stdin.close()
    except OSError:
        pass  # the child is gone already


def _child_main() -> int:
    """The child: settings from the first stdin line; stops at end of stdin (the mapper closed it or died)."""
    from mapper.work.worker import run
    from protocol.runtime import install_stop_handlers, setup_logging

    config = WorkerConfig.model_validate_json(sys.stdin.readline())
    setup_logging(f"worker[{config.id}]", config.log_level)
    stop = install_stop_handlers()

    def watch() -> None:
        while sys.stdin.readline():
            pass
        stop.set()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    return run(config, stop)


if __name__ == "__main__":
    sys.exit(_child_main())
