"""Fault injection across the running system: bad input never crashes a process and never loses data.

A router and the long-running processes (mapper with ORACLE geometry and 2D perception on tiny ray-cast
frames, planner, one robot agent with the light kinematic body, one edge camera with the test pattern)
run as real CLI processes on loopback. The test then publishes hostile payloads on every key each
process subscribes to or queries, and checks that every process is still alive, that its Status
counters counted the bad input (exactly, where the count is deterministic), and that it still does
its job afterwards with the data it had before (the mapper's graph is unchanged and grows on the next
valid frame, the planner still plans on the live graph, the robot still drives to a valid goal, the
camera still streams).

The robot agent runs on its own site so the planner does not drive it (the test plays a robot towards
the planner instead, which keeps every count deterministic).

Bugs this module found are pinned by the tests at the end (they were strict xfails until fixed).
"""

from __future__ import annotations

import math
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from mapper.geometry.contract import View
from planner import synthetic as S
from protocol.codec import DecodeError, decode, encode
from protocol.jpeg import JpegError, decode_jpeg, encode_jpeg
from protocol.keys import Keys
from protocol.messages import (
    FrameHeader,
    GraphDelta,
    GraphSnapshot,
    Message,
    NbvGoal,
    OracleFrame,
    PointMap,
    RobotState,
    Status,
    ViewpointSet,
)
from protocol.oracle import decode_u16_png, depth_to_png, encode_u16_png, ids_to_png
from protocol.query import GraphQuery
from protocol.session import ZenohSettings, open_session
from protocol.transport import Frame, decode_frame_sample
from tests.support.boxes import EYES, INTR, LABELS, view
from tests.support.procs import Proc, endpoint, free_port, wait_for, wait_port

SITE = "robust"
ROBOT_SITE = "robust_bot"  # the real robot agent: not driven by the planner
CAM = "cam_r"
BOT = "bot1"  # the real robot agent
FAKE = "fake_bot"  # a robot the test plays towards the planner
SRC = "robot1"  # the test's own valid frame source (ray-cast boxes with ORACLE samples)
KEYS = Keys(SITE)
BOT_KEYS = Keys(ROBOT_SITE)
SPOOF_STAMP_NS = 1  # frames the test forges on the camera's key carry this capture time
MAPPER = ("mapper", "mapper")
PLANNER = ("planner", "planner")
ROBOT = ("robot-agent", BOT)
CAMERA = ("edge-camera", CAM)


# --- hostile payloads --------------------------------------------------------------------------------
def ndarray_ext(dtype: str, shape: list[int], raw: bytes) -> msgpack.ExtType:
    """An array as the codec ships it (ext type 1), with whatever header the test wants to lie in."""
    return msgpack.ExtType(1, msgpack.packb([dtype, shape, raw], use_bin_type=True))


def _pack_numpy(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        return ndarray_ext(a.dtype.str, list(a.shape), a.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot pack {type(obj).__name__}")


def envelope(kind: str, body: Any, major: int = 1, minor: int = 0, magic: str = "ARG1") -> bytes:
    """A hand-made envelope (the codec's layout) around any body, lies included."""
    return msgpack.packb([magic, kind, major, minor, body], use_bin_type=True, default=_pack_numpy)


def hostile_envelopes(valid: Message, n_random: int = 6, seed: int = 0) -> list[bytes]:
    """About 20 payloads that must never decode as ``type(valid)``: random, empty, truncated, lying headers."""
    good = encode(valid)
    kind = type(valid).KIND
    body = valid.model_dump(mode="python")
    rng = np.random.default_rng(seed)
    other = Status(role="x", node_id="y", stamp_ns=0)
    out = [
        b"",
        b"\x00",
        b"\xc1",  # a byte msgpack never uses
        good[: len(good) // 2],  # truncated envelope
        good[:-1],
        good[1:],
        envelope(kind, body, major=99),  # a future major version
        envelope(kind, body, magic="ARG0"),  # wrong magic
        envelope(kind, {"not_a_field": 1}),  # schema violation
        envelope(kind, [1, 2, 3]),  # body is not a map
        envelope("no_such_kind", body),
        encode(other) if kind != other.KIND else envelope("status", []),  # another message kind
        msgpack.packb(["ARG1", kind, 1]),  # short envelope
        envelope(kind, {**body, "stamp_ns": ndarray_ext("<f8", [2**40, 2**20], b"")}),  # oversized array header
        envelope(kind, {**body, "stamp_ns": ndarray_ext("|O", [1], b"\x00" * 8)}),  # object dtype
        envelope(kind, {**body, "stamp_ns": ndarray_ext("<f4", [4, 3], b"\x00" * 5)}),  # short array bytes
        envelope(kind, {**body, "stamp_ns": msgpack.ExtType(42, b"??")}),  # unknown ext type
        b"\x91" * 5000 + b"\xc0",  # 5000 nested arrays
        b"\xdb\xff\xff\xff\xff" + b"x" * 16,  # a 4 GiB string header with 16 bytes behind it
    ]
    out += [rng.bytes(int(rng.integers(1, 3000))) for _ in range(n_random)]
    for p in out:  # the test's own premise: each one really is undecodable
        with pytest.raises(DecodeError):
            decode(p, type(valid))
    return out


def jpeg_claiming(height: int, width: int) -> bytes:
    """A ~600-byte 8x8 JPEG whose frame header (SOF0) claims ``height`` x ``width`` pixels."""
    j = bytearray(encode_jpeg(np.zeros((8, 8, 3), np.uint8)))
    i = j.find(b"\xff\xc0")
    j[i + 5 : i + 9] = struct.pack(">HH", height, width)
    return bytes(j)


def png_claiming(height: int, width: int) -> bytes:
    """A tiny 16-bit PNG whose IHDR claims ``height`` x ``width`` pixels (CRC fixed up)."""
    p = bytearray(encode_u16_png(np.zeros((4, 4), np.uint16)))
    i = p.find(b"IHDR")
    p[i + 4 : i + 12] = struct.pack(">II", width, height)
    p[i + 17 : i + 21] = struct.pack(">I", zlib.crc32(bytes(p[i : i + 17])) & 0xFFFFFFFF)
    return bytes(p)


BAD_QUERIES = [
    "bogus=1", "label", "near=1,2", "near=a,b,c", "near=nan,0,0", "near=1e999,0,0", "near=1,2,3,4", "near=",
    "radius=nan", "radius=-1", "radius=0", "radius=abc", "since_version=-1", "since_version=1.5",
    "since_version=", "=1", "label=a;label", "x" * 4000, "id=a;bogus=2", "radius=1;near=1,2,x",
]


# --- the test's own Zenoh peer -----------------------------------------------------------------------
@dataclass
class Peer:
    """Collects Status (both sites), graph deltas, maps, robot states, goals and camera frames; sends anything."""

    router: str
    lock: threading.Lock = field(default_factory=threading.Lock)
    status: dict[tuple[str, str], Status] = field(default_factory=dict)
    deltas: list[GraphDelta] = field(default_factory=list)
    maps: list[bytes] = field(default_factory=list)
    bot_states: list[RobotState] = field(default_factory=list)
    goals: dict[str, list[NbvGoal]] = field(default_factory=dict)
    cam_frames: list[Frame] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.session = open_session(ZenohSettings(mode="client", connect=[self.router]))
        s = self.session
        self.subs = [
            s.declare_subscriber(KEYS.all_status, self._on_status),
            s.declare_subscriber(BOT_KEYS.all_status, self._on_status),
            s.declare_subscriber(KEYS.graph_delta, self._on_delta),
            s.declare_subscriber(KEYS.map_points, self._on_map),
            s.declare_subscriber(BOT_KEYS.robot_state(BOT), self._on_bot_state),
            s.declare_subscriber(f"{KEYS.root}/robot/*/goal", self._on_goal),
            s.declare_subscriber(KEYS.cam_frame(CAM), self._on_cam_frame),
        ]

    # Callbacks ignore what the test itself sends on the same keys (hostile payloads).
    def _on_status(self, sample: Any) -> None:
        try:
            st = decode(sample.payload.to_bytes(), Status)
        except DecodeError:
            return
        with self.lock:
            self.status[(st.role, st.node_id)] = st

    def _on_delta(self, sample: Any) -> None:
        try:
            d = decode(sample.payload.to_bytes(), GraphDelta)
        except DecodeError:
            return
        with self.lock:
            self.deltas.append(d)

    def _on_map(self, sample: Any) -> None:
        data = sample.payload.to_bytes()
        try:
            decode(data, PointMap)
        except DecodeError:
            return
        with self.lock:
            self.maps.append(data)
            del self.maps[:-2]

    def _on_bot_state(self, sample: Any) -> None:
        st = decode(sample.payload.to_bytes(), RobotState)
        with self.lock:
            self.bot_states.append(st)

    def _on_goal(self, sample: Any) -> None:
        try:
            g = decode(sample.payload.to_bytes(), NbvGoal)
        except DecodeError:
            return
        with self.lock:
            self.goals.setdefault(g.robot_id, []).append(g)

    def _on_cam_frame(self, sample: Any) -> None:
        try:
            f = decode_frame_sample(sample)
        except DecodeError:
            return
        if f.header.source_id == CAM and f.header.stamp_ns > SPOOF_STAMP_NS:
            with self.lock:
                self.cam_frames.append(f)
                del self.cam_frames[:-4]

    # --- reading -------------------------------------------------------------------------------
    def counters(self, who: tuple[str, str]) -> dict[str, float]:
        with self.lock:
            st = self.status.get(who)
            return dict(st.counters) if st is not None else {}

    def counter(self, who: tuple[str, str], name: str) -> float:
        return self.counters(who).get(name, 0.0)

    def wait_counts(self, who: tuple[str, str], base: dict[str, float], expected: dict[str, float],
                    timeout: float = 20.0, proc: Proc | None = None) -> dict[str, float]:
        """Wait until every counter grew by at least ``expected`` over ``base``; returns the growth."""

        def grown() -> dict[str, float]:
            now = self.counters(who)
            return {k: now.get(k, 0.0) - base.get(k, 0.0) for k in expected}

        def done() -> bool:
            if proc is not None and not proc.alive():
                raise AssertionError(f"{who} died (exit {proc.popen.returncode}):\n{proc.output[-3000:]}")
            return all(grown()[k] >= v for k, v in expected.items())

        try:
            wait_for(done, timeout=timeout, what=f"{who} counters {expected}")
        except TimeoutError as e:
            tail = "" if proc is None else proc.output[-3000:]
            with self.lock:
                st = self.status.get(who)
            age = "never" if st is None else f"{(time.time_ns() - st.stamp_ns) / 1e9:.1f} s ago"
            raise AssertionError(f"{e}; they grew {grown()}; last Status {age}: {self.counters(who)}\n{tail}") \
                from None
        return grown()

    def get(self, key: str, params: str = "", timeout: float = 5.0) -> list[Any]:
        import zenoh

        sel = zenoh.Selector(key, params) if params else key
        return list(self.session.get(sel, timeout=timeout))

    def snapshot(self) -> GraphSnapshot | None:
        oks = [r.ok for r in self.get(KEYS.graph_snapshot) if r.ok is not None]
        return decode(oks[0].payload.to_bytes(), GraphSnapshot) if oks else None

    # --- writing -------------------------------------------------------------------------------
    def put(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """Put with BLOCK congestion control, so the receiver's counts are exact (nothing dropped on the way)."""
        import zenoh

        self.session.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)

    def send_view(self, eye: list[float], seq: int, source: str = SRC, header_pose: np.ndarray | None = None) -> None:
        """A valid frame of the ray-cast scene with its ORACLE sample (sent first); ``header_pose`` replaces
        the header's (true) pose."""
        v = self.send_oracle(source, seq, eye)
        T = v.T_world_cam if header_pose is None else header_pose
        self.put(KEYS.robot_frame(source), encode_jpeg(v.image), encode(header(source, seq, T)))

    def send_oracle(self, source: str, seq: int, eye: list[float] | None = None) -> View:
        """The ORACLE sample of the ray-cast view from ``eye`` (default EYES[0]) as ``source``'s frame ``seq``; an
        oracle mapper decodes a frame only once its ORACLE sample is there."""
        v = view(eye if eye is not None else EYES[0], seq, source)
        assert v.oracle is not None and v.oracle.instance_id is not None
        self.put(KEYS.oracle("robot", source), encode(OracleFrame(
            source_id=source, seq=seq, stamp_ns=v.stamp_ns, T_world_cam_true=v.oracle.T_world_cam_true,
            ids_png=ids_to_png(v.oracle.instance_id), depth_png=depth_to_png(v.oracle.depth_m),
            labels={str(k): lab for k, lab in LABELS.items()},
        )))
        return v

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def header(source: str, seq: int, T_world_cam: np.ndarray | None = None, **update: Any) -> FrameHeader:
    h = FrameHeader(source_id=source, source_kind="robot", seq=seq, stamp_ns=seq * 1000 + 1, width=INTR.width,
                    height=INTR.height, intrinsics=INTR, T_world_cam=T_world_cam)
    return h.model_copy(update=update) if update else h


# --- the running system ------------------------------------------------------------------------------
def robot_config(path: Path, router: str) -> Path:
    path.write_text(f"""id = "{BOT}"
site = "{ROBOT_SITE}"
state_period_s = 0.5
viewpoints_period_s = 5.0
status_period_s = 0.2
[body]
type = "kinematic"
bounds_m = [0.0, 0.0, 6.0, 4.0]
obstacles = [[2.5, 0.0, 3.5, 2.5]]
start = [1.0, 1.0, 0.0]
speed_mps = 1.0
turn_rate_dps = 180.0
width = 64
height = 48
[frames]
moving_rate_hz = 2.0
[motion]
tick_hz = 20.0
time_scale = 4.0
[zenoh]
mode = "client"
connect = ["{router}"]
""")
    return path


def mapper_args(router: str, *extra: str) -> list[str]:
    return ["mapper", "--connect", router, "--site", SITE, "--geometry", "oracle", "--segmenter", "sim",
            "--embedder", "sim", "--set", "publish.snapshot_period_s=0", "--set", "publish.point_map_period_s=0",
            "--set", "status_period_s=0.2", "--set", "torch_threads=1", *extra]


@dataclass
class Stack:
    router: Proc
    procs: dict[tuple[str, str], Proc]
    peer: Peer

    def assert_all_alive(self) -> None:
        for who, p in {("router", "router"): self.router, **self.procs}.items():
            assert p.alive(), f"{who} died (exit {p.popen.returncode}):\n{p.output[-3000:]}"


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stack]:
    port = free_port()
    router = Proc(["router", "--listen", endpoint(port)])
    started: list[Proc] = []
    peer: Peer | None = None
    try:
        wait_port(port)
        ep = endpoint(port)
        procs = {
            MAPPER: Proc(mapper_args(ep)),
            PLANNER: Proc(["planner", "--connect", ep, "--site", SITE, "--set", "status_period_s=0.2",
                           "--set", "resend_s=600"]),
            ROBOT: Proc(["robot-agent", "--config", str(robot_config(tmp_path_factory.mktemp("bot") / "r.toml",
                                                                     ep))]),
            CAMERA: Proc(["edge-camera", "--source", "pattern", "--id", CAM, "--site", SITE, "--connect", ep,
                          "--rate", "4", "--set", "source.width=64", "--set", "source.height=48",
                          "--set", "status_period_s=0.3"]),
        }
        started.extend(procs.values())
        peer = Peer(ep)
        st = Stack(router, procs, peer)

        def up() -> bool:
            st.assert_all_alive()
            return all(peer.counters(who) for who in procs) and peer.snapshot() is not None

        wait_for(up, timeout=60, what="every process reporting Status and the mapper answering")
        yield st
    finally:
        if peer is not None:
            peer.close()
        for p in reversed(started):
            p.stop()
        router.stop()


# --- mapper ------------------------------------------------------------------------------------------
def test_mapper_counts_hostile_frames_oracles_and_queries_and_keeps_its_graph(stack: Stack) -> None:
    peer = stack.peer
    # A graph to protect: two valid keyframes of the ray-cast scene.
    n0 = len(peer.deltas)
    v0 = peer.snapshot().version
    for i, eye in enumerate(EYES[:2]):
        peer.send_view(eye, 1000 + v0 * 10 + i)
        wait_for(lambda i=i: len(peer.deltas) >= n0 + i + 1, timeout=30,
                 what=f"delta {i + 1}\n{stack.procs[MAPPER].output[-2000:]}")
    before = peer.snapshot()
    assert before is not None and before.version == v0 + 2 and len(before.nodes) >= 2
    base = peer.counters(MAPPER)

    # Frames whose header is missing, garbage, truncated, of another kind, lying or naming another source.
    tiny = encode_jpeg(np.zeros((INTR.height, INTR.width, 3), np.uint8))
    good = encode(header(SRC, 5))
    bad_header: list[tuple[str, bytes, bytes | None]] = [
        (KEYS.robot_frame(SRC), tiny, None),
        (KEYS.cam_frame(CAM), tiny, None),
        (KEYS.robot_frame(SRC), tiny, b"\x93garbage"),
        (KEYS.robot_frame(SRC), tiny, good[: len(good) // 2]),
        (KEYS.robot_frame(SRC), tiny, good[:-1]),
        (KEYS.robot_frame(SRC), tiny, b""),
        (KEYS.robot_frame(SRC), tiny, encode(Status(role="x", node_id="y", stamp_ns=0))),
        (KEYS.robot_frame(SRC), tiny, envelope("frame_header", {**header(SRC, 6).model_dump(), "width": 10**9})),
        (KEYS.robot_frame(SRC), tiny, envelope("frame_header", {**header(SRC, 6).model_dump(), "seq": -1})),
        (KEYS.robot_frame(SRC), tiny, envelope("frame_header", {
            **header(SRC, 6).model_dump(), "T_world_cam": [[math.nan] * 4] * 4})),
        (KEYS.robot_frame(SRC), tiny, envelope("frame_header", {
            **header(SRC, 6).model_dump(), "T_world_cam": ndarray_ext("<f8", [10**6, 10**6], b"")})),
        (KEYS.robot_frame(SRC), tiny, encode(header("someone_else", 7))),  # header names another source
        (KEYS.cam_frame(CAM), tiny, encode(header(CAM, 8))),  # a robot header on a fixed camera's key
        (KEYS.robot_frame(SRC), tiny, envelope("frame_header", header(SRC, 9).model_dump(), major=2)),
    ]
    bad_header += [(KEYS.robot_frame(SRC), tiny, p) for p in hostile_envelopes(header(SRC, 10), n_random=2)[:8]]
    for key, payload, att in bad_header:
        peer.put(key, payload, att)

    # Well-formed headers with bad images, one per source so none is evicted unseen: each must be refused. Most
    # are refused on arrival, unread; the two cut short pass those checks and fail when decoded, which happens
    # once their ORACLE sample is there (sent first). The ORACLE path: valid frames whose ORACLE PNGs are corrupt
    # or of the wrong size.
    v = view(EYES[2], 1)
    bad_images = [
        b"", b"\xff\xd8", b"\xff\xd8not a jpeg\xff\xd9", tiny[: len(tiny) // 2], tiny[:-2], b"\x89PNG\r\n\x1a\n",
        encode_jpeg(np.zeros((8, 8, 3), np.uint8)),  # header says 96x72
    ]
    for i, img in enumerate(bad_images):
        if img in (tiny[: len(tiny) // 2], tiny[:-2]):
            peer.send_oracle(f"evil_j{i}", 1)
        peer.put(KEYS.robot_frame(f"evil_j{i}"), img, encode(header(f"evil_j{i}", 1)))
    huge = header("evil_j_huge", 1, width=16384, height=16384, intrinsics=None)  # header claims a huge image
    peer.put(KEYS.robot_frame("evil_j_huge"), tiny, encode(huge))
    bad_oracles = [  # undecodable PNGs: refused before the view is built (decode_errors)
        {"ids_png": b"garbage"},
        {"depth_png": b"\x89PNG\r\n\x1a\n"},
        {"depth_png": png_claiming(20000, 20000)},  # IHDR lies; libpng refuses it before allocating
        {"ids_png": None, "depth_png": b""},
    ]
    misfit_oracles = [  # decodable PNGs of another size than their frame: refused from the header (decode_errors)
        {"depth_png": depth_to_png(np.ones((INTR.height + 1, INTR.width), np.float32))},
        {"ids_png": ids_to_png(np.ones((INTR.height // 2, INTR.width // 2), np.int32))},
    ]
    for i, upd in enumerate(bad_oracles + misfit_oracles):
        src = f"evil_o{i}"
        o = OracleFrame(source_id=src, seq=1, stamp_ns=1, T_world_cam_true=v.oracle.T_world_cam_true,
                        ids_png=ids_to_png(v.oracle.instance_id), depth_png=depth_to_png(v.oracle.depth_m))
        peer.put(KEYS.oracle("robot", src), encode(o.model_copy(update=upd)))
        peer.put(KEYS.robot_frame(src), encode_jpeg(v.image), encode(header(src, 1, v.T_world_cam)))

    # Undecodable ORACLE samples.
    bad_oracle_msgs = hostile_envelopes(OracleFrame(source_id=SRC, seq=1, stamp_ns=1, T_world_cam_true=np.eye(4)))
    for p in bad_oracle_msgs:
        peer.put(KEYS.oracle("robot", SRC), p)

    # Malformed graph queries: each gets an error reply, none a crash.
    for params in BAD_QUERIES:
        with pytest.raises(ValueError):
            GraphQuery.from_parameters(params)
        replies = peer.get(KEYS.graph_nodes, params)
        assert replies and all(r.err is not None for r in replies), params

    expected = {
        "header_errors": len(bad_header), "decode_errors": len(bad_images) + 1 + len(bad_oracles) + len(misfit_oracles),
        "keyframe_errors": 0, "oracle_errors": len(bad_oracle_msgs),
        "query_errors": len(BAD_QUERIES),
    }
    grew = peer.wait_counts(MAPPER, base, expected, proc=stack.procs[MAPPER])
    # Exactly those: nothing else was miscounted as bad, and the test's inputs were all delivered.
    assert grew == expected
    stack.assert_all_alive()

    # No data lost, none invented: the graph is exactly what it was.
    assert peer.snapshot() == before
    (table,) = [r.ok for r in peer.get(KEYS.graph_nodes, GraphQuery(label="table").to_parameters())]
    assert decode(table.payload.to_bytes(), GraphSnapshot).nodes == [n for n in before.nodes if n.label == "table"]
    # And it still grows from the next valid frame.
    n1 = len(peer.deltas)
    peer.send_view(EYES[2], 2000 + v0)
    wait_for(lambda: len(peer.deltas) > n1, timeout=30, what=f"a delta after the attack\n"
             f"{stack.procs[MAPPER].output[-2000:]}")
    assert peer.deltas[n1].version == before.version + 1
    after = peer.snapshot()
    assert after is not None and after.version == before.version + 1
    assert {n.node_id for n in before.nodes} <= {n.node_id for n in after.nodes}
    stack.assert_all_alive()


# --- planner -----------------------------------------------------------------------------------------
def fake_viewpoints(robot_id: str = FAKE) -> ViewpointSet:
    return S.grid_viewpoints(robot_id, (0.5, -2.5), (3.5, 1.5), spacing_m=1.0, n_headings=4)


def test_planner_counts_hostile_graph_map_and_robot_messages_and_still_plans(stack: Stack) -> None:
    peer = stack.peer
    base = peer.counters(PLANNER)
    snap = GraphSnapshot(version=1, stamp_ns=1, nodes=[S.node("n1", "chair", (1.0, 1.0, 0.4), (0.5, 0.5, 0.8))])
    samples: dict[str, Message] = {
        KEYS.graph_snapshot: snap,
        KEYS.graph_delta: GraphDelta(version=2, stamp_ns=2, upserted=snap.nodes),
        KEYS.map_points: PointMap(version=1, stamp_ns=1, voxel_m=0.05, points=np.zeros((4, 3), np.float32)),
        KEYS.robot_state(FAKE): S.robot_state(FAKE, 2.0, 0.5, 0.0, "arrived"),
        KEYS.robot_viewpoints(FAKE): fake_viewpoints(),
    }
    map_body = samples[KEYS.map_points].model_dump(mode="python")
    map_lies = [  # array headers that lie: a billion points, a shape the bytes do not fill, a bad dtype
        envelope("point_map", {**map_body, "points": ndarray_ext("<f4", [10**9, 3], b"")}),
        envelope("point_map", {**map_body, "points": ndarray_ext("<f4", [1000, 3], b"\x00" * 12)}),
        envelope("point_map", {**map_body, "points": ndarray_ext("<c16", [1, 3], b"\x00" * 48)}),
        envelope("point_map", {**map_body, "points": ndarray_ext("<f4", [-1, 3], b"")}),
    ]
    for p in map_lies:
        with pytest.raises(DecodeError):
            decode(p, PointMap)
        peer.put(KEYS.map_points, p)
    n_garbage = len(map_lies)
    for seed, (key, msg) in enumerate(samples.items()):
        for p in hostile_envelopes(msg, seed=seed):
            peer.put(key, p)
            n_garbage += 1
    # Decodable but refused: a state naming another robot than its key, states on keys that are no robot id.
    peer.put(KEYS.robot_state(FAKE), encode(S.robot_state("not_" + FAKE, 2.0, 0.5, 0.0, "arrived")))
    for bad_id in ("bad+id", "bad@id", "x" * 200):
        peer.put(f"{KEYS.root}/robot/{bad_id}/state", encode(S.robot_state(FAKE, 2.0, 0.5, 0.0, "arrived")))
    # A delta that does not follow: counted as a gap and healed from the mapper's snapshot (no data lost).
    peer.put(KEYS.graph_delta, encode(GraphDelta(version=10**9, stamp_ns=1, upserted=snap.nodes)))

    grew = peer.wait_counts(PLANNER, base, {"decode_errors": n_garbage + 1, "bad_keys": 3, "delta_gaps": 1})
    assert grew == {"decode_errors": n_garbage + 1, "bad_keys": 3, "delta_gaps": 1}
    stack.assert_all_alive()

    # Still planning on the mapper's live graph: it re-queried the snapshot after the gap and follows it.
    mapper_graph = peer.snapshot()
    assert mapper_graph is not None
    peer.wait_counts(PLANNER, base, {"snapshot_queries": 1})
    wait_for(lambda: peer.counter(PLANNER, "graph_nodes") == len(mapper_graph.nodes), timeout=10,
             what=f"planner following the mapper's graph ({len(mapper_graph.nodes)} nodes)")
    assert peer.counters(PLANNER).get("plan_errors", 0) == base.get("plan_errors", 0)
    peer.put(KEYS.robot_viewpoints(FAKE), encode(fake_viewpoints()))
    peer.put(KEYS.robot_state(FAKE), encode(S.robot_state(FAKE, 2.0, 0.5, 0.0, "arrived")))
    wait_for(lambda: peer.goals.get(FAKE), timeout=20,
             what=f"a goal for {FAKE}\n{stack.procs[PLANNER].output[-2000:]}")
    goal = peer.goals[FAKE][0]
    assert goal.robot_id == FAKE and goal.vp_id is not None
    assert goal.graph_version == peer.snapshot().version
    assert any(v.vp_id == goal.vp_id and (v.x, v.y) == (goal.x, goal.y) for v in fake_viewpoints().viewpoints)
    stack.assert_all_alive()


# --- robot agent -------------------------------------------------------------------------------------
def bot_goal(goal_id: str, x: float, y: float, yaw: float = 0.0, robot_id: str = BOT) -> NbvGoal:
    return NbvGoal(goal_id=goal_id, robot_id=robot_id, stamp_ns=time.time_ns(), x=x, y=y, yaw_rad=yaw)


def test_robot_agent_counts_hostile_goals_and_still_drives(stack: Stack) -> None:
    peer = stack.peer
    base = peer.counters(ROBOT)
    key = BOT_KEYS.robot_goal(BOT)
    garbage = hostile_envelopes(bot_goal("g", 1.5, 3.0))
    refused = [
        bot_goal("nan_x", math.nan, 1.0),
        bot_goal("inf_y", 1.0, math.inf),
        bot_goal("nan_yaw", 1.5, 3.0, math.nan),
        bot_goal("other_robot", 1.5, 3.0, robot_id="someone_else"),
        bot_goal("far", 1e9, -1e9),
        bot_goal("off_map", 100.0, 100.0),
        bot_goal("in_obstacle", 3.0, 1.0),
        bot_goal("huge_yaw", 1e308, 1e308, 1e308),
    ]
    for p in garbage:
        peer.put(key, p)
    for g in refused:
        peer.put(key, encode(g))
    # Viewpoint queries with junk selector parameters are still answered.
    for params in ("x=1", "bogus", ";;;", "radius=nan", "y" * 2000):
        oks = [r.ok for r in peer.get(BOT_KEYS.robot_viewpoints(BOT), params) if r.ok is not None]
        assert len(oks) == 1 and decode(oks[0].payload.to_bytes(), ViewpointSet).robot_id == BOT

    n = len(garbage) + len(refused)
    grew = peer.wait_counts(ROBOT, base, {"goals_received": n, "goals_garbage": len(garbage),
                                          "viewpoint_queries": 5})
    # Every decodable bad goal was refused, or replaced in the one-slot mailbox by a newer one; none accepted.
    wait_for(lambda: peer.counter(ROBOT, "goals_refused") + peer.counter(ROBOT, "goals_superseded")
             - base.get("goals_refused", 0) - base.get("goals_superseded", 0) >= len(refused), timeout=10,
             what="bad goals refused")
    now = peer.counters(ROBOT)
    assert grew["goals_received"] == n and grew["goals_garbage"] == len(garbage)
    assert (now.get("goals_refused", 0) - base.get("goals_refused", 0)
            + now.get("goals_superseded", 0) - base.get("goals_superseded", 0)) == len(refused)
    assert now.get("goals_accepted", 0) == base.get("goals_accepted", 0)
    assert now.get("tick_errors", 0) == 0
    stack.assert_all_alive()

    # A valid goal is still driven to.
    peer.put(key, encode(bot_goal("valid", 1.5, 3.0, math.pi / 2)))

    def arrived() -> RobotState | None:
        with peer.lock:
            return next((s for s in peer.bot_states if s.goal_id == "valid" and s.status == "arrived"), None)

    wait_for(lambda: arrived() is not None, timeout=20,
             what=f"arrival at the valid goal\n{stack.procs[ROBOT].output[-2000:]}")
    st = arrived()
    assert math.hypot(st.x - 1.5, st.y - 3.0) < 0.1 and st.reason is None
    stack.assert_all_alive()


# --- edge camera -------------------------------------------------------------------------------------
def test_edge_camera_keeps_streaming_while_its_key_is_spoofed(stack: Stack) -> None:
    """The camera subscribes to nothing; others spoofing its key must neither stop it nor reach the graph."""
    peer = stack.peer
    graph = peer.snapshot()
    base = peer.counters(CAMERA)
    mbase = peer.counters(MAPPER)
    spoofs = [(b"\xff\xd8junk\xff\xd9", encode(FrameHeader(source_id=CAM, source_kind="fixed", seq=10**6,
                                                             stamp_ns=SPOOF_STAMP_NS, width=64, height=48)))]
    spoofs += [(b"x" * 100, p) for p in hostile_envelopes(FrameHeader(source_id=CAM, source_kind="fixed", seq=1,
                                                                       stamp_ns=SPOOF_STAMP_NS, width=64, height=48))]
    for payload, att in spoofs:
        peer.put(KEYS.cam_frame(CAM), payload, att)
    expected = {"header_errors": len(spoofs) - 1, "decode_errors": 1}
    assert peer.wait_counts(MAPPER, mbase, expected, proc=stack.procs[MAPPER]) == expected
    with peer.lock:
        last_seq = peer.cam_frames[-1].header.seq if peer.cam_frames else -1
    # The camera carries on: new frames, well-formed, nothing failed on its side.
    peer.wait_counts(CAMERA, base, {"frames_sent": 3}, proc=stack.procs[CAMERA])
    wait_for(lambda: peer.cam_frames and peer.cam_frames[-1].header.seq > last_seq + 1, timeout=10,
             what="new camera frames")
    with peer.lock:
        frame = peer.cam_frames[-1]
    assert frame.header.source_kind == "fixed" and decode_jpeg(frame.jpeg).shape == (48, 64, 3)
    assert peer.counter(CAMERA, "publish_errors") == 0 and peer.counter(CAMERA, "source_errors") == 0
    assert peer.snapshot() == graph  # none of the spoofs reached the graph
    stack.assert_all_alive()


# --- regressions for bugs this module found (image size bombs, source slots, planner map and queries) ---
def vm_mib(pid: int, name: str) -> float:
    """A memory figure of a live process from /proc (VmHWM: peak resident set, VmRSS: now), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key == name:
            return int(value.split()[0]) / 1024
    raise KeyError(name)


@pytest.fixture
def lone_mapper(router: str, procs: list[Proc], request: pytest.FixtureRequest) -> Iterator[tuple[Proc, Peer]]:
    """A mapper of its own (tests that may kill it or fill it up), with a peer; extra args via indirect param."""
    mapper = Proc(mapper_args(router, *getattr(request, "param", ())))
    procs.append(mapper)
    peer = Peer(router)
    try:
        def up() -> bool:
            assert mapper.alive(), mapper.output
            return bool(peer.counters(MAPPER)) and peer.snapshot() is not None

        wait_for(up, timeout=60, what="the mapper answering")
        yield mapper, peer
    finally:
        peer.close()


@pytest.mark.parametrize(
    ("decoder", "data"),
    [(decode_jpeg, jpeg_claiming(40000, 40000)), (decode_u16_png, png_claiming(40000, 40000))],
    ids=["jpeg", "png"],
)
def test_image_decoders_raise_their_own_error_on_a_size_bomb(decoder: Any, data: bytes) -> None:
    assert len(data) < 1024
    with pytest.raises(JpegError):
        decoder(data)


def test_mapper_survives_a_jpeg_claiming_a_huge_size(lone_mapper: tuple[Proc, Peer]) -> None:
    mapper, peer = lone_mapper
    base = peer.counters(MAPPER)
    peer.put(KEYS.robot_frame(SRC), jpeg_claiming(40000, 40000), encode(header(SRC, 1)))
    peer.wait_counts(MAPPER, base, {"decode_errors": 1}, proc=mapper)
    assert mapper.alive()


def test_mapper_refuses_a_jpeg_bigger_than_its_header_without_decoding_it(
    lone_mapper: tuple[Proc, Peer],
) -> None:
    mapper, peer = lone_mapper
    pid = mapper.popen.pid
    peak0 = vm_mib(pid, "VmHWM")
    base = peer.counters(MAPPER)
    peer.put(KEYS.robot_frame(SRC), jpeg_claiming(6000, 6000), encode(header(SRC, 1)))
    peer.wait_counts(MAPPER, base, {"decode_errors": 1}, proc=mapper)
    assert vm_mib(pid, "VmHWM") - peak0 < 64, "a 600-byte frame raised the mapper's peak memory"


def test_mapper_refuses_forty_bombs_that_match_their_headers_unread(lone_mapper: tuple[Proc, Peer]) -> None:
    """Issue 19: 40 ~600-byte JPEGs whose JPEG and frame header both claim 6000x6000 took the mapper to 4.6 GB."""
    mapper, peer = lone_mapper
    pid = mapper.popen.pid
    peak0 = vm_mib(pid, "VmHWM")
    base = peer.counters(MAPPER)
    for i in range(40):
        # over the pixel cap (max_frame_pixels, 8192x8192); under it but far too few bytes for its size
        w = h = 9000 if i % 2 == 0 else 3000
        peer.put(KEYS.robot_frame(f"bomb{i}"), jpeg_claiming(h, w), encode(header(f"bomb{i}", 1, width=w, height=h,
                                                                                  intrinsics=None)))
    expected = {"frames_too_large": 20, "frames_implausible_jpeg": 20, "decode_errors": 40}
    assert peer.wait_counts(MAPPER, base, expected, proc=mapper) == expected
    assert peer.counter(MAPPER, "decoded_pixels_peak") == base.get("decoded_pixels_peak", 0.0) == 0.0
    assert vm_mib(pid, "VmHWM") - peak0 < 64, "small frames raised the mapper's peak memory"


@pytest.mark.parametrize("lone_mapper", [("--set", "max_sources=4")], indirect=True)
def test_mapper_still_ingests_a_new_source_after_made_up_sources(lone_mapper: tuple[Proc, Peer]) -> None:
    mapper, peer = lone_mapper
    base = peer.counters(MAPPER)
    # Well-formed headers, images whose JPEG header is right but whose data is cut short: they pass the checks on
    # arrival, so each takes a slot, and fail only when decoded (once their ORACLE sample is there).
    cut = encode_jpeg(np.zeros((INTR.height, INTR.width, 3), np.uint8))[:-2]
    for i in range(4):
        peer.send_oracle(f"evil{i}", 1)
        peer.put(KEYS.robot_frame(f"evil{i}"), cut, encode(header(f"evil{i}", 1)))
    peer.wait_counts(MAPPER, base, {"decode_errors": 4}, proc=mapper)
    peer.send_view(EYES[0], 1)  # a legitimate new source
    peer.send_oracle("evil0", 2)
    peer.put(KEYS.robot_frame("evil0"), cut, encode(header("evil0", 2)))  # a marker after it
    peer.wait_counts(MAPPER, base, {"decode_errors": 5, "frames_in": 6}, proc=mapper)
    wait_for(lambda: peer.counter(MAPPER, "frames_processed") > base.get("frames_processed", 0)
             or peer.counter(MAPPER, "frames_without_oracle") > base.get("frames_without_oracle", 0), timeout=3,
             what=f"the new source's frame processed or dropped; counters {peer.counters(MAPPER)}")
    assert peer.counter(MAPPER, "frames_processed") == base.get("frames_processed", 0) + 1


def test_mapper_drops_bad_poses_projects_nearly_rigid_ones_and_still_ingests(lone_mapper: tuple[Proc, Peer]) -> None:
    mapper, peer = lone_mapper
    base = peer.counters(MAPPER)
    tiny = encode_jpeg(np.zeros((INTR.height, INTR.width, 3), np.uint8))
    T = view(EYES[0], 1).T_world_cam
    assert T is not None

    def posed(R: np.ndarray | None = None, last_row: list[float] | None = None) -> np.ndarray:
        out = T.copy()
        if R is not None:
            out[:3, :3] = R
        if last_row is not None:
            out[3] = last_row
        return out

    # The codec refuses a NaN or 3x3 pose while decoding the header (header_errors): no FrameHeader exists.
    for src, pose in (("pose_nan", [[math.nan] * 4] * 4), ("pose_3x3", np.eye(3).tolist())):
        body = {**header(src, 1).model_dump(), "T_world_cam": pose}
        peer.put(KEYS.robot_frame(src), tiny, envelope("frame_header", body))
    # Well-formed 4x4 headers whose pose is no rigid transform: the mapper drops them (frames_bad_pose), one
    # warning for the source. The shear comes first, so that is the warning.
    bad_poses = [
        posed(T[:3, :3] @ np.array([[1.0, 0.05, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])),  # shear
        posed(T[:3, :3] @ np.diag([1.0, 1.0, -1.0])),  # reflection
        posed(last_row=[0.0, 0.0, 1e-3, 1.0]),  # not homogeneous
    ]
    for i, Tb in enumerate(bad_poses):
        peer.put(KEYS.robot_frame("pose_bad"), tiny, encode(header("pose_bad", 10 + i, Tb)))
    # A full valid frame whose pose is off orthonormal by ~1e-3: projected onto SO(3) and ingested.
    near = posed(T[:3, :3] * (1 + 5e-4))
    peer.send_view(EYES[0], 1, header_pose=near)
    expected = {"header_errors": 2, "frames_bad_pose": 3, "poses_projected": 1, "frames_processed": 1}
    grew = peer.wait_counts(MAPPER, base, expected, proc=mapper)
    assert grew == expected
    wait_for(lambda: "dropped a frame: pose_bad frame 10 pose: pose rotation is not orthonormal "
                     "(||R^T R - I|| = 0.0708 > 0.01)" in mapper.output,
             timeout=5, what=f"the shear's warning in the mapper's log:\n{mapper.output[-2000:]}")
    assert mapper.output.count("dropped a frame: pose_bad") == 1  # rate-limited per source

    # Still ingesting: the next valid frame is processed and grows the graph.
    n0 = len(peer.deltas)
    version = peer.snapshot().version
    peer.send_view(EYES[1], 2)
    peer.wait_counts(MAPPER, base, {"frames_processed": 2}, proc=mapper)
    wait_for(lambda: len(peer.deltas) > n0, timeout=30, what=f"a delta after the bad poses\n{mapper.output[-2000:]}")
    assert peer.snapshot().version > version
    counts = peer.counters(MAPPER)
    for name in ("decode_errors", "keyframe_errors", "frames_without_oracle"):
        assert counts.get(name, 0.0) == base.get(name, 0.0), name
    assert counts["frames_bad_pose"] - base.get("frames_bad_pose", 0.0) == 3
    assert mapper.alive()


def test_planner_keeps_its_map_when_a_malformed_point_map_arrives(stack: Stack) -> None:
    peer = stack.peer
    robot = FAKE + "_map"
    with peer.lock:
        real = peer.maps[-1] if peer.maps else None
    base = peer.counters(PLANNER)
    try:
        # model_construct skips validation: the bytes a hostile or buggy peer could send.
        bad_map = PointMap.model_construct(version=1, stamp_ns=1, voxel_m=0.05, points=np.zeros((5, 2), np.float32),
                                           counts=None, colors=None)
        peer.put(KEYS.map_points, encode(bad_map))
        peer.wait_counts(PLANNER, base, {"decode_errors": 1}, proc=stack.procs[PLANNER])
        peer.put(KEYS.robot_viewpoints(robot), encode(fake_viewpoints(robot)))
        peer.put(KEYS.robot_state(robot), encode(S.robot_state(robot, 2.0, 0.5, 0.0, "arrived")))
        wait_for(lambda: peer.goals.get(robot) or peer.counter(PLANNER, "plan_errors") > base.get("plan_errors", 0),
                 timeout=20, what="a goal or a planning error")
        stack.assert_all_alive()
        assert peer.counter(PLANNER, "plan_errors") == base.get("plan_errors", 0)
        assert peer.goals.get(robot)
    finally:  # give the planner a valid map again for whatever runs next
        peer.put(KEYS.map_points, real if real is not None else encode(
            PointMap(version=0, stamp_ns=0, voxel_m=0.05, points=np.zeros((0, 3), np.float32))))


def test_planner_counts_viewpoints_naming_another_robot(stack: Stack) -> None:
    peer = stack.peer
    base = peer.counters(PLANNER)
    peer.put(KEYS.robot_viewpoints(FAKE + "_vp"), encode(fake_viewpoints("not_" + FAKE)))
    peer.put(KEYS.robot_state(FAKE + "_vp"), encode(S.robot_state("not_" + FAKE, 2.0, 0.5, 0.0)))  # a marker
    # both are refused (waiting for the first alone raced the second's count on a loaded machine), and nothing else
    peer.wait_counts(PLANNER, base, {"decode_errors": 2}, proc=stack.procs[PLANNER])
    time.sleep(0.5)
    assert peer.counter(PLANNER, "decode_errors") - base.get("decode_errors", 0) == 2


def test_planner_resyncs_although_a_peer_answers_snapshot_queries_with_garbage(stack: Stack) -> None:
    peer = stack.peer

    def garbage_reply(query: Any) -> None:
        time.sleep(0.3)  # answer after the mapper: the reply consolidation keeps the last one
        query.reply(KEYS.graph_snapshot, b"\x93not a snapshot")

    rogue = peer.session.declare_queryable(KEYS.graph_snapshot, garbage_reply)
    try:
        base = peer.counters(PLANNER)
        peer.put(KEYS.graph_delta, encode(GraphDelta(version=10**9, stamp_ns=1)))  # a gap: re-query the snapshot
        peer.wait_counts(PLANNER, base, {"delta_gaps": 1, "snapshot_queries": 1, "decode_errors": 1},
                         proc=stack.procs[PLANNER])
        # The same query brought the mapper's snapshot: adopted without waiting for another re-query (2 s).
        wait_for(lambda: peer.counter(PLANNER, "snapshots_in") > base.get("snapshots_in", 0), timeout=1.5,
                 what="the mapper's snapshot adopted")
    finally:
        rogue.undeclare()
