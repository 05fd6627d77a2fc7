"""Helpers for integration tests: free loopback ports, CLI processes in their own process group,
and waiting on events with timeouts (never fixed sleeps)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def wait_for(predicate: Callable[[], bool], timeout: float = 20.0, interval: float = 0.05, what: str = "") -> None:
    """Poll ``predicate`` until true; fail with ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout:.0f}s waiting for {what or predicate}")


def wait_port(port: int, timeout: float = 20.0) -> None:
    """Wait until something listens on 127.0.0.1:port."""

    def listening() -> bool:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            return s.connect_ex(("127.0.0.1", port)) == 0

    wait_for(listening, timeout, what=f"port {port}")


class Proc:
    """An ``argus`` CLI process (or ``python -m <module>``) in its own process group, output captured."""

    def __init__(
        self,
        args: list[str],
        env: dict[str, str] | None = None,
        cwd: Path | None = None,
        module: str = "deploy.cli",
    ) -> None:
        full_env = dict(os.environ)
        full_env["PYTHONUNBUFFERED"] = "1"
        full_env.update(env or {})
        self.args = args
        self.popen = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            cwd=str(cwd or REPO),
            env=full_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int = signal.SIGINT) -> None:
        if self.alive():
            os.killpg(self.popen.pid, sig)

    def wait(self, timeout: float = 20.0) -> int:
        return self.popen.wait(timeout=timeout)

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGINT, then SIGKILL the whole process group if it does not exit in time."""
        if self.popen.poll() is None:
            try:
                os.killpg(self.popen.pid, signal.SIGINT)
                self.popen.wait(timeout=timeout)
            except (subprocess.TimeoutExpired, ProcessLookupError):
                try:
                    os.killpg(self.popen.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.popen.wait(timeout=5)
        self._reader.join(timeout=2)
        return self.popen.returncode


class FramePeer:
    """A client session collecting one source's frames and its process's Status messages.

    Subclasses add their own subscriptions to ``self._subs`` (liveliness, robot state, ...).
    """

    def __init__(self, router: str, frame_key: str, status_key: str) -> None:
        from protocol.session import ZenohSettings, open_session

        self.session = open_session(ZenohSettings(mode="client", connect=[router]))
        self.frames: list = []
        self.statuses: list = []
        self._lock = threading.Lock()
        self._subs = [
            self.session.declare_subscriber(frame_key, self._on_frame),
            self.session.declare_subscriber(status_key, self._on_status),
        ]

    def _on_frame(self, sample) -> None:  # noqa: ANN001 - zenoh.Sample
        from protocol.transport import decode_frame_sample

        frame = decode_frame_sample(sample)
        with self._lock:
            self.frames.append(frame)

    def _on_status(self, sample) -> None:  # noqa: ANN001
        from protocol.codec import DecodeError, decode
        from protocol.messages import Status

        try:
            msg = decode(sample.payload.to_bytes(), Status)
        except DecodeError:
            return
        with self._lock:
            self.statuses.append(msg)

    def n_frames(self) -> int:
        with self._lock:
            return len(self.frames)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()
