from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from tests.support.procs import Proc, endpoint, free_port, wait_port
from tests.support.robot import RobotClient


@pytest.fixture
def router() -> Iterator[str]:
    """A real ``argus router`` process on a free loopback port; yields its endpoint."""
    port = free_port()
    proc = Proc(["router", "--listen", endpoint(port)])
    try:
        wait_port(port)
        yield endpoint(port)
    finally:
        proc.stop()


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Processes appended here are stopped (whole process group) at teardown."""
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        p.stop()


@pytest.fixture
def client_factory() -> Iterator[Callable[[str], RobotClient]]:
    """Makes planner-like peers of one robot (``tests.support.robot.RobotClient``); closed at teardown."""
    made: list[RobotClient] = []

    def make(router: str) -> RobotClient:
        c = RobotClient(router)
        made.append(c)
        return c

    yield make
    for c in made:
        c.close()
