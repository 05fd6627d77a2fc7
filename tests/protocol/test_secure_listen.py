"""Loopback-only by default: a plaintext listen endpoint on a non-loopback address is refused unless
``--insecure``; every process takes ``--zenoh-config``. No test here binds a non-loopback address:
the refusals happen before any socket is opened, and the ``insecure`` path is only built, never opened."""

from __future__ import annotations

import importlib
import json
import logging
import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from protocol.session import (
    DEFAULT_ENDPOINT,
    InsecureListenError,
    ZenohSettings,
    build_config,
    endpoint_is_loopback,
    exposed_plaintext,
)
from protocol.tomlconfig import process_values
from tests.support.procs import REPO, Proc, endpoint, free_port

LAN = "tcp/192.168.1.10:7447"  # only ever a string here


@pytest.mark.parametrize(("ep", "loopback"), [
    ("tcp/127.0.0.1:7447", True), ("tcp/127.3.2.1:1", True), ("tcp/[::1]:7447", True),
    ("tcp/localhost:7447", True), ("tcp/0.0.0.0:7447", False), ("tcp/[::]:7447", False),
    (LAN, False), ("tcp/mapper.lan:7447", False), ("udp/10.0.0.2:7447", False),
    ("tcp/127.0.0.1:7447#iface=lo", True),
])
def test_endpoint_is_loopback(ep: str, loopback: bool) -> None:
    assert endpoint_is_loopback(ep) is loopback


def test_exposed_plaintext_ignores_tls_quic_and_local_sockets() -> None:
    eps = ["tls/192.168.1.10:7447", "quic/0.0.0.0:7447", "unixsock-stream//tmp/z.sock", LAN, "tcp/0.0.0.0:1"]
    assert exposed_plaintext(eps) == [LAN, "tcp/0.0.0.0:1"]


def test_plaintext_lan_listen_is_refused_without_insecure() -> None:
    for mode in ("router", "peer"):
        with pytest.raises(ValidationError, match="refusing to listen on tcp/192.168.1.10:7447"):
            ZenohSettings(mode=mode, connect=[], listen=[LAN])
    ZenohSettings(mode="client", connect=[DEFAULT_ENDPOINT], listen=[LAN])  # a client never listens


def test_insecure_builds_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    conf = build_config(ZenohSettings(mode="router", connect=[], listen=[LAN], insecure=True))  # built, never opened
    assert json.loads(conf.get_json("listen/endpoints")) == [LAN]
    assert any("INSECURE" in r.message and LAN in r.message for r in caplog.records)


def test_tls_may_listen_on_the_lan() -> None:
    conf = build_config(ZenohSettings(mode="router", connect=[], listen=["tls/192.168.1.10:7447"]))
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/192.168.1.10:7447"]


def test_a_config_file_listening_on_the_lan_is_refused(tmp_path: Path) -> None:
    cfg = tmp_path / "router.json5"
    cfg.write_text('{ mode: "router", listen: { endpoints: ["tcp/0.0.0.0:7447"] } }')
    with pytest.raises(InsecureListenError):
        build_config(ZenohSettings(mode="router", connect=[], config_file=cfg))


def test_zenoh_every_interface_default_becomes_loopback(tmp_path: Path) -> None:
    cfg = tmp_path / "router.json5"
    cfg.write_text('{ mode: "router" }')  # no listen section: Zenoh alone would listen on tcp/[::]:7447
    conf = build_config(ZenohSettings(mode="router", connect=[], config_file=cfg))
    assert json.loads(conf.get_json("listen/endpoints")) == [DEFAULT_ENDPOINT]
    conf = build_config(ZenohSettings(mode="peer", connect=[]))
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]


@pytest.mark.integration
def test_router_cli_refuses_a_plaintext_lan_endpoint() -> None:
    p = Proc(["router", "--listen", LAN])
    assert p.wait(30) == 2
    p.stop()
    assert "refusing to listen on tcp/192.168.1.10:7447" in p.output and "--insecure" in p.output


@pytest.mark.integration
def test_mapper_cli_refuses_a_plaintext_lan_endpoint_in_peer_mode() -> None:
    p = Proc(["mapper", "--mode", "peer", "--listen", "tcp/0.0.0.0:7447", "--connect", endpoint(free_port())])
    assert p.wait(60) == 2
    p.stop()
    assert "refusing to listen on tcp/0.0.0.0:7447" in p.output and "Traceback" not in p.output


@pytest.mark.parametrize("module", ["mapper.cli", "planner.cli", "robot_agent.cli", "edge_camera.cli"])
def test_every_process_takes_zenoh_config_and_insecure(module: str) -> None:
    a = importlib.import_module(module).parser().parse_args(["--zenoh-config", "c.json5", "--insecure"])
    values = process_values(a)
    assert values["zenoh.config_file"] == "c.json5" and values["zenoh.insecure"] is True
    a = importlib.import_module(module).parser().parse_args([])
    assert "zenoh.config_file" not in process_values(a) and "zenoh.insecure" not in process_values(a)


def test_client_tls_example_command_parses() -> None:
    """client-tls.json5 documents a command line: it must be one the mapper accepts."""
    from mapper.cli import parser

    text = (REPO / "deploy" / "zenoh" / "client-tls.json5").read_text()
    cmd = re.search(r"`argus mapper ([^`]+)`", text)
    assert cmd is not None
    a = parser().parse_args(cmd.group(1).split())
    assert a.zenoh_config == Path("deploy/zenoh/client-tls.json5")
