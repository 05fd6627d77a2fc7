"""The rate-limited bad-input log shared by mapper, planner and robot agent (exact, on an injected clock)."""

from __future__ import annotations

import logging

import pytest

from protocol.ratelog import MAX_LINE_CHARS, RateLimitedLog, clean


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def lines(caplog: pytest.LogCaptureFixture, level: int = logging.WARNING) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == level]


def test_first_of_each_reason_then_one_summary_per_period(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    bad = RateLimitedLog(logging.getLogger("test.ratelog"), period_s=10.0, clock=clock)
    with caplog.at_level(logging.WARNING):
        assert bad.warning("decode_errors", "bad goal %d", 1)
        assert not bad.warning("decode_errors", "bad goal %d", 2)
        assert bad.warning("bad_keys", "bad key %s", "x")  # another reason is not held back by the first
        for i in range(3205):
            clock.t += 0.001
            assert not bad.warning("decode_errors", "bad goal %d", i)
        assert bad.held() == {"decode_errors": 3206}
        clock.t = 109.99  # the first held-back message came at 100.0: no summary before 110.0
        assert not bad.flush()
        clock.t = 110.0
        assert bad.flush()
        assert not bad.flush()  # nothing held any more
        assert bad.warning("decode_errors", "bad goal %d", 99)  # the reason's last full line was 10 s ago
        assert not bad.warning("decode_errors", "bad goal %d", 100)
        assert bad.warning("bad_keys", "bad key %s", "y")  # last logged at 100.0
        assert not bad.warning("bad_keys", "bad key %s", "z")
        clock.t = 119.9
        assert not bad.flush()
        clock.t = 120.0
        assert bad.flush()
    assert lines(caplog) == [
        "bad goal 1",
        "bad key x",
        "3206 more bad inputs in the last 10 s (not logged one by one): decode_errors x3206",
        "bad goal 99",
        "bad key y",
        "2 more bad inputs in the last 10 s (not logged one by one): bad_keys x1, decode_errors x1",
    ]
    assert bad.logged == 6


def test_a_burst_with_no_later_input_is_summarised_by_flush_alone(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    bad = RateLimitedLog(logging.getLogger("test.ratelog"), period_s=5.0, clock=clock)
    with caplog.at_level(logging.WARNING):
        for i in range(50):
            bad.warning("goals_garbage", "garbage %d", i)
        clock.t += 5.0
        bad.flush()
        bad.flush(force=True)  # nothing held: no line
    assert lines(caplog) == [
        "garbage 0", "49 more bad inputs in the last 5 s (not logged one by one): goals_garbage x49",
    ]


def test_force_flush_and_level(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    bad = RateLimitedLog(logging.getLogger("test.ratelog"), period_s=10.0, level=logging.INFO, clock=clock)
    with caplog.at_level(logging.INFO):
        bad.warning("goals_refused", "refusing %s", "g1")
        bad.warning("goals_refused", "refusing %s", "g2")
        assert bad.flush(force=True)
    assert lines(caplog, logging.INFO) == [
        "refusing g1", "1 more bad inputs in the last 0 s (not logged one by one): goals_refused x1",
    ]
    assert lines(caplog, logging.WARNING) == []


def test_reasons_are_bounded(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    bad = RateLimitedLog(logging.getLogger("test.ratelog"), period_s=10.0, max_reasons=3, clock=clock)
    with caplog.at_level(logging.WARNING):
        for i in range(100):
            assert bad.warning(f"r{i}", "x")
            assert not bad.warning(f"r{i}", "x")
    assert len(bad._seen) == 3
    assert set(bad.held()) == {"r97", "r98", "r99"}  # forgotten reasons take their held counts with them


def test_peer_text_cannot_forge_lines_or_flood_them(caplog: pytest.LogCaptureFixture) -> None:
    bad = RateLimitedLog(logging.getLogger("test.ratelog"), clock=Clock())
    with caplog.at_level(logging.WARNING):
        bad.warning("query_errors", "bad query %s", "a\nWARNING forged line\r" + "x" * 5000)
        bad.warning("wrong_format", "%d items", "not a number")
    (first, second) = lines(caplog)
    assert "\n" not in first and "\r" not in first and first.startswith("bad query a\\nWARNING forged line\\r")
    assert len(first) == MAX_LINE_CHARS and first.endswith("...")
    assert second.startswith("%d items ('not a number',)")
    assert clean("short") == "short"


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError):
        RateLimitedLog(logging.getLogger("x"), period_s=0)
    with pytest.raises(ValueError):
        RateLimitedLog(logging.getLogger("x"), max_reasons=0)


# --- the processes use it: issue 19 counted 3,207 WARNING lines for 3,207 bad goals ---------------------------
class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Payload(data)


def test_the_robot_logs_one_line_for_3207_garbage_goals(caplog: pytest.LogCaptureFixture) -> None:
    from tests.support.robot import agent_with_fakes

    agent = agent_with_fakes()
    with caplog.at_level(logging.WARNING, logger="argus.robot_agent"):
        for i in range(3207):
            agent.on_goal_bytes(b"junk %d" % i)
        agent.tick(0.0)
    assert agent.counters.get("goals_garbage") == 3207
    assert len(lines(caplog)) == 1 and lines(caplog)[0].startswith("refusing an unreadable goal payload")
    assert agent.bad_input.held() == {"goals_garbage": 3206}  # summarised on a tick once 10 s have passed
    assert agent.bad_input.flush(force=True)
    assert lines(caplog)[-1].startswith("3206 more bad inputs")


def test_the_planner_logs_one_line_per_reason_for_a_flood(caplog: pytest.LogCaptureFixture) -> None:
    from planner.config import PlannerNodeConfig
    from planner.node import PlannerNode

    node = PlannerNode(PlannerNodeConfig())
    with caplog.at_level(logging.WARNING, logger="argus.planner"):
        for i in range(3207):
            node.on_delta(_Sample("argus/default/graph/delta", b"\x93junk%d" % i))  # type: ignore[arg-type]
            node.on_snapshot(_Sample("argus/default/graph/snapshot", b""))  # type: ignore[arg-type]
    assert node.counters.get("decode_errors") == 2 * 3207
    assert len(lines(caplog)) == 1 and lines(caplog)[0].startswith("dropping bad graph_delta")
