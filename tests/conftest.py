"""Shared fixtures and the ``integration`` marker.

A test is marked ``integration`` when it lives under tests/integration/, when it uses a fixture that starts
processes or opens Zenoh sessions (``router``, ``procs``, ``client_factory``, directly or through another
fixture), or by its own ``@pytest.mark.integration`` / module ``pytestmark``. An unmarked test that starts a
process or opens a Zenoh session fails with the reason, so ``-m "not integration"`` never starts one.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tests.support.procs import Proc, endpoint, free_port, wait_port
from tests.support.robot import RobotClient

# Mappers started by tests (in-process or as processes, which inherit this) start no local worker process
# (``[workers] local``, default 1): tests of the offloader start their workers themselves, and
# tests/mapper/work/test_work_local.py sets ``local`` explicitly.
os.environ["ARGUS_LOCAL_WORKERS"] = "0"
INTEGRATION_DIR = Path(__file__).parent / "integration"
PROCESS_FIXTURES = {"router", "procs", "client_factory"}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        in_dir = INTEGRATION_DIR in item.path.parents
        if in_dir or PROCESS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.integration)


def _starts_a_process(args: Any) -> bool:
    """Whether a Popen command runs Python (an ``argus`` process, a fresh interpreter), ``argus`` or a server
    (``rerun``); tools a library probes with (``uname``, ``openssl``, ...) are not process-starting tests."""
    argv = [args] if isinstance(args, str | bytes | os.PathLike) else list(args)
    prog = Path(os.fsdecode(argv[0])).name if argv else ""
    return prog.startswith(("python", "argus", "rerun")) or prog == Path(sys.executable).name


@pytest.fixture(autouse=True)
def _unmarked_tests_start_no_process(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Outside ``integration`` tests, starting a process or opening a Zenoh session is an error."""
    if request.node.get_closest_marker("integration") is not None:
        return

    def refuse() -> None:
        raise RuntimeError(f"{request.node.nodeid} starts a process or opens a Zenoh session: mark it "
                           "@pytest.mark.integration (tests/README.md)")

    popen_init = subprocess.Popen.__init__

    def guarded_popen(self: subprocess.Popen[bytes], args: Any, *rest: Any, **kw: Any) -> None:
        if _starts_a_process(args):
            refuse()
        popen_init(self, args, *rest, **kw)

    def guarded_open(*_: object, **__: object) -> None:
        refuse()

    monkeypatch.setattr(subprocess.Popen, "__init__", guarded_popen)
    monkeypatch.setattr(zenoh, "open", guarded_open)


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
