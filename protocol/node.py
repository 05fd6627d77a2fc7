"""The one process shell of every long-running Argus process (camera, robot, mapper, planner, worker).

A :class:`Node` owns what each process would otherwise write again: the Zenoh session, opened with
retry and back-off (a process may start before its router); every publisher, subscriber, queryable and
liveliness token it declares, undeclared in reverse order on exit; the liveliness token
``alive/<role>/<id>``; the :class:`~protocol.transport.StatusReporter` on ``status/<role>/<id>``; the stop
event (SIGINT/SIGTERM unless the caller passes its own) and the orderly shutdown. A process is its own
logic plus a few lines::

    def serve(node: Node) -> None:
        node.subscribe(keys.robot_goal(rid), on_goal)
        pub = node.publisher(keys.robot_state(rid), message=RobotState)
        node.alive()
        node.status(extra=lambda: {"steps": steps})
        while node.running:
            ...

    Node(config.zenoh, keys, "robot-agent", rid, counters=counters).run(serve)

``run`` returns 0 after a stop, also a stop that came before the session could be opened. A process class
derives from :class:`Process`: it makes its node in ``__init__`` and serves in ``serve(node)``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from protocol.codec import MSGPACK_MIME
from protocol.keys import Keys
from protocol.messages import Message
from protocol.session import Backoff, ReconnectConfig, ZenohSettings, open_session_retrying
from protocol.transport import Counters, LatestValue, StatusReporter, declare_frame_publisher, declare_message_publisher

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)


class _Undeclarable(Protocol):
    def undeclare(self) -> None: ...


U = TypeVar("U", bound=_Undeclarable)


class Stopped(Exception):
    """The stop event was set before the session could be opened: nothing to run, a clean exit."""


class Node:
    """A process's Zenoh session and everything declared on it; a context manager, or ``run(body, stop)``.

    ``stop``: the event that ends the process (default: one set on SIGINT/SIGTERM, installed when the node
    opens, so open it in the main thread). ``reconnect``: the back-off between attempts to open the
    session; each retry counts ``session_attempts`` in ``counters``. Nothing happens until it is opened.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        keys: Keys,
        role: str,
        node_id: str,
        *,
        counters: Counters | None = None,
        status_period_s: float = 1.0,
        stop: threading.Event | None = None,
        reconnect: ReconnectConfig | None = None,
        logger: logging.Logger | None = None,
    ) -> None:
        self.settings, self.keys, self.role, self.node_id = settings, keys, role, node_id
        self.counters = counters if counters is not None else Counters()
        self.status_period_s = status_period_s
        self._stop = stop
        self.reconnect = reconnect or ReconnectConfig()
        self.log = logger or log
        self.reporter: StatusReporter | None = None
        self._session: zenoh.Session | None = None
        self._stack = contextlib.ExitStack()

    # -- lifetime ----------------------------------------------------------------------------------
    def __enter__(self) -> Node:
        if self._stop is None:
            from protocol.runtime import install_stop_handlers

            self._stop = install_stop_handlers()
        backoff = Backoff(self.reconnect)

        def next_wait_s() -> float:
            self.counters.add("session_attempts")
            return backoff.next_wait_s()

        session = open_session_retrying(self.settings, self._stop, self.log, next_wait_s)
        if session is None:
            raise Stopped
        self._session, self.reporter = session, None
        return self

    def __exit__(self, *exc: object) -> None:
        """Undo every declaration (newest first: the status goes before what it reports on), then close."""
        session, self._session = self._session, None
        try:
            self._stack.close()
        finally:
            if session is not None:
                session.close()

    def run(self, body: Callable[[Node], None], stop: threading.Event | None = None) -> int:
        """Open the session, run ``body(self)`` until it returns (it watches :attr:`running`), shut down in
        order; 0 (a clean exit) after a stop, also one before the session could be opened. ``stop`` replaces
        the node's stop event."""
        if stop is not None:
            self._stop = stop
        try:
            with self:
                body(self)
        except Stopped:
            pass
        return 0

    @property
    def stop(self) -> threading.Event:
        """The stop event (set once the node is opened)."""
        if self._stop is None:
            raise RuntimeError(f"{self.role} {self.node_id}: not started")
        return self._stop

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError(f"{self.role} {self.node_id}: the session is not open")
        return self._session

    @property
    def is_open(self) -> bool:
        return self._session is not None

    @property
    def running(self) -> bool:
        """False once the stop event is set."""
        return not self.stop.is_set()

    def on_exit(self, callback: Callable[[], object]) -> None:
        """Call ``callback`` at shutdown, before whatever was declared before it is undeclared."""
        self._stack.callback(callback)

    # -- declarations (all undone on exit) -----------------------------------------------------------
    def declared(self, entity: U) -> U:
        """Hold ``entity`` (anything with ``undeclare()``) until the node closes; returns it."""
        self._stack.callback(_undeclare, entity, self.log)
        return entity

    def publisher(self, key: str, *, message: type[Message] | None = None, important: bool = True,
                  mime: str = MSGPACK_MIME, block: bool | None = None) -> zenoh.Publisher:
        """A codec-message publisher (:func:`~protocol.transport.declare_message_publisher`)."""
        return self.declared(declare_message_publisher(self.session, key, important=important, message=message,
                                                       mime=mime, block=block))

    def frame_publisher(self, key: str, *, block: bool = False) -> zenoh.Publisher:
        """A JPEG frame publisher (:func:`~protocol.transport.declare_frame_publisher`)."""
        return self.declared(declare_frame_publisher(self.session, key, block=block))

    def latest(self, publisher: zenoh.Publisher) -> LatestValue:
        """``publisher`` whose newest payload also answers queries on its key (late joiners)."""
        return self.declared(LatestValue(self.session, publisher))

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], Any]) -> zenoh.Subscriber[None]:
        return self.declared(self.session.declare_subscriber(key, callback))

    def queryable(self, key: str, callback: Callable[[zenoh.Query], Any]) -> zenoh.Queryable[None]:
        return self.declared(self.session.declare_queryable(key, callback))

    def watch_alive(self, key: str, callback: Callable[[zenoh.Sample], Any]) -> zenoh.Subscriber[None]:
        """Liveliness tokens on ``key`` appearing (PUT) and disappearing (DELETE)."""
        return self.declared(self.session.liveliness().declare_subscriber(key, callback))

    def alive(self) -> zenoh.LivelinessToken:
        """This process's liveliness token ``alive/<role>/<id>``: declare it once the process can serve."""
        return self.declared(self.session.liveliness().declare_token(self.keys.alive(self.role, self.node_id)))

    def status(self, extra: Callable[[], dict[str, Any]] | None = None) -> StatusReporter:
        """Start the Status on ``status/<role>/<id>``: published now, then every period, a last time at exit
        (before anything declared earlier is undeclared)."""
        reporter = StatusReporter(self.session, self.keys.status(self.role, self.node_id), self.role, self.node_id,
                                  self.counters, self.status_period_s, extra=extra)
        self.reporter = self._stack.enter_context(reporter)
        return reporter

    def error(self, message: str, state: str | None = None) -> None:
        """Show ``message`` (and ``state``, e.g. ``degraded``) in the Status from now on."""
        if self.reporter is not None:
            self.reporter.last_error = message
            if state is not None:
                self.reporter.state = state


def _undeclare(entity: _Undeclarable, logger: logging.Logger) -> None:
    try:
        entity.undeclare()
    except Exception as e:  # noqa: BLE001 - shutdown goes on: the session may already be closing
        logger.debug("undeclare failed: %s", e)


class Process:
    """A long-running process: its node (made in the subclass's ``__init__``, nothing opened) and its ``serve``."""

    node: Node

    def serve(self, node: Node) -> None:
        """Declare what the process needs on ``node``, then work while ``node.running``."""
        raise NotImplementedError

    def run(self, stop: threading.Event | None = None) -> int:
        """Serve until ``stop`` is set (default: SIGINT/SIGTERM); the router may start later. 0 after a stop."""
        return self.node.run(self.serve, stop)
