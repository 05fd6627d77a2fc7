"""The process shell (:class:`protocol.node.Node`): session with retry, declarations undone in order,
liveliness, status, stop. Two peers on loopback, multicast scouting off (the settings' default)."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
import zenoh

from protocol.codec import decode
from protocol.keys import Keys
from protocol.messages import Status
from protocol.node import Node, Stopped
from protocol.session import Backoff, ReconnectConfig, ZenohSettings, open_session
from protocol.transport import Counters
from tests.support.procs import endpoint, free_port, wait_for

KEYS = Keys("nodetest")


class Entity:
    """Something declared: records when it is undeclared."""

    def __init__(self, name: str, log: list[str], fail: bool = False) -> None:
        self.name, self.log, self.fail = name, log, fail

    def undeclare(self) -> None:
        self.log.append(self.name)
        if self.fail:
            raise zenoh.ZError("already closed")


@pytest.fixture
def peer() -> Iterator[tuple[ZenohSettings, zenoh.Session]]:
    """Settings of a node listening on a free loopback port, and a second peer connected to it."""
    ep = endpoint(free_port())
    node_settings = ZenohSettings(mode="peer", connect=[], listen=[ep])
    with open_session(ZenohSettings(mode="peer", connect=[ep])) as watcher:
        yield node_settings, watcher


def test_backoff_grows_caps_and_resets() -> None:
    b = Backoff(ReconnectConfig(initial_s=0.5, max_s=3.0, factor=2.0))
    assert [b.next_wait_s() for _ in range(5)] == [0.5, 1.0, 2.0, 3.0, 3.0]
    b.reset()
    assert b.next_wait_s() == 0.5


def test_counters_ema_takes_the_first_value_then_moves_a_fifth_of_the_way() -> None:
    c = Counters()
    c.ema("t", 10.0)
    assert c.get("t") == 10.0
    c.ema("t", 20.0)
    assert c.get("t") == pytest.approx(12.0)
    c.ema("t", 20.0, alpha=0.5)
    assert c.get("t") == pytest.approx(16.0)


def test_a_stop_before_the_session_opens_is_a_clean_exit_and_the_body_never_runs() -> None:
    stop = threading.Event()
    stop.set()
    ran: list[Node] = []
    node = Node(ZenohSettings(mode="client", connect=[endpoint(free_port())]), KEYS, "t", "n1", stop=stop)
    assert node.run(ran.append) == 0 and not ran
    with pytest.raises(Stopped):
        node.__enter__()
    with pytest.raises(RuntimeError, match="not open"):
        _ = node.session


def test_the_session_is_retried_with_the_backoff_until_stopped() -> None:
    stop = threading.Event()
    counters = Counters()
    node = Node(ZenohSettings(mode="client", connect=[endpoint(free_port())]), KEYS, "t", "n1", stop=stop,
                counters=counters, reconnect=ReconnectConfig(initial_s=0.02, max_s=0.05))
    ran: list[Node] = []
    result: list[int] = []
    t = threading.Thread(target=lambda: result.append(node.run(ran.append)))
    t.start()
    try:
        wait_for(lambda: counters.get("session_attempts") >= 3, 10, what="three attempts")
    finally:
        stop.set()
        t.join(10)
    assert result == [0] and not ran


@pytest.mark.integration
def test_declarations_are_undone_newest_first_then_the_session_closes(
    peer: tuple[ZenohSettings, zenoh.Session]) -> None:
    settings, _ = peer
    log: list[str] = []
    node = Node(settings, KEYS, "t", "n1", stop=threading.Event())
    with node:
        session = node.session
        node.declared(Entity("first", log))
        node.declared(Entity("broken", log, fail=True))  # a failing undeclare does not stop the shutdown
        node.on_exit(lambda: log.append("callback"))
        node.declared(Entity("last", log))
        assert log == []
    assert log == ["last", "callback", "broken", "first"]
    assert session.is_closed()
    with pytest.raises(RuntimeError):
        _ = node.session


@pytest.mark.integration
def test_an_error_in_the_body_still_shuts_down_and_propagates(peer: tuple[ZenohSettings, zenoh.Session]) -> None:
    settings, _ = peer
    log: list[str] = []

    def body(node: Node) -> None:
        node.declared(Entity("pub", log))
        raise ValueError("boom")

    with pytest.raises(ValueError, match="boom"):
        Node(settings, KEYS, "t", "n1", stop=threading.Event()).run(body)
    assert log == ["pub"]


@pytest.mark.integration
def test_token_status_and_messages_reach_a_peer_and_go_at_exit(peer: tuple[ZenohSettings, zenoh.Session]) -> None:
    settings, watcher = peer
    alive: list[str] = []
    statuses: list[Status] = []
    samples: list[bytes] = []
    watcher.liveliness().declare_subscriber(KEYS.all_alive_of("t"), lambda s: alive.append(str(s.kind)))
    watcher.declare_subscriber(KEYS.status("t", "n1"), lambda s: statuses.append(decode(s.payload.to_bytes(), Status)))
    stop = threading.Event()
    got: list[bytes] = []

    def body(node: Node) -> None:
        node.subscribe(KEYS.graph_delta, lambda s: got.append(s.payload.to_bytes()))
        pub = node.publisher(KEYS.map_points, important=False)
        node.alive()
        node.status(extra=lambda: {"extra_value": 7})
        wait_for(lambda: len(alive) == 1 and bool(statuses), 10, what="the token and a status")
        watcher.declare_subscriber(KEYS.map_points, lambda s: samples.append(s.payload.to_bytes()))
        wait_for(lambda: bool(pub.put(b"x") or samples), 10, what="a sample at the peer")
        wait_for(lambda: bool(watcher.put(KEYS.graph_delta, b"d") or got), 10, what="a sample from the peer")
        node.counters.add("done")
        node.error("something failed", state="degraded")

    Node(settings, KEYS, "t", "n1", stop=stop, status_period_s=0.05).run(body)
    wait_for(lambda: len(alive) == 2, 10, what="the token to go")
    assert alive[0].endswith("PUT") and alive[1].endswith("DELETE")
    first, last = statuses[0], statuses[-1]  # the last one is published at exit
    assert (first.role, first.node_id, first.state, first.counters["extra_value"]) == ("t", "n1", "ok", 7.0)
    assert last.counters["done"] == 1.0 and last.state == "degraded" and last.last_error == "something failed"
    assert samples[0] == b"x" and got[0] == b"d"


@pytest.mark.integration
def test_latest_value_answers_a_late_joiner_and_is_undeclared(peer: tuple[ZenohSettings, zenoh.Session]) -> None:
    settings, watcher = peer

    def get() -> list[bytes]:
        return [r.ok.payload.to_bytes() for r in watcher.get(KEYS.map_points, timeout=1.0) if r.ok is not None]

    def body(node: Node) -> None:
        latest = node.latest(node.publisher(KEYS.map_points))
        latest.put(b"newest")
        wait_for(lambda: get() == [b"newest"], 10, what="the queryable")

    Node(settings, KEYS, "t", "n1", stop=threading.Event()).run(body)
    assert get() == []
