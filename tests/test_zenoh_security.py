"""The shipped security configs work: TLS with mutual authentication, and access control by user."""

from __future__ import annotations

import shutil
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh

from protocol.keys import Keys
from protocol.session import ZenohSettings, open_session
from tests.procs import REPO, Proc, endpoint, free_port, wait_for, wait_port

ZENOH_DIR = REPO / "deploy" / "zenoh"
PASSWORDS = dict(line.split(":", 1) for line in (ZENOH_DIR / "users.txt").read_text().split())


def _user(ep: str, user: str) -> ZenohSettings:
    return ZenohSettings(mode="client", connect=[ep], overrides={
        "transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": PASSWORDS[user]})


class _Inbox:
    def __init__(self) -> None:
        self.keys: list[str] = []
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:  # noqa: ANN001 - zenoh.Sample
        with self._lock:
            self.keys.append(str(sample.key_expr))


def test_access_control_lets_each_role_do_only_its_part(tmp_path: Path, procs: list[Proc]) -> None:
    shutil.copy(ZENOH_DIR / "router-acl.json5", tmp_path)
    shutil.copy(ZENOH_DIR / "users.txt", tmp_path)
    port = free_port()
    ep = endpoint(port)
    procs.append(Proc(["router", "--config", str(tmp_path / "router-acl.json5"), "--listen", ep], cwd=tmp_path))
    wait_port(port)
    keys = Keys()
    mapper_in, viewer_in = _Inbox(), _Inbox()
    with (
        open_session(_user(ep, "mapper")) as mapper,
        open_session(_user(ep, "viewer")) as viewer,
        open_session(_user(ep, "cam-01")) as cam,
    ):
        # ACL rules match key expressions, not supersets: consumers subscribe to graph/** itself.
        subs = [mapper.declare_subscriber(keys.all_frames, mapper_in),
                viewer.declare_subscriber(keys.graph_all, viewer_in),
                viewer.declare_subscriber(keys.all_frames, viewer_in)]
        # The camera may put its own frames only; wait on a sentinel rather than sleeping.
        wait_for(lambda: (cam.put(keys.cam_frame("cam-02"), b"spoof"), cam.put(keys.cam_frame("cam-01"), b"ok"),
                          keys.cam_frame("cam-01") in mapper_in.keys)[-1], 20, what="cam-01 frame at mapper")
        # The mapper's graph reaches the consumer; frames never do.
        wait_for(lambda: (mapper.put(keys.graph_delta, b"d"), keys.graph_delta in viewer_in.keys)[-1], 20,
                 what="graph delta at the consumer")
        assert keys.cam_frame("cam-02") not in mapper_in.keys, "a camera put another camera's frame key"
        assert not [k for k in viewer_in.keys if k.endswith("/frame")], "a consumer received camera frames"
        # A consumer may not publish into the graph.
        wait_for(lambda: (viewer.put(keys.graph_node("evil"), b"x"), mapper.put(keys.graph_snapshot, b"s"),
                          keys.graph_snapshot in viewer_in.keys)[-1], 20, what="snapshot at the consumer")
        mapper_graph = _Inbox()
        subs.append(mapper.declare_subscriber(keys.graph_all, mapper_graph))
        wait_for(lambda: (viewer.put(keys.graph_node("evil"), b"x"), mapper.put(keys.graph_node("n1"), b"n"),
                          keys.graph_node("n1") in viewer_in.keys)[-1], 20, what="node at the consumer")
        assert keys.graph_node("evil") not in mapper_graph.keys
        for s in subs:
            s.undeclare()


def test_wrong_password_cannot_join(tmp_path: Path, procs: list[Proc]) -> None:
    shutil.copy(ZENOH_DIR / "router-acl.json5", tmp_path)
    shutil.copy(ZENOH_DIR / "users.txt", tmp_path)
    port = free_port()
    ep = endpoint(port)
    procs.append(Proc(["router", "--config", str(tmp_path / "router-acl.json5"), "--listen", ep], cwd=tmp_path))
    wait_port(port)
    bad = ZenohSettings(mode="client", connect=[ep], overrides={
        "transport/auth/usrpwd/user": "cam-01", "transport/auth/usrpwd/password": "wrong",
        "connect/timeout_ms": 2000, "connect/exit_on_failure": True})
    with pytest.raises(zenoh.ZError):
        open_session(bad)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_mutual_tls(tmp_path: Path, procs: list[Proc]) -> None:
    subprocess.run(["bash", str(ZENOH_DIR / "make_certs.sh"), str(tmp_path / "certs")], check=True,
                   capture_output=True)
    shutil.copy(ZENOH_DIR / "router-tls.json5", tmp_path)
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    procs.append(Proc(["router", "--config", str(tmp_path / "router-tls.json5"), "--listen", ep], cwd=tmp_path))
    wait_port(port)
    tls = {f"transport/link/tls/{k}": str(tmp_path / "certs" / v) for k, v in
           {"root_ca_certificate": "ca.crt", "connect_private_key": "client.key",
            "connect_certificate": "client.crt"}.items()}
    tls["transport/link/tls/enable_mtls"] = True
    inbox = _Inbox()
    with (
        open_session(ZenohSettings(mode="client", connect=[ep], overrides=tls)) as a,
        open_session(ZenohSettings(mode="client", connect=[ep], overrides=tls)) as b,
    ):
        sub = a.declare_subscriber("argus/**", inbox)
        wait_for(lambda: (b.put("argus/default/cam/c/frame", b"x"), bool(inbox.keys))[-1], 20, what="TLS put")
        sub.undeclare()
    # Without a client certificate the router refuses the connection.
    no_cert = {k: v for k, v in tls.items() if k.endswith(("root_ca_certificate", "enable_mtls"))}
    no_cert.update({"connect/timeout_ms": 2000, "connect/exit_on_failure": True})
    with pytest.raises(zenoh.ZError):
        open_session(ZenohSettings(mode="client", connect=[ep], overrides=no_cert))
