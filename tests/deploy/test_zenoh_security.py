"""The shipped security configs work: TLS with mutual authentication, and access control by user.

The access-control tests are strict: after the publisher has been told of the subscriber (its
matching status, not a sleep), N puts give N samples; a denied put is followed by an allowed one on
the same link, so when the allowed one arrives the denied one would have arrived before it.
"""

from __future__ import annotations

import shutil
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh

from deploy.acl import Principal, access_control
from protocol.codec import DecodeError, decode
from protocol.keys import Keys
from protocol.messages import Status
from protocol.session import ZenohSettings, ZenohUnavailable, open_session
from protocol.transport import decode_frame_sample
from tests.support.procs import REPO, Proc, endpoint, free_port, wait_for, wait_port

ZENOH_DIR = REPO / "deploy" / "zenoh"
PASSWORDS = dict(line.split(":", 1) for line in (ZENOH_DIR / "users.txt").read_text().split())
N_PUTS = 20


def _user(ep: str, user: str) -> ZenohSettings:
    return ZenohSettings(mode="client", connect=[ep], overrides={
        "transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": PASSWORDS[user]})


class _Inbox:
    def __init__(self) -> None:
        self.keys: list[str] = []
        self.payloads: list[bytes] = []
        self._lock = threading.Lock()

    def __call__(self, sample) -> None:  # noqa: ANN001 - zenoh.Sample
        with self._lock:
            self.keys.append(str(sample.key_expr))
            self.payloads.append(sample.payload.to_bytes())

    def count(self, payload: bytes) -> int:
        with self._lock:
            return self.payloads.count(payload)


def _acl_router(tmp_path: Path, procs: list[Proc]) -> str:
    shutil.copy(ZENOH_DIR / "router-acl.json5", tmp_path)
    shutil.copy(ZENOH_DIR / "users.txt", tmp_path)
    port = free_port()
    ep = endpoint(port)
    procs.append(Proc(["router", "--config", str(tmp_path / "router-acl.json5"), "--listen", ep], cwd=tmp_path))
    wait_port(port)
    return ep


def _told_of_subscriber(pub: zenoh.Publisher, what: str) -> None:
    """The publisher's router has declared a matching subscriber to it (else its puts never leave)."""
    wait_for(lambda: pub.matching_status.matching, 10, what=f"{what}: the publisher told of a subscriber")


def _n_of_n(pub: zenoh.Publisher, inbox: _Inbox, payload: bytes, what: str) -> None:
    _told_of_subscriber(pub, what)
    for _ in range(N_PUTS):
        pub.put(payload)
    wait_for(lambda: inbox.count(payload) >= N_PUTS, 10, what=f"{what}: {N_PUTS} puts")
    assert inbox.count(payload) == N_PUTS


def test_shipped_acl_is_generated_by_deploy_acl() -> None:
    """router-acl.json5 is the deploy/acl.py output for its principals (so the two cannot drift)."""
    import json

    conf = zenoh.Config.from_file(str(ZENOH_DIR / "router-acl.json5"))
    shipped = json.loads(conf.get_json("access_control"))
    principals = [Principal("cam-01", "edge-camera", "cam-01"), Principal("robot-01", "robot-agent", "robot-01"),
                  Principal("mapper", "mapper", "mapper"), Principal("planner", "planner", "planner"),
                  Principal("viewer", "consumer", "viewer"), Principal("monitor", "monitor", "monitor")]
    want = access_control(principals)
    for section in ("rules", "subjects", "policies"):
        got = [{k: v for k, v in item.items() if v is not None} for item in shipped[section]]
        assert got == want[section], section
    assert {p.user for p in principals} == set(PASSWORDS)


def test_access_control_every_role_strictly(tmp_path: Path, procs: list[Proc]) -> None:
    ep = _acl_router(tmp_path, procs)
    keys = Keys()
    frames, graph, goals, consumer = _Inbox(), _Inbox(), _Inbox(), _Inbox()
    with (
        open_session(_user(ep, "mapper")) as mapper,
        open_session(_user(ep, "planner")) as planner,
        open_session(_user(ep, "viewer")) as viewer,
        open_session(_user(ep, "cam-01")) as cam,
        open_session(_user(ep, "robot-01")) as robot,
        open_session(_user(ep, "cam-01")) as cam_reader,  # not `cam`: a session's own puts reach it locally
    ):
        cam_read = _Inbox()
        subs = [cam_reader.declare_subscriber(k, cam_read) for k in (keys.all_frames, keys.graph_all,
                                                                      keys.robot_goal("robot-01"))]
        subs += [mapper.declare_subscriber(keys.all_frames, frames),
                mapper.declare_subscriber(keys.graph_all, graph),
                robot.declare_subscriber(keys.robot_goal("robot-01"), goals),
                # ACL rules match key expressions, not supersets: consumers subscribe to graph/** itself.
                viewer.declare_subscriber(keys.graph_all, consumer),
                viewer.declare_subscriber(keys.all_frames, consumer)]
        cam_pub = cam.declare_publisher(keys.cam_frame("cam-01"))
        robot_pub = robot.declare_publisher(keys.robot_frame("robot-01"))
        goal_pub = planner.declare_publisher(keys.robot_goal("robot-01"))
        delta_pub = mapper.declare_publisher(keys.graph_delta)
        # Allowed traffic: N of N, each after the publisher knows of the subscriber.
        _n_of_n(cam_pub, frames, b"cam-01 frame", "camera -> mapper")
        _n_of_n(robot_pub, frames, b"robot-01 frame", "robot -> mapper")
        _n_of_n(goal_pub, goals, b"goal", "planner -> robot")
        _n_of_n(delta_pub, consumer, b"delta", "mapper -> consumer")
        # Denied: a camera forging another camera's frame and a goal, a consumer writing the graph.
        # Each is followed by an allowed put on the same link (and goals by a real goal on the
        # robot's link), so the forged ones would have arrived first.
        for _ in range(N_PUTS):
            cam.put(keys.cam_frame("cam-02"), b"forged frame")
            cam.put(keys.robot_frame("robot-01"), b"forged frame")
            cam.put(keys.robot_goal("robot-01"), b"forged goal")
            viewer.put(keys.graph_delta, b"forged delta")
        cam_pub.put(b"cam sentinel")
        wait_for(lambda: frames.count(b"cam sentinel") == 1, 10, what="the camera's sentinel frame")
        goal_pub.put(b"goal sentinel")
        wait_for(lambda: goals.count(b"goal sentinel") == 1, 10, what="the planner's sentinel goal")
        delta_pub.put(b"delta sentinel")
        wait_for(lambda: graph.count(b"delta sentinel") == 1, 10, what="the mapper's sentinel delta")
        assert frames.count(b"forged frame") == 0 and keys.cam_frame("cam-02") not in frames.keys
        assert goals.count(b"forged goal") == 0, "a camera's goal reached the robot"
        assert graph.count(b"forged delta") == 0, "a consumer wrote into the graph"
        assert not [k for k in consumer.keys if k.endswith("/frame")], "a consumer received camera frames"
        # The mapper may not send goals, the planner may not write the graph.
        for _ in range(N_PUTS):
            mapper.put(keys.robot_goal("robot-01"), b"mapper goal")
            planner.put(keys.graph_delta, b"planner delta")
        delta_pub.put(b"delta sentinel 2")
        wait_for(lambda: consumer.count(b"delta sentinel 2") == 1, 10, what="the mapper's second sentinel")
        goal_pub.put(b"goal sentinel 2")
        wait_for(lambda: goals.count(b"goal sentinel 2") == 1, 10, what="the planner's second sentinel")
        assert goals.count(b"mapper goal") == 0 and consumer.count(b"planner delta") == 0
        assert cam_read.keys == [], "a camera read frames, graph or goals"
        for s in subs:
            s.undeclare()


def test_a_camera_cannot_impersonate_another_process(tmp_path: Path, procs: list[Proc]) -> None:
    """Liveliness tokens (what health and the planner trust) only under a login's own role and id."""
    ep = _acl_router(tmp_path, procs)
    keys = Keys()
    alive = _Inbox()
    with open_session(_user(ep, "monitor")) as monitor, open_session(_user(ep, "cam-01")) as cam:
        sub = monitor.liveliness().declare_subscriber(keys.all_alive, alive, history=True)
        forged = [cam.liveliness().declare_token(keys.alive("mapper", "mapper")),
                  cam.liveliness().declare_token(keys.alive("edge-camera", "cam-02"))]
        own = cam.liveliness().declare_token(keys.alive("edge-camera", "cam-01"))  # same link, after the forged
        wait_for(lambda: keys.alive("edge-camera", "cam-01") in alive.keys, 10, what="the camera's own token")
        assert keys.alive("mapper", "mapper") not in alive.keys, "a camera posed as the mapper"
        assert keys.alive("edge-camera", "cam-02") not in alive.keys, "a camera posed as another camera"
        for t in [*forged, own]:
            t.undeclare()
        sub.undeclare()


def test_real_edge_camera_through_the_shipped_acl(tmp_path: Path, procs: list[Proc]) -> None:
    """A real ``argus edge-camera`` logged in as cam-01: its frames and status get through."""
    ep = _acl_router(tmp_path, procs)
    shutil.copy(ZENOH_DIR / "client-acl-example.json5", tmp_path)
    keys = Keys()
    frames: list[str] = []
    statuses: list[Status] = []
    alive = _Inbox()

    def on_frame(sample) -> None:  # noqa: ANN001
        frames.append(decode_frame_sample(sample).header.source_id)

    def on_status(sample) -> None:  # noqa: ANN001
        try:
            statuses.append(decode(sample.payload.to_bytes(), Status))
        except DecodeError:
            pass

    with open_session(_user(ep, "mapper")) as mapper, open_session(_user(ep, "monitor")) as monitor:
        subs = [mapper.declare_subscriber(keys.all_frames, on_frame),
                monitor.declare_subscriber(keys.all_status, on_status),
                monitor.liveliness().declare_subscriber(keys.all_alive, alive, history=True)]
        cam = Proc(["edge-camera", "--id", "cam-01", "--source", "pattern", "--rate", "10", "--width", "64",
                    "--height", "48", "--connect", ep, "--set", "status_period_s=0.5",
                    "--set", f"zenoh.config_file={tmp_path / 'client-acl-example.json5'}"])
        procs.append(cam)
        wait_for(lambda: len(frames) >= 5, 30, what=f"5 real frames at the mapper; camera output:\n{cam.output}")
        wait_for(lambda: any(s.counters.get("frames_sent", 0) >= 1 for s in statuses), 15,
                 what="the camera's Status at the monitor")
        assert set(frames) == {"cam-01"}
        assert keys.alive("edge-camera", "cam-01") in alive.keys
        for s in subs:
            s.undeclare()


def test_wrong_password_cannot_join(tmp_path: Path, procs: list[Proc]) -> None:
    ep = _acl_router(tmp_path, procs)
    bad = ZenohSettings(mode="client", connect=[ep], overrides={
        "transport/auth/usrpwd/user": "cam-01", "transport/auth/usrpwd/password": "wrong",
        "connect/timeout_ms": 2000, "connect/exit_on_failure": True})
    with pytest.raises(ZenohUnavailable):
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
    with pytest.raises(ZenohUnavailable):
        open_session(ZenohSettings(mode="client", connect=[ep], overrides=no_cert))
