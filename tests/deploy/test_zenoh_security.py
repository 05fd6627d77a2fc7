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
from protocol.codec import DecodeError, decode, encode
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
                  Principal("mapper", "mapper", "mapper", local_workers=1), Principal("planner", "planner", "planner"),
                  Principal("worker-01", "worker", "worker-01"),
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


def test_keyframe_jobs_through_the_shipped_acl(tmp_path: Path, procs: list[Proc]) -> None:
    """A real ``argus worker`` logged in as worker-01 does a keyframe job for the mapper's login: its token
    reaches the mapper, the job reaches it, it fetches the source keyframes from the mapper's store and its
    result comes back. The mapper's login also carries its local worker (mapper-local0). Denied: another
    worker's jobs and results, the graph, frames."""
    from mapper.config import MapperCoreConfig
    from mapper.geometry.contract import View
    from mapper.work.jobs import make_job
    from protocol.jpeg import decode_jpeg
    from protocol.messages import WorkResult
    from tests.mapper.work.test_work_offload import frames

    ep = _acl_router(tmp_path, procs)
    shutil.copy(ZENOH_DIR / "client-acl-example.json5", tmp_path)
    conf = tmp_path / "worker.json5"
    conf.write_text((tmp_path / "client-acl-example.json5").read_text().replace('"cam-01"', '"worker-01"')
                    .replace('"cam-01-secret"', '"worker-01-secret"'))
    keys = Keys()
    jpegs, poses, intr = frames()
    views = [View(image=decode_jpeg(j), source_id="r1", intrinsics=intr, T_world_cam=T, seq=i, stamp_ns=1000 + i)
             for i, (j, T) in enumerate(zip(jpegs[:3], poses[:3], strict=True))]
    job = make_job(views, 2, jpegs[2], 1, False, MapperCoreConfig())
    results, alive, acks, graph, jobs_seen = _Inbox(), _Inbox(), _Inbox(), _Inbox(), _Inbox()
    fetched: list[str] = []

    def store(query: zenoh.Query) -> None:
        seq = int(str(query.key_expr).rsplit("/", 1)[1])
        fetched.append(str(query.key_expr))
        query.reply(str(query.key_expr), jpegs[seq])

    with (
        open_session(_user(ep, "mapper")) as mapper,
        open_session(_user(ep, "mapper")) as local,  # the mapper's local worker logs in as the mapper
        open_session(_user(ep, "worker-01")) as rogue,  # the same login as the real worker, misbehaving
        open_session(_user(ep, "viewer")) as viewer,
    ):
        decls = [mapper.declare_subscriber(keys.all_work_results, results),
                 mapper.declare_subscriber(keys.all_work_acks, acks),
                 mapper.declare_queryable(keys.all_work_keyframes, store),
                 mapper.liveliness().declare_subscriber(keys.all_alive_of("worker"), alive, history=True),
                 viewer.declare_subscriber(keys.graph_all, graph),
                 rogue.declare_subscriber(keys.work_job("worker-02"), jobs_seen),
                 rogue.declare_subscriber(keys.all_frames, jobs_seen)]
        worker = Proc(["worker", "--id", "worker-01", "--connect", ep, "--set", "torch_threads=1",
                       "--set", f"zenoh.config_file={conf}"])
        procs.append(worker)
        wait_for(lambda: keys.alive("worker", "worker-01") in alive.keys, 60,
                 what=f"the worker's token at the mapper; its output:\n{worker.output}")
        job_pub = mapper.declare_publisher(keys.work_job("worker-01"))
        _told_of_subscriber(job_pub, "mapper -> worker")
        job_pub.put(encode(job))
        wait_for(lambda: len(results.payloads) >= 1, 60, what=f"the worker's result; its output:\n{worker.output}")
        res = decode(results.payloads[0], WorkResult)
        assert res.ok and res.job_id == job.job_id, res.error
        assert acks.keys == [keys.work_ack("worker-01")]
        assert sorted(fetched) == [keys.work_keyframe("r1", 0), keys.work_keyframe("r1", 1)]
        # The local worker's part under the mapper's login: token, its jobs, its results.
        token = local.liveliness().declare_token(keys.alive("worker", "mapper-local0"))
        local_jobs = _Inbox()
        sub = local.declare_subscriber(keys.work_job("mapper-local0"), local_jobs)
        wait_for(lambda: keys.alive("worker", "mapper-local0") in alive.keys, 10, what="the local worker's token")
        _n_of_n(mapper.declare_publisher(keys.work_job("mapper-local0")), local_jobs, b"local job", "mapper -> local")
        _n_of_n(local.declare_publisher(keys.work_result("mapper-local0")), results, b"local result", "local -> mapper")
        # Denied for a worker: another worker's token and results, the graph; it receives no frames or other jobs.
        forged = rogue.liveliness().declare_token(keys.alive("worker", "worker-02"))
        for _ in range(N_PUTS):
            rogue.put(keys.work_result("worker-02"), b"forged result")
            rogue.put(keys.graph_delta, b"worker delta")
            mapper.put(keys.work_job("worker-02"), b"job for worker-02")
        rogue.put(keys.work_result("worker-01"), b"worker sentinel")
        wait_for(lambda: results.count(b"worker sentinel") == 1, 10, what="the worker's sentinel")
        assert results.count(b"forged result") == 0, "a worker put another worker's result"
        assert graph.count(b"worker delta") == 0, "a worker wrote into the graph"
        assert jobs_seen.keys == [], "a worker read another worker's jobs or camera frames"
        assert keys.alive("worker", "worker-02") not in alive.keys, "a worker posed as another worker"
        for d in [*decls, token, sub, forged]:
            d.undeclare()
