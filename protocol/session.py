"""One Zenoh session config builder for every Argus process.

Multicast scouting is **off** unless explicitly enabled, and processes find each other through
explicit endpoints (``tcp/127.0.0.1:7447`` by default, or the comma-separated endpoints of the
``ARGUS_CONNECT`` environment variable; ``ARGUS_SITE`` likewise replaces the default site ``default``).
Precedence everywhere: a command-line flag, then the config file, then the environment, then the
built-in default. Processes that connect to a router should run
in ``client`` mode. Shared memory is off by default (killed processes leave ``/dev/shm`` files and
the loopback TCP path is fast enough for JPEG frames).

Listening is loopback-only unless encrypted: a router or peer refuses to listen on a non-loopback
address with a plaintext protocol (``tcp/0.0.0.0:7447``, ``tcp/192.168.1.10:7447``) unless
``insecure`` is set (``--insecure``; a warning is logged). ``tls/`` and ``quic/`` endpoints may listen
anywhere. Where no listen endpoint is given at all, Zenoh's own default (every interface) is replaced
by a loopback one.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

if TYPE_CHECKING:
    import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_SITE = "default"
ENV_CONNECT = "ARGUS_CONNECT"
ENV_SITE = "ARGUS_SITE"
_ENDPOINT = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*/\S+$")


def default_endpoints() -> list[str]:
    """``ARGUS_CONNECT`` (comma-separated Zenoh endpoints) if set, else ``[DEFAULT_ENDPOINT]``."""
    raw = os.environ.get(ENV_CONNECT, "")
    endpoints = [e.strip() for e in raw.split(",") if e.strip()]
    return endpoints or [DEFAULT_ENDPOINT]


def default_site() -> str:
    """``ARGUS_SITE`` if set, else ``default`` (validated like every site name where it is used)."""
    return os.environ.get(ENV_SITE, "").strip() or DEFAULT_SITE


# Where Zenoh would listen on every interface by default, Argus listens on loopback.
LOOPBACK_LISTEN = {"router": [DEFAULT_ENDPOINT], "peer": ["tcp/127.0.0.1:0"]}
ENCRYPTED_PROTOCOLS = ("tls", "quic")
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe")

log = logging.getLogger(__name__)


class ZenohConfigError(ValueError):
    """A Zenoh configuration that cannot work (a bad config file, an exposed plaintext endpoint): not retried."""


class InsecureListenError(ZenohConfigError):
    """A plaintext listen endpoint on a non-loopback address, without ``insecure``."""


def endpoint_is_loopback(endpoint: str) -> bool:
    """True for ``<proto>/127.x.x.x:<port>``, ``<proto>/[::1]:<port>`` and ``<proto>/localhost:<port>``.

    Host names other than ``localhost`` count as non-loopback (they are not resolved here).
    """
    _, _, address = endpoint.partition("/")
    host = address.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposed_plaintext(endpoints: list[str]) -> list[str]:
    """The endpoints that would listen unencrypted on a non-loopback address."""
    out = []
    for ep in endpoints:
        proto = ep.split("/", 1)[0].lower()
        if proto not in ENCRYPTED_PROTOCOLS and proto not in LOCAL_PROTOCOLS and not endpoint_is_loopback(ep):
            out.append(ep)
    return out


def check_listen(endpoints: list[str], insecure: bool) -> None:
    """Raise :class:`InsecureListenError` for plaintext non-loopback endpoints (a warning if ``insecure``)."""
    exposed = exposed_plaintext(endpoints)
    if not exposed:
        return
    if not insecure:
        raise InsecureListenError(
            f"refusing to listen on {', '.join(exposed)}: plaintext on a non-loopback address (anyone on that "
            "network could read every frame and inject goals). Use a tls/ endpoint with certificates "
            "(argus up --secure sets them up, see docs/SECURITY.md) or pass --insecure to accept the risk")
    log.warning("INSECURE: listening on %s without TLS or authentication (--insecure)", ", ".join(exposed))


class ReconnectConfig(BaseModel):
    """Back-off between attempts to reach the router (or to reopen a failed source)."""

    model_config = ConfigDict(extra="forbid")
    initial_s: float = Field(default=0.5, gt=0, description="first wait after a fault")
    max_s: float = Field(default=10.0, gt=0, description="longest wait between attempts")
    factor: float = Field(default=2.0, ge=1.0, description="wait multiplier per consecutive failure")


class Backoff:
    """Exponential back-off: ``initial_s``, then times ``factor`` per failure, capped at ``max_s``."""

    def __init__(self, config: ReconnectConfig) -> None:
        self.config = config
        self.failures = 0

    def next_wait_s(self) -> float:
        c = self.config
        wait = min(c.max_s, c.initial_s * c.factor**self.failures)
        self.failures += 1
        return wait

    def reset(self) -> None:
        self.failures = 0


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
    insecure: bool = Field(
        default=False,
        description="allow listening on a non-loopback address without TLS (plaintext, no authentication); "
        "logs a warning. Off: such a listen endpoint is refused",
    )

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        for ep in v:
            if not _ENDPOINT.match(ep):
                raise ValueError(f"{ep!r} is not a Zenoh endpoint (<protocol>/<address>, e.g. {DEFAULT_ENDPOINT})")
        return v

    @model_validator(mode="after")
    def _listen_is_safe(self) -> ZenohSettings:
        if self.mode != "client" and not self.insecure and exposed_plaintext(self.listen):
            check_listen(self.listen, insecure=False)
        return self


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
    if settings.mode != "client":
        check_listen(_loopback_by_default(conf, settings.mode), settings.insecure)
    return conf


class ZenohUnavailable(RuntimeError):
    """A Zenoh session could not be opened; the message is one line, fit for a user."""


def clean_error(e: BaseException) -> str:
    """One line of ``e`` without the Rust source location zenoh appends (``at /root/.cargo/...rs:447.``) or
    its debug wrapping (``Json5Err(Message { msg: ... })``)."""
    from protocol.exits import one_line

    return one_line(e)


def describe_endpoints(settings: ZenohSettings) -> str:
    parts = [f"mode {settings.mode}"]
    if settings.connect:
        parts.append("connect " + ", ".join(settings.connect))
    if settings.listen:
        parts.append("listen " + ", ".join(settings.listen))
    return "; ".join(parts)


def _loopback_by_default(conf: zenoh.Config, mode: str) -> list[str]:
    """The endpoints ``conf`` listens on; Zenoh's every-interface default becomes a loopback one."""
    import zenoh

    listen = json.loads(conf.get_json("listen/endpoints"))
    if listen == json.loads(zenoh.Config().get_json("listen/endpoints")):
        listen = LOOPBACK_LISTEN[mode]
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    elif isinstance(listen, dict):  # a mode-dependent value from a config file
        listen = listen.get(mode) or []
    return [str(ep) for ep in listen]


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a Zenoh session (use it as a context manager: ``with open_session(s) as session:``).

    Raises :class:`ZenohUnavailable` with a one-line message naming the endpoints.
    """
    import zenoh

    zenoh.init_log_from_env_or("error")
    where = describe_endpoints(settings)
    try:
        conf = build_config(settings)
    except ZenohConfigError:
        raise
    except Exception as e:  # noqa: BLE001 - e.g. a json5 file zenoh cannot read: a config error, not retried
        raise ZenohConfigError(f"bad Zenoh configuration ({where}): {clean_error(e)}") from None
    try:
        return zenoh.open(conf)
    except Exception as e:  # noqa: BLE001 - zenoh raises ZError for everything; one message for the user
        raise ZenohUnavailable(f"cannot open a Zenoh session ({where}): {clean_error(e)}") from None


def open_session_retrying(
    settings: ZenohSettings,
    stop: threading.Event,
    logger: logging.Logger,
    next_wait_s: Callable[[], float] | None = None,
) -> zenoh.Session | None:
    """Open a session, retrying until it works or ``stop`` is set (then ``None``).

    Waits ``next_wait_s()`` between attempts (default: :class:`Backoff`, 0.5 s doubling to 10 s) and logs one
    line each. Every long-running process starts this way (:class:`protocol.node.Node`), so it may start
    before its router.
    """
    pause = next_wait_s or Backoff(ReconnectConfig()).next_wait_s
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
