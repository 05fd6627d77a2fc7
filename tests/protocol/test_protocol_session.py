"""Session opening: one-line errors for users, retry until the router appears."""

from __future__ import annotations

import logging
import threading

import pytest

from protocol.session import (
    ZenohUnavailable,
    clean_error,
    client,
    open_session,
    open_session_retrying,
    router,
)
from tests.support.procs import Proc, endpoint, free_port

RUST = ("Unable to connect to any of [Single(tcp/127.0.0.1:1)]!  at "
        "/root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/cc83980/zenoh/src/net/runtime/orchestrator.rs:447.")


def test_clean_error_drops_rust_source_locations_and_extra_lines() -> None:
    assert clean_error(RuntimeError(RUST)) == "Unable to connect to any of [Single(tcp/127.0.0.1:1)]!"
    assert clean_error(RuntimeError("first line\nsecond")) == "first line"
    assert clean_error(RuntimeError()) == "RuntimeError"


def test_unreachable_router_is_one_line_naming_the_endpoint() -> None:
    ep = endpoint(free_port())
    with pytest.raises(ZenohUnavailable) as err:
        open_session(client(ep))
    msg = str(err.value)
    assert ep in msg and ".rs:" not in msg and "\n" not in msg


@pytest.mark.integration
def test_cli_error_without_router_has_no_traceback_or_source_path() -> None:
    p = Proc(["query", "--connect", endpoint(free_port()), "snapshot"])
    assert p.wait(30) == 4  # unreachable (protocol/exits.py)
    p.stop()
    lines = [line for line in p.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("argus query: cannot open a Zenoh session"), p.output
    assert ".cargo" not in p.output and "Traceback" not in p.output


@pytest.mark.integration
def test_retrying_open_waits_for_a_router_that_starts_later(caplog: pytest.LogCaptureFixture) -> None:
    ep = endpoint(free_port())
    stop = threading.Event()
    opened: list[object] = []
    waits = iter([0.2] * 100)
    t = threading.Thread(target=lambda: opened.append(
        open_session_retrying(client(ep), stop, logging.getLogger("t"), lambda: next(waits))))
    with caplog.at_level(logging.WARNING):
        t.start()
        t.join(1.0)  # no router yet: still retrying
        assert t.is_alive() and not opened
        with open_session(router(ep)):
            t.join(20)
            assert opened and opened[0] is not None
            opened[0].close()  # type: ignore[attr-defined]
    assert any("retrying in 0.2 s" in r.getMessage() and ep in r.getMessage() for r in caplog.records)


def test_retrying_open_gives_up_when_stopped() -> None:
    stop = threading.Event()
    stop.set()
    assert open_session_retrying(client(endpoint(free_port())), stop, logging.getLogger("t")) is None
