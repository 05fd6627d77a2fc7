"""The mapper's per-source rate-limited warning (frames dropped for a bad pose)."""

from __future__ import annotations

import logging

import pytest

from mapper import node
from mapper.node import PerSourceLog


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> Clock:
    c = Clock()
    monkeypatch.setattr(node.time, "monotonic", c)
    return c


def messages(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_one_warning_per_source_per_period_then_the_held_back_count(
    clock: Clock, caplog: pytest.LogCaptureFixture
) -> None:
    log = PerSourceLog(logging.getLogger("test.pose"), period_s=10.0)
    with caplog.at_level(logging.WARNING):
        assert log.warning("a", "a1")
        assert not log.warning("a", "a2")
        assert log.warning("b", "b1")  # another source is not held back by a
        clock.t += 9.9
        assert not log.warning("a", "a3")
        clock.t += 0.1
        assert log.warning("a", "a4")
        clock.t += 10.0
        assert log.warning("a", "a5")
    assert messages(caplog) == ["a1", "b1", "a4 (2 more from a held back since the last report)", "a5"]


def test_made_up_sources_do_not_grow_it_without_bound(clock: Clock, caplog: pytest.LogCaptureFixture) -> None:
    log = PerSourceLog(logging.getLogger("test.pose"), period_s=10.0, max_sources=3)
    with caplog.at_level(logging.WARNING):
        for i in range(100):
            assert log.warning(f"fake{i}", "x")
        assert len(log._last) == 3
        assert not log.warning("fake99", "x")  # the newest ones are still remembered
        assert log.warning("fake0", "x")  # forgotten: reported again, sooner than the period
