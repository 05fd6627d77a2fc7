"""``argus up --secure``: the shipped multi-machine stack over TLS with one login per process and an ACL.

The stack is ``deploy/launch/multi-machine.toml`` (router, mapper, planner, a robot, two cameras) on a
free loopback port with the ORACLE mapper backend (light enough for a test machine). The test shows
that allowed traffic flows (real frames reach the mapper, graph deltas reach a consumer through the real
``argus query``, the planner's goals reach the robot) and that every denied action has no effect.

How a denial is shown without sleeping: a denied put is followed by an allowed put on the same link;
when the allowed one arrives, the denied one, had the router forwarded it, would have arrived first.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from deploy.acl import Principal
from deploy.secure import SecuritySpec, make_ca, make_cert, principals
from deploy.up import LaunchFile, Stack, load_launch
from protocol.codec import decode, encode
from protocol.keys import Keys
from protocol.messages import NbvGoal
from protocol.session import ZenohSettings, ZenohUnavailable, open_session
from tests.support.procs import REPO, Proc, endpoint, free_port, wait_for

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")

SHIPPED = REPO / "deploy" / "launch" / "multi-machine.toml"
N = 20


class Inbox:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []
        self.keys: list[str] = []
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.payloads.append(sample.payload.to_bytes())
            self.keys.append(str(sample.key_expr))

    def count(self, payload: bytes) -> int:
        with self._lock:
            return self.payloads.count(payload)

    def __len__(self) -> int:
        with self._lock:
            return len(self.payloads)


def _launch_text(port: int) -> str:
    text = SHIPPED.read_text()
    text = text.replace('endpoint = "tls/127.0.0.1:7447"', f'endpoint = "tls/127.0.0.1:{port}"')
    text = text.replace('geometry = { backend = "mvs" }', 'geometry = { backend = "oracle" }')
    assert f":{port}" in text and '"oracle" }' in text, "multi-machine.toml changed: update this test"
    return text


def test_shipped_multi_machine_launch_is_secure() -> None:
    launch = load_launch(SHIPPED)
    assert launch.security is not None and launch.security.enabled
    assert launch.endpoint.startswith("tls/127.0.0.1:")
    users = {p.user: p for p in principals(launch, SHIPPED.parent, launch.security)}
    assert users["cam_kitchen"] == Principal("cam_kitchen", "edge-camera", "cam_kitchen")
    assert users["robot0"] == Principal("robot0", "robot-agent", "robot0")
    assert {p.role for p in users.values()} == {"edge-camera", "robot-agent", "mapper", "planner", "consumer",
                                                "monitor"}


def test_secure_needs_a_tls_endpoint_and_known_ids(tmp_path: Path) -> None:
    from deploy.secure import prepare

    router = {"name": "r", "command": "router"}
    plain = LaunchFile.model_validate({"endpoint": "tcp/127.0.0.1:7447", "process": [router]})
    with pytest.raises(ValueError, match="tls/ endpoint"):
        prepare(plain, tmp_path, SecuritySpec(), ["r"], tmp_path / "s")
    no_id = LaunchFile.model_validate({"endpoint": "tls/127.0.0.1:7447", "process": [
        {"name": "r", "command": "router"}, {"name": "cam", "command": "edge-camera", "settings": {"site": "x"}}]})
    with pytest.raises(ValueError, match="needs its id"):
        prepare(no_id, tmp_path, SecuritySpec(), ["r"], tmp_path / "s")


def test_workers_get_their_own_login_and_the_mapper_its_local_workers_keys(tmp_path: Path) -> None:
    launch = LaunchFile.model_validate({"endpoint": "tls/127.0.0.1:7447", "process": [
        {"name": "r", "command": "router"},
        {"name": "mapper", "command": "mapper", "settings": {"workers": {"local": 2}}},
        {"name": "gpu", "command": "worker", "settings": {"id": "gpu0"}},
        {"name": "w", "command": "worker"}]})
    got = {p.user: p for p in principals(launch, tmp_path, SecuritySpec(consumers=[]))}
    assert got["mapper"] == Principal("mapper", "mapper", "mapper", local_workers=2)
    assert got["gpu"] == Principal("gpu", "worker", "gpu0") and got["w"] == Principal("w", "worker", "worker")
    bad = launch.model_copy(update={"process": [launch.process[0], launch.process[1].model_copy(
        update={"settings": {"workers": {"local": -1}}})]})
    with pytest.raises(ValueError, match="workers"):
        principals(bad, tmp_path, SecuritySpec(consumers=[]))


def test_material_is_kept_and_only_made_on_the_router_machine(tmp_path: Path) -> None:
    """A second start keeps every certificate and password; a camera machine without them is told
    to copy its folder; deleting one folder rotates that login only."""
    from deploy.secure import prepare

    launch = LaunchFile.model_validate_json(json.dumps(_toml(_launch_text(free_port()))))
    sec, d = launch.security or SecuritySpec(), tmp_path / "s"
    with pytest.raises(ValueError, match="copy"):
        prepare(launch, SHIPPED.parent, sec, ["cam_hall"], d)  # nothing there yet, not the router's machine
    site = prepare(launch, SHIPPED.parent, sec, ["router", "mapper", "planner"], d)
    before = {p: p.read_bytes() for p in d.rglob("*") if p.name in ("cert.pem", "key.pem", "password", "ca.crt")}
    assert (d / "ca.key").stat().st_mode & 0o077 == 0 and (d / "cam_hall" / "password").stat().st_mode & 0o077 == 0
    prepare(launch, SHIPPED.parent, sec, ["cam_hall"], d)  # a camera machine with its folder copied: fine
    prepare(launch, SHIPPED.parent, sec, ["router"], d)
    assert before == {p: p.read_bytes() for p in before}
    old_pw = (d / "cam_hall" / "password").read_text()
    shutil.rmtree(d / "cam_hall")
    prepare(launch, SHIPPED.parent, sec, ["router"], d)
    assert (d / "cam_hall" / "password").read_text() != old_pw
    assert f"cam_hall:{(d / 'cam_hall' / 'password').read_text().strip()}" in (d / "router" / "users.txt").read_text()
    cfg = json.loads(site.client_file("cam_hall").read_text())
    assert cfg["transport"]["auth"]["usrpwd"]["user"] == "cam_hall"
    assert cfg["transport"]["link"]["tls"]["enable_mtls"] is True


def _toml(text: str) -> dict:
    import tomllib

    return tomllib.loads(text)


# --- the running stack ---------------------------------------------------------------------------
class Site:
    def __init__(self, secure_dir: Path, ep: str, keys: Keys) -> None:
        self.dir, self.ep, self.keys = secure_dir, ep, keys

    def settings(self, user: str, **overrides: object) -> ZenohSettings:
        return ZenohSettings(mode="client", connect=[self.ep], config_file=self.dir / user / "zenoh.json5",
                             overrides={**overrides, "connect/timeout_ms": 3000, "connect/exit_on_failure": True})

    def session(self, user: str, **overrides: object) -> zenoh.Session:
        return open_session(self.settings(user, **overrides))


def _told_of_subscriber(pub: zenoh.Publisher, what: str) -> None:
    wait_for(lambda: pub.matching_status.matching, 20, what=f"{what}: the publisher told of a subscriber")


def _refused(site: Site, what: str, **overrides: object) -> None:
    with pytest.raises(ZenohUnavailable):
        open_session(site.settings("cam_kitchen", **overrides)).close()
        pytest.fail(f"{what}: a session opened")


@pytest.mark.slow
def test_secure_stack_allows_the_work_and_denies_everything_else(tmp_path: Path, procs: list[Proc]) -> None:
    t0 = time.monotonic()
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    launch = tmp_path / "multi-machine.toml"
    launch.write_text(_launch_text(port))
    secure_dir, ready = tmp_path / "secure", tmp_path / "ready"
    up = Proc(["up", str(launch), "--secure-dir", str(secure_dir), "--ready-file", str(ready)], cwd=tmp_path)
    procs.append(up)
    wait_for(ready.exists, 180, what=f"the secure stack healthy; output:\n{up.output[-3000:]}")
    t_healthy = time.monotonic() - t0
    site, k = Site(secure_dir, ep, Keys("home")), Keys("home")
    assert "secure: TLS on" in up.output

    # Allowed: real frames reach the mapper (observed with the mapper's own login), graph deltas reach a
    # consumer through the real `argus query`, and the planner's goals reach the robot.
    frames, goals, graph = Inbox(), Inbox(), Inbox()
    with (
        site.session("mapper") as mapper_eye,
        site.session("robot0") as robot_eye,
        site.session("viewer") as viewer_eye,
    ):
        subs = [mapper_eye.declare_subscriber(k.all_frames, frames),
                robot_eye.declare_subscriber(k.robot_goal("robot0"), goals),
                viewer_eye.declare_subscriber(k.graph_all, graph)]
        wait_for(lambda: {k.cam_frame("cam_kitchen"), k.cam_frame("cam_hall")} <= set(frames.keys), 60,
                 what="frames of both real cameras at the mapper")
        q = subprocess.run([sys.executable, "-m", "deploy.cli", "query", "--connect", ep, "--site", "home",
                            "--zenoh-config", str(secure_dir / "viewer" / "zenoh.json5"), "watch", "--count", "1",
                            "--idle-timeout", "60"], cwd=REPO, capture_output=True, text=True, timeout=90,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
        assert q.returncode == 0 and re.search(r"v\d+: ", q.stdout), q.stdout + q.stderr
        wait_for(lambda: len(goals) >= 1, 120, what="a planner goal at the robot")
        t_flow = time.monotonic() - t0

        with (
            site.session("cam_kitchen") as cam,
            site.session("planner") as planner,
            site.session("mapper") as mapper2,
            site.session("viewer") as viewer,  # not viewer_eye: a session's own puts reach it locally
        ):
            cam_pub = cam.declare_publisher(k.cam_frame("cam_kitchen"))
            _told_of_subscriber(cam_pub, "camera")
            rogue_goal = encode(NbvGoal(goal_id="rogue", robot_id="robot0", stamp_ns=1, x=9.0, y=9.0, yaw_rad=0.0))
            for _ in range(N):
                cam.put(k.robot_goal("robot0"), rogue_goal)      # a goal from a camera's identity
                cam.put(k.cam_frame("cam_hall"), b"forged frame")  # another camera's frame
                cam.put(k.graph_delta, b"forged delta")           # writing the graph
                viewer.put(k.graph_delta, b"consumer delta")      # a consumer writing the graph
            cam_pub.put(b"cam sentinel")
            wait_for(lambda: frames.count(b"cam sentinel") == 1, 20, what="the camera's sentinel at the mapper")
            list(viewer.get(k.graph_snapshot, timeout=10))  # a round trip on the consumer's link, after its puts
            goal_pub = planner.declare_publisher(k.robot_goal("robot0"))
            _told_of_subscriber(goal_pub, "planner")
            goal_pub.put(b"planner sentinel")
            delta_pub = mapper2.declare_publisher(k.graph_delta)
            _told_of_subscriber(delta_pub, "mapper")
            delta_pub.put(b"mapper sentinel")
            wait_for(lambda: goals.count(b"planner sentinel") == 1, 20, what="the planner's sentinel at the robot")
            wait_for(lambda: graph.count(b"mapper sentinel") == 1, 20, what="the mapper's sentinel at a consumer")
            assert goals.count(rogue_goal) == 0, "a camera's goal reached the robot"
            assert frames.count(b"forged frame") == 0, "a camera put another camera's frame"
            assert graph.count(b"forged delta") == 0 and graph.count(b"consumer delta") == 0

            # A stolen password with another login's certificate: the session opens (both are valid)
            # but matches no ACL subject, so it can do nothing.
            stolen = {"transport/auth/usrpwd/user": "planner",
                      "transport/auth/usrpwd/password": (secure_dir / "planner" / "password").read_text().strip()}
            with site.session("cam_kitchen", **stolen) as thief:
                for _ in range(N):
                    thief.put(k.robot_goal("robot0"), b"stolen goal")
                list(thief.get(k.graph_snapshot, timeout=3))
            goal_pub.put(b"planner sentinel 2")
            wait_for(lambda: goals.count(b"planner sentinel 2") == 1, 20, what="the second planner sentinel")
            assert goals.count(b"stolen goal") == 0, "a password without its certificate gave the planner's rights"
        for s in subs:
            s.undeclare()

    # Not logged in at all: no password, no client certificate, wrong password, plain TCP, foreign CA.
    _refused(site, "no password", **{"transport/auth/usrpwd/user": None, "transport/auth/usrpwd/password": None})
    _refused(site, "no client certificate", **{"transport/link/tls/connect_certificate": None,
                                               "transport/link/tls/connect_private_key": None})
    _refused(site, "wrong password", **{"transport/auth/usrpwd/password": "guess"})
    foreign = tmp_path / "foreign"  # a certificate for the right name from another CA
    (foreign / "cam_kitchen").mkdir(parents=True)
    make_ca(foreign, "other-ca", 1)
    make_cert(foreign, foreign / "cam_kitchen", "cam_kitchen", ["cam_kitchen"], 1)
    _refused(site, "certificate of another CA", **{
        "transport/link/tls/connect_certificate": str(foreign / "cam_kitchen" / "cert.pem"),
        "transport/link/tls/connect_private_key": str(foreign / "cam_kitchen" / "key.pem")})
    with pytest.raises(ZenohUnavailable):
        open_session(ZenohSettings(mode="client", connect=[endpoint(port)], overrides={
            "connect/timeout_ms": 3000, "connect/exit_on_failure": True})).close()
    t_total = time.monotonic() - t0
    print(f"\nsecure stack: healthy after {t_healthy:.1f}s, frames+delta+goal flowing after {t_flow:.1f}s, "
          f"all denials checked after {t_total:.1f}s")
    os.kill(up.popen.pid, signal.SIGINT)
    assert up.wait(60) == 0, up.output[-3000:]


def test_stack_secure_flags_per_process(tmp_path: Path) -> None:
    """Every process gets its own Zenoh config file; the router gets the generated router config."""
    from deploy.up import _secure_site

    text = _launch_text(free_port())
    (tmp_path / "l.toml").write_text(text)
    launch = load_launch(tmp_path / "l.toml")
    site = _secure_site(launch, tmp_path, None, False, tmp_path / "s")
    assert site is not None
    stack = Stack(launch, tmp_path, secure=site)
    try:
        for spec in launch.process:
            argv = stack.argv_for(spec)
            if spec.command == "router":
                assert argv[-2:] == ["--config", str(site.router_file)]
            else:
                assert argv[-2:] == ["--zenoh-config", str(site.client_file(spec.name))]
    finally:
        stack.stop()


def _tls_router_alone(tmp_path: Path, procs: list[Proc]) -> Site:
    """The shipped launch file's generated security material and its router alone, listening over TLS."""
    from deploy.secure import prepare

    port = free_port()
    launch = LaunchFile.model_validate_json(json.dumps(_toml(_launch_text(port))))
    site = prepare(launch, SHIPPED.parent, launch.security or SecuritySpec(), ["router"], tmp_path / "s")
    procs.append(Proc(["router", "--config", str(site.router_file), "--listen", launch.endpoint], cwd=tmp_path))
    wait_for(lambda: _port_open(port), 20, what="the TLS router")
    return Site(site.dir, launch.endpoint, Keys("home"))


def test_generated_router_over_tls_lets_a_camera_do_only_its_part(tmp_path: Path, procs: list[Proc]) -> None:
    """The fast tier's check of the generated material: a router alone, the camera's login over TLS."""
    s, k = _tls_router_alone(tmp_path, procs), Keys("home")
    frames, goals = Inbox(), Inbox()
    with s.session("mapper") as mapper, s.session("robot0") as robot, s.session("cam_kitchen") as cam:
        subs = [mapper.declare_subscriber(k.all_frames, frames),
                robot.declare_subscriber(k.robot_goal("robot0"), goals)]
        pub = cam.declare_publisher(k.cam_frame("cam_kitchen"))
        _told_of_subscriber(pub, "camera")
        for _ in range(N):
            cam.put(k.robot_goal("robot0"), b"rogue goal")
            cam.put(k.cam_frame("cam_hall"), b"forged frame")
            pub.put(b"frame")
        wait_for(lambda: frames.count(b"frame") == N, 10, what=f"{N} frames over TLS")
        with s.session("planner") as planner:  # a sentinel on the robot's link, after the rogue goals
            goal_pub = planner.declare_publisher(k.robot_goal("robot0"))
            _told_of_subscriber(goal_pub, "planner")
            goal_pub.put(b"sentinel")
            wait_for(lambda: goals.count(b"sentinel") == 1, 10, what="the planner's goal")
        assert frames.count(b"forged frame") == 0 and goals.count(b"rogue goal") == 0
        for sub in subs:
            sub.undeclare()


def test_goal_answers_reach_argus_goal_over_tls(tmp_path: Path, procs: list[Proc]) -> None:
    """``argus goal`` on a secure site (the planner's login) gets the robot's answer; a camera cannot forge one
    (issue 37 item 6: the ACL had no rule for robot/<id>/goal/status, so every answer was dropped)."""
    from deploy.goal import make_goal, send_goal
    from protocol.messages import GoalStatus

    s, k = _tls_router_alone(tmp_path, procs), Keys("home")
    with s.session("robot0") as robot, s.session("cam_kitchen") as cam, s.session("planner") as planner:
        answers = robot.declare_publisher(k.robot_goal_status("robot0"))
        forged = cam.declare_publisher(k.robot_goal_status("robot0"))

        def answer(sample: zenoh.Sample) -> None:  # the robot agent's answer, as robot_agent.control gives it
            goal = decode(sample.payload.to_bytes(), NbvGoal)
            forged.put(encode(GoalStatus(goal_id=goal.goal_id, robot_id="robot0", accepted=False,
                                         reason="forged by a camera", stamp_ns=1, received=1)))
            answers.put(encode(GoalStatus(goal_id=goal.goal_id, robot_id="robot0", accepted=True, stamp_ns=2,
                                          received=1)))

        sub = robot.declare_subscriber(k.robot_goal("robot0"), answer)
        goal_pub = planner.declare_publisher(k.robot_goal("robot0"))
        _told_of_subscriber(goal_pub, "planner")
        goal_pub.undeclare()
        status = send_goal(planner, k, make_goal("robot0", 1.0, 2.0, 0.0), timeout_s=10.0)
        sub.undeclare()
    assert status is not None, "no answer from the robot over TLS"
    assert status.accepted and status.reason != "forged by a camera"


def _port_open(port: int) -> bool:
    import socket

    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0
