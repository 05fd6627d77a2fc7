"""A router, a publisher and a subscriber as separate processes on loopback."""

from __future__ import annotations

import json
import signal
import threading

import pytest

from protocol.keys import Keys
from protocol.session import client, open_session
from tests.support.procs import Proc, wait_for

pytestmark = pytest.mark.integration


def _Py(module_args: list[str]) -> Proc:
    """A ``python -m <module> ...`` process."""
    return Proc(module_args[1:], module=module_args[0])


def _json_lines(p: Proc) -> list[dict]:
    out = []
    for line in list(p.lines):
        if line.startswith("{"):
            out.append(json.loads(line))
    return out


def test_frames_flow_intact_through_a_router(router: str, procs: list[Proc]) -> None:
    sub = _Py(["deploy.loopback", "subscribe", "--endpoint", router, "--frames", "5"])
    procs.append(sub)
    wait_for(lambda: any(m.get("ready") for m in _json_lines(sub)), 20, what="subscriber ready")
    pub = _Py(["deploy.loopback", "publish", "--endpoint", router, "--frames", "5"])
    procs.append(pub)
    assert sub.wait(timeout=60) == 0, sub.output
    pub.wait(timeout=30)
    sent = {m["sent"]: m["sha1"] for m in _json_lines(pub) if "sent" in m}
    got = {m["received"]: m for m in _json_lines(sub) if "received" in m}
    assert len(got) == 5
    for seq, m in got.items():
        assert m["sha1"] == sent[seq]  # payload intact
        assert (m["width"], m["height"]) == (640, 480)  # decodes to the size the header announced
        assert m["source_id"] == "demo-cam" and m["key"] == Keys().cam_frame("demo-cam")


def test_liveliness_token_follows_its_process(router: str, procs: list[Proc]) -> None:
    keys = Keys()
    events: list[tuple[str, str]] = []
    lock = threading.Lock()

    def on_alive(sample) -> None:  # noqa: ANN001
        with lock:
            events.append((str(sample.kind).split(".")[-1], str(sample.key_expr)))

    token_key = keys.alive("publisher", "demo-cam")
    with open_session(client(router)) as session:
        sub = session.liveliness().declare_subscriber(keys.all_alive, on_alive, history=True)
        pub = _Py(["deploy.loopback", "publish", "--endpoint", router, "--frames", "0"])
        procs.append(pub)
        wait_for(lambda: ("PUT", token_key) in events, 20, what="token to appear")
        pub.signal(signal.SIGKILL)  # even a crash withdraws the token (session lease)
        wait_for(lambda: ("DELETE", token_key) in events, 30, what="token to disappear")
        sub.undeclare()


def test_router_exits_cleanly_on_sigint(procs: list[Proc]) -> None:
    from tests.support.procs import endpoint, free_port, wait_port

    port = free_port()
    r = Proc(["router", "--listen", endpoint(port)])
    procs.append(r)
    wait_port(port)
    r.signal(signal.SIGINT)
    assert r.wait(timeout=15) == 0
    assert "shutting down" in r.output


def test_router_refuses_a_bad_config_with_a_message(tmp_path) -> None:  # noqa: ANN001
    r = Proc(["router", "--config", str(tmp_path / "missing.json5")])
    assert r.wait(timeout=30) == 2
    r.stop()
    assert "argus router:" in r.output


def test_router_refuses_plugin_config_it_cannot_load(tmp_path) -> None:  # noqa: ANN001
    conf = tmp_path / "storage.json5"
    conf.write_text('{ mode: "router", plugins: { storage_manager: { storages: { g: { key_expr: "argus/**",'
                    ' volume: "memory" } } } } }')
    r = Proc(["router", "--config", str(conf)])
    assert r.wait(timeout=30) == 2
    r.stop()
    assert "configures Zenoh plugins (storage_manager)" in r.output and "zenohd" in r.output
