"""One Zenoh session config builder for every Argus process.

Multicast scouting is **off** unless explicitly enabled, and processes find each other through
explicit endpoints (``tcp/127.0.0.1:7447`` by default, or the comma-separated endpoints of the
``ARGUS_CONNECT`` environment variable; ``ARGUS_SITE`` likewise replaces the default site ``default``).
Precedence everywhere: a command-line flag, then the config file, then the environment, then the
built-in default. Processes that connect to a router should run
in ``client`` mode. Shared memory is off by default (killed processes leave ``/dev/shm`` files and
the loopback TCP path is fast enough for JPEG frames).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_SITE = "default"
ENV_CONNECT = "ARGUS_CONNECT"
ENV_SITE = "ARGUS_SITE"


def default_endpoints() -> list[str]:
    """``ARGUS_CONNECT`` (comma-separated Zenoh endpoints) if set, else ``[DEFAULT_ENDPOINT]``."""
    raw = os.environ.get(ENV_CONNECT, "")
    endpoints = [e.strip() for e in raw.split(",") if e.strip()]
    return endpoints or [DEFAULT_ENDPOINT]


def default_site() -> str:
    """``ARGUS_SITE`` if set, else ``default`` (validated like every site name where it is used)."""
    return os.environ.get(ENV_SITE, "").strip() or DEFAULT_SITE


class ZenohSettings(BaseModel):
    """How a process joins the Zenoh network."""

    model_config = ConfigDict(extra="forbid")
    mode: Literal["peer", "client", "router"] = Field(
        default="client", description="client (connects to a router), peer, or router"
    )
    connect: list[str] = Field(
        default_factory=default_endpoints,
        description=f"endpoints to connect to, e.g. tcp/127.0.0.1:7447 (default: ${ENV_CONNECT} or {DEFAULT_ENDPOINT})",
    )
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on (routers, peers)")
    config_file: Path | None = Field(default=None, description="optional json5 Zenoh config applied first")
    multicast_scouting: bool = Field(
        default=False, description="UDP multicast discovery; keep off unless the LAN is yours"
    )
    shared_memory: bool = Field(default=False, description="Zenoh shared-memory transport between local processes")
    overrides: dict[str, Any] = Field(
        default_factory=dict, description="extra Zenoh config keys (json5 paths such as 'transport/link/tx/lease')"
    )


def build_config(settings: ZenohSettings) -> zenoh.Config:
    """Turn :class:`ZenohSettings` into a ``zenoh.Config``."""
    import zenoh

    conf = zenoh.Config.from_file(str(settings.config_file)) if settings.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(settings.shared_memory))
    for key, value in settings.overrides.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class ZenohUnavailable(RuntimeError):
    """A Zenoh session could not be opened; the message is one line, fit for a user."""


_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def clean_error(e: BaseException) -> str:
    """One line of ``e`` without the Rust source location zenoh appends (``at /root/.cargo/...rs:447.``)."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return _RUST_LOCATION.sub("", text).strip()


def describe_endpoints(settings: ZenohSettings) -> str:
    parts = [f"mode {settings.mode}"]
    if settings.connect:
        parts.append("connect " + ", ".join(settings.connect))
    if settings.listen:
        parts.append("listen " + ", ".join(settings.listen))
    return "; ".join(parts)


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a Zenoh session (use it as a context manager: ``with open_session(s) as session:``).

    Raises :class:`ZenohUnavailable` with a one-line message naming the endpoints.
    """
    import zenoh

    zenoh.init_log_from_env_or("error")
    try:
        return zenoh.open(build_config(settings))
    except Exception as e:  # noqa: BLE001 - zenoh raises ZError for everything; one message for the user
        where = describe_endpoints(settings)
        raise ZenohUnavailable(f"cannot open a Zenoh session ({where}): {clean_error(e)}") from None


def open_session_retrying(
    settings: ZenohSettings,
    stop: threading.Event,
    logger: logging.Logger,
    next_wait_s: Callable[[], float] | None = None,
) -> zenoh.Session | None:
    """Open a session, retrying until it works or ``stop`` is set (then ``None``).

    Waits ``next_wait_s()`` between attempts (default: 0.5 s doubling to 10 s) and logs one line each.
    Every long-running process starts this way, so it may start before its router.
    """
    wait = 0.25

    def doubling() -> float:
        nonlocal wait
        wait = min(10.0, wait * 2)
        return wait

    pause = next_wait_s or doubling
    while not stop.is_set():
        try:
            return open_session(settings)
        except ZenohUnavailable as e:
            seconds = pause()
            logger.warning("%s; retrying in %.1f s", e, seconds)
            stop.wait(seconds)
    return None


def client(endpoint: str = DEFAULT_ENDPOINT) -> ZenohSettings:
    """Settings of a client connecting to one router endpoint."""
    return ZenohSettings(mode="client", connect=[endpoint])


def router(endpoint: str = DEFAULT_ENDPOINT) -> ZenohSettings:
    """Settings of a router listening on one endpoint."""
    return ZenohSettings(mode="router", connect=[], listen=[endpoint])
