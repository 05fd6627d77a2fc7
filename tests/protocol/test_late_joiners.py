"""Late joiners: a consumer that connects after a value was published gets it with one ``get``."""

from __future__ import annotations

import time

import pytest
import zenoh

from protocol.codec import decode
from protocol.messages import RobotState, Status
from protocol.session import client, open_session
from protocol.transport import LatestValue, declare_message_publisher
from tests.support.robot import KEYS, RID, start_agent


def _latest(session: zenoh.Session, key: str, timeout: float = 1.0) -> list[zenoh.Sample]:
    return [r.ok for r in session.get(key, timeout=timeout) if r.ok is not None]


def test_latest_value_answers_late_getters_with_the_newest_payload(router: str) -> None:
    key = KEYS.map_points
    with open_session(client(router)) as pub_session, open_session(client(router)) as late:
        value = LatestValue(pub_session, declare_message_publisher(pub_session, key, important=False))
        time.sleep(0.3)  # declarations reach the router
        assert _latest(late, key) == []  # nothing published yet: no reply, not a made-up value
        value.put(b"first")
        value.put(b"second")
        samples = _latest(late, key)
        assert [s.payload.to_bytes() for s in samples] == [b"second"]
        assert str(samples[0].key_expr) == key and samples[0].encoding == value.publisher.encoding
        assert value.queries == 1
        value.undeclare()
        time.sleep(0.3)
        assert _latest(late, key) == []


def test_robot_state_and_status_reach_a_late_joiner_within_one_second(tmp_path, router, procs, client_factory):
    start_agent(tmp_path, router, procs, client_factory)
    with open_session(client(router)) as late:  # joins after the robot published its idle state
        states = _latest(late, KEYS.robot_state(RID))  # answered within the get's 1 s timeout or not at all
        statuses = _latest(late, KEYS.all_status)
    assert [decode(s.payload.to_bytes(), RobotState).robot_id for s in states] == [RID]
    assert [decode(s.payload.to_bytes(), Status).node_id for s in statuses] == [RID]


@pytest.mark.integration
def test_link_watch_says_when_the_router_goes_and_comes_back(caplog) -> None:  # noqa: ANN001
    import logging

    from protocol.session import router as router_settings
    from protocol.transport import Counters, LinkWatch
    from tests.support.procs import endpoint, free_port, wait_for

    ep = endpoint(free_port())
    counters = Counters()
    r = open_session(router_settings(ep))
    with open_session(client(ep)) as c, caplog.at_level(logging.INFO):
        watch = LinkWatch(c, counters, "test")
        assert watch.check() and counters.get("links") == 1
        r.close()
        wait_for(lambda: not watch.check(), timeout=10, what="the link to go")
        assert counters.get("link_losses") == 1 and counters.get("links") == 0
        assert any("no Zenoh link" in m for m in caplog.messages)
        r = open_session(router_settings(ep))
        wait_for(watch.check, timeout=20, what="the client to reconnect")
        assert any("link back after" in m for m in caplog.messages)
    r.close()
