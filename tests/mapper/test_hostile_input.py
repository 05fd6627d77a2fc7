"""Physically impossible or oversized input is refused with a counter before it costs memory or reaches the graph.

Pure checks (mapper.intake), the byte-bounded receive ring, and the mapper's frame path in-process: samples
are fed to ``MapperNode._on_frame`` (no Zenoh) and processed by ``_step`` with the oracle core.
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh

from mapper import inbox as mapper_inbox
from mapper.config import GeometryConfig, MapperConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.inbox import DecodeBudget
from mapper.intake import InputLimits, frame_problem, intrinsics_problem, pose_problem, view_problem
from mapper.node import MapperNode
from protocol.codec import encode
from protocol.jpeg import MIN_BYTES_PER_MPIXEL_FLOOR, JpegError, decode_jpeg, encode_jpeg, jpeg_problem
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics, OracleFrame
from protocol.oracle import depth_to_png, ids_to_png
from protocol.ratelog import RateLimitedLog
from protocol.transport import LatestSlots
from tests.support.boxes import EYES, INTR, LABELS, view

LIM = InputLimits()
SITE = "hostile"
KEYS = Keys(SITE)
# The site of the ray-cast test scene: a few metres around the origin.
TIGHT = {"site_min_m": (-10.0, -10.0, -2.0), "site_max_m": (10.0, 10.0, 5.0)}


def jpeg_claiming(width: int, height: int) -> bytes:
    """A ~600-byte 8x8 JPEG whose frame header (SOF0) claims ``width`` x ``height`` pixels (the issue's bomb)."""
    j = bytearray(encode_jpeg(np.zeros((8, 8, 3), np.uint8)))
    i = j.find(b"\xff\xc0")
    j[i + 5 : i + 9] = struct.pack(">HH", height, width)
    return bytes(j)


def header(source: str, seq: int, **update: Any) -> FrameHeader:
    h = FrameHeader(source_id=source, source_kind="robot", seq=seq, stamp_ns=seq * 1000 + 1, width=INTR.width,
                    height=INTR.height, intrinsics=INTR)
    return h.model_copy(update=update) if update else h


# --- JPEG checks before decoding ---------------------------------------------------------------------
def test_the_bomb_is_refused_from_its_header_and_byte_count() -> None:
    bomb = jpeg_claiming(6000, 6000)
    assert len(bomb) < 1024
    # Under the library's 40 MP cap and matching its frame header: before, decode_jpeg allocated 108 MB for it.
    assert jpeg_problem(bomb, (6000, 6000)) is None
    reason, detail = jpeg_problem(bomb, (6000, 6000), min_bytes_per_mpixel=1000.0) or ("", "")
    assert reason == "jpeg_implausible" and "cannot hold 6000x6000" in detail
    with pytest.raises(JpegError, match="cannot hold"):
        decode_jpeg(bomb, (6000, 6000), min_bytes_per_mpixel=1000.0)
    assert jpeg_problem(bomb, (6000, 6000), max_pixels=6000 * 6000 - 1)[0] == "jpeg_too_large"
    assert jpeg_problem(bomb, (640, 480))[0] == "jpeg_size_mismatch"
    assert jpeg_problem(b"\xff\xd8" + b"\x00" * 10)[0] == "jpeg_corrupt"
    assert jpeg_problem(b"x" * 100, max_bytes=50)[0] == "jpeg_too_large"
    assert jpeg_problem(None)[0] == "jpeg_corrupt"


@pytest.mark.parametrize("shape", [(72, 96), (480, 640), (1080, 1920)])
@pytest.mark.parametrize("value", [0, 255])
def test_real_flat_jpegs_pass_the_byte_floor(shape: tuple[int, int], value: int) -> None:
    """The floor is below what an encoder produces for the flattest image (the least compressible-looking)."""
    import cv2

    img = np.full((*shape, 3), value, np.uint8)
    for flags in ([], [cv2.IMWRITE_JPEG_OPTIMIZE, 1], [cv2.IMWRITE_JPEG_OPTIMIZE, 1, cv2.IMWRITE_JPEG_PROGRESSIVE, 1]):
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 1, *flags])
        data = buf.tobytes()
        assert len(data) / (shape[0] * shape[1] / 1e6) > MIN_BYTES_PER_MPIXEL_FLOOR
        assert jpeg_problem(data, (shape[1], shape[0]), LIM.max_frame_pixels, LIM.min_jpeg_bytes_per_mpixel) is None


def test_arithmetic_coded_jpegs_are_refused_when_the_floor_is_on() -> None:
    j = bytearray(encode_jpeg(np.zeros((64, 64, 3), np.uint8)))
    i = j.find(b"\xff\xc0")
    j[i + 1] = 0xC9  # SOF9: arithmetic coding, which can beat one bit per block
    assert jpeg_problem(bytes(j), (64, 64), min_bytes_per_mpixel=1000.0)[0] == "jpeg_implausible"
    assert jpeg_problem(bytes(j), (64, 64)) is None


# --- intrinsics and poses -----------------------------------------------------------------------------
@pytest.mark.parametrize("field", ["fx", "fy", "cx", "cy"])
@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan])
def test_non_finite_intrinsics_never_validate(field: str, value: float) -> None:
    with pytest.raises(ValueError, match="finite"):
        Intrinsics(**{**INTR.model_dump(), field: value})


@pytest.mark.parametrize(
    ("update", "what"),
    [
        ({"fx": 1e-300}, "horizontal field of view 180"),
        ({"fy": 1e-3}, "vertical field of view 180"),
        ({"fy": 1e4}, "pixel aspect"),
        ({"fx": 1e6}, "horizontal field of view 0.0055"),
        ({"cx": 1e5}, "principal point"),
        ({"cy": -100.0}, "principal point"),
        ({"width": 97}, "intrinsics are for 97x72"),
    ],
)
def test_absurd_intrinsics_are_refused(update: dict[str, float], what: str) -> None:
    intr = Intrinsics(**{**INTR.model_dump(), **update})
    reason, detail = intrinsics_problem(intr, INTR.width, INTR.height, LIM) or ("", "")
    assert reason == "frames_bad_intrinsics" and what in detail


def test_plausible_intrinsics_pass() -> None:
    for hfov in (5.0, 60.0, 120.0, 170.0):
        for w, h in ((640, 480), (480, 640), (1920, 1080)):
            intr = Intrinsics.from_fov(w, h, hfov)
            assert intrinsics_problem(intr, w, h, LIM) is None, (hfov, w, h)
    off = Intrinsics(width=640, height=480, fx=500, fy=500, cx=700, cy=-100)  # off-centre, within the margin
    assert intrinsics_problem(off, 640, 480, LIM) is None
    constructed = Intrinsics.model_construct(width=640, height=480, fx=math.inf, fy=500.0, cx=320.0, cy=240.0)
    assert intrinsics_problem(constructed, 640, 480, LIM)[0] == "frames_bad_intrinsics"  # validation bypassed


def test_pose_outside_the_site_box_is_refused() -> None:
    T = np.eye(4)
    assert pose_problem(T, LIM) is None
    T[:3, 3] = (99.0, -99.0, 29.0)
    assert pose_problem(T, LIM) is None
    for t in ((101.0, 0.0, 0.0), (0.0, -100.5, 0.0), (0.0, 0.0, -10.5), (0.0, 0.0, 1e300)):
        T[:3, 3] = t
        reason, detail = pose_problem(T, LIM) or ("", "")
        assert reason == "frames_outside_site" and "outside the site box" in detail
    assert pose_problem([[1.0]], LIM)[0] == "frames_outside_site"


def test_limits_are_validated() -> None:
    with pytest.raises(ValueError):
        InputLimits(site_min_m=(0, 0, 0), site_max_m=(1, 1, 0))
    with pytest.raises(ValueError):
        InputLimits(min_hfov_deg=100, max_hfov_deg=90)
    with pytest.raises(ValueError):
        InputLimits(decode_budget_pixels=100, max_working_pixels=1000)
    with pytest.raises(ValueError):
        InputLimits(max_buffered_frame_bytes=2048, max_frame_bytes=4096)
    with pytest.raises(ValueError):
        MapperConfig.model_validate({"limits": {"site_max_m": [math.inf, 1, 1]}})


def test_frame_problem_orders_the_checks_cheapest_first() -> None:
    good = encode_jpeg(np.zeros((INTR.height, INTR.width, 3), np.uint8))
    assert frame_problem(header("a", 1), good, LIM) is None
    big = header("a", 1, width=9000, height=9000, intrinsics=None)
    assert frame_problem(big, jpeg_claiming(9000, 9000), LIM)[0] == "frames_too_large"  # 81 MP > 67 MP
    mid = header("a", 1, width=3000, height=3000, intrinsics=None)
    assert frame_problem(mid, jpeg_claiming(3000, 3000), LIM)[0] == "frames_implausible_jpeg"
    assert frame_problem(header("a", 1), jpeg_claiming(3000, 3000), LIM)[0] == "frames_size_mismatch"
    assert frame_problem(header("a", 1), b"\xff\xd8junk\xff\xd9", LIM)[0] == "frames_corrupt_jpeg"
    bad_intr = header("a", 1, intrinsics=INTR.model_copy(update={"fx": 1e-300}))
    assert frame_problem(bad_intr, good, LIM)[0] == "frames_bad_intrinsics"
    far = np.eye(4)
    far[:3, 3] = (150.0, 0.0, 1.0)
    assert frame_problem(header("a", 1, T_world_cam=far.tolist()), good, LIM)[0] == "frames_outside_site"


# --- bounded buffers ------------------------------------------------------------------------------------
def test_latest_slots_byte_bound_drops_the_oldest_across_keys() -> None:
    slots: LatestSlots[bytes] = LatestSlots(depth=2, max_keys=8, max_bytes=100, size=len)
    assert slots.put("a", b"1" * 40)
    assert slots.put("b", b"2" * 40)
    assert slots.bytes == 80 and slots.dropped == 0
    assert slots.put("c", b"3" * 40)  # 120 > 100: a's item (the least recently active key's oldest) goes
    assert slots.bytes == 80 and slots.dropped == 1
    assert not slots.put("d", b"4" * 101)  # alone over the bound: refused, nothing else dropped
    assert slots.dropped == 2 and slots.bytes == 80
    assert slots.put("b", b"5" * 10)  # the ring of b: 2 items
    assert [(k, len(v)) for k, v in slots.take_all()] == [("c", 40), ("b", 40), ("b", 10)]  # by activity
    assert slots.bytes == 0
    assert slots.put("a", b"6" * 30) and slots.put("a", b"7" * 30) and slots.put("a", b"8" * 30)
    assert slots.bytes == 60  # the ring's own eviction gives its bytes back
    with pytest.raises(ValueError):
        LatestSlots(max_bytes=10)


def test_latest_slots_wake_ends_a_wait_for_frames_and_is_not_lost_before_it() -> None:
    import threading

    slots: LatestSlots[bytes] = LatestSlots()
    got: list[list[tuple[str, bytes]]] = []
    slots.wake()  # news before the wait: the next take_all does not sleep out its timeout
    early = threading.Thread(target=lambda: got.append(slots.take_all(timeout=60.0)), daemon=True)
    early.start()
    early.join(timeout=5.0)
    assert not early.is_alive() and got == [[]]
    got.clear()
    t = threading.Thread(target=lambda: got.append(slots.take_all(timeout=60.0)), daemon=True)
    t.start()
    while not got and t.is_alive():
        slots.wake()  # a worker's result arrives while the mapper waits for frames
        t.join(timeout=0.05)
    t.join(timeout=5.0)
    assert not t.is_alive() and got == [[]]
    slots.put("a", b"x")
    assert slots.take_all(timeout=60.0) == [("a", b"x")]


def test_decode_budget() -> None:
    b = DecodeBudget(100)
    assert b.acquire(60) and not b.acquire(41) and b.acquire(40)
    assert b.in_flight == 100 and b.peak == 100
    b.release(60)
    b.release(60)
    assert b.in_flight == 0 and b.peak == 100


# --- the mapper's frame path, in-process ----------------------------------------------------------------
@dataclass
class Sample:
    """What MapperNode reads from a zenoh.Sample."""

    key_expr: str
    payload: zenoh.ZBytes
    attachment: zenoh.ZBytes | None = None


class Sink:
    def __init__(self) -> None:
        self.puts: list[Any] = []

    def put(self, *args: Any, **kw: Any) -> None:
        self.puts.append(args)

    def delete(self, *args: Any) -> None:
        self.puts.append(("delete", *args))


def mapper(oracle: bool = True, **limits: Any) -> MapperNode:
    """A mapper node with the oracle core; ``oracle=False``: configured as RGB-only (frames do not wait for ORACLE
    samples), still with the oracle core (its views then fail in the core: keyframe_errors)."""
    core_cfg = MapperConfig(site=SITE, geometry=GeometryConfig(backend="oracle"),
                            perception=PerceptionConfig(segmenter="sim", embedder="sim"),
                            limits=InputLimits(**limits))
    cfg = core_cfg if oracle else MapperConfig(site=SITE, limits=InputLimits(**limits))
    node = MapperNode(cfg, core=MapperCore(core_cfg))
    assert node.intake.needs_oracle == oracle
    return node


def frame(node: MapperNode, h: FrameHeader, jpeg: bytes) -> None:
    node.intake.on_frame(Sample(KEYS.robot_frame(h.source_id), zenoh.ZBytes(jpeg), zenoh.ZBytes(encode(h))))


def raw_frame(node: MapperNode, source: str, jpeg: bytes, header_body: dict[str, Any]) -> None:
    att = msgpack.packb(["ARG1", "frame_header", 1, 0, header_body], use_bin_type=True)
    node.intake.on_frame(Sample(KEYS.robot_frame(source), zenoh.ZBytes(jpeg), zenoh.ZBytes(att)))


def valid_frame(node: MapperNode, eye: list[float], seq: int, source: str = "robot1",
                pose: np.ndarray | None = None) -> FrameHeader:
    """A valid frame of the ray-cast scene with its ORACLE sample (fed first); ``pose`` replaces the header's."""
    v = view(eye, seq, source)
    assert v.oracle is not None and v.oracle.instance_id is not None and v.T_world_cam is not None
    o = OracleFrame(source_id=source, seq=seq, stamp_ns=v.stamp_ns, T_world_cam_true=v.oracle.T_world_cam_true,
                    ids_png=ids_to_png(v.oracle.instance_id), depth_png=depth_to_png(v.oracle.depth_m),
                    labels={str(k): lab for k, lab in LABELS.items()})
    node.intake.on_oracle(Sample(KEYS.oracle("robot", source), zenoh.ZBytes(encode(o))))
    h = header(source, seq, T_world_cam=(v.T_world_cam if pose is None else pose).tolist())
    frame(node, h, encode_jpeg(v.image))
    return h


def step(node: MapperNode) -> None:
    node.outbox.session, node.outbox.pubs = Sink(), {"delta": Sink(), "snapshot": Sink(), "map": Sink()}
    node._step(timeout_s=0.0)


@pytest.fixture
def decodes(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, int]]:
    """Every JPEG the mapper decodes (its claimed size)."""
    seen: list[tuple[int, int]] = []
    real = mapper_inbox.decode_jpeg

    def counting(data: bytes, expected_size: tuple[int, int], **kw: Any) -> np.ndarray:
        seen.append(expected_size)
        return real(data, expected_size, **kw)

    monkeypatch.setattr(mapper_inbox, "decode_jpeg", counting)
    return seen


def test_forty_bomb_frames_are_refused_unread_and_a_real_frame_still_maps(decodes: list[tuple[int, int]]) -> None:
    """Issue 19: 40 ~600-byte frames whose JPEG and header both claim 6000x6000 took the mapper to 4.6 GB."""
    node = mapper()
    for i in range(40):
        w = h = 9000 if i % 2 == 0 else 3000  # 81 MP: over the pixel cap; 9 MP: too few bytes for it
        frame(node, header(f"evil{i}", 1, width=w, height=h, intrinsics=None), jpeg_claiming(w, h))
    c = node.counters.snapshot()
    assert c["frames_too_large"] == 20 and c["frames_implausible_jpeg"] == 20 and c["decode_errors"] == 40
    assert len(node.intake.slots) == 0 and node.intake.slots.bytes == 0  # not one took a ring slot
    step(node)
    assert decodes == [] and node.intake.decode_budget.peak == 0
    # A real frame afterwards is decoded (alone, within the budget) and maps.
    valid_frame(node, EYES[0], 1)
    step(node)
    assert decodes == [(INTR.width, INTR.height)]
    assert node.intake.decode_budget.peak == INTR.width * INTR.height and node.intake.decode_budget.in_flight == 0
    assert node.counters.get("frames_processed") == 1 and len(node.core.store.nodes) > 0


def test_with_the_byte_floor_off_frames_are_still_decoded_one_at_a_time(decodes: list[tuple[int, int]]) -> None:
    node = mapper(oracle=False, min_jpeg_bytes_per_mpixel=0.0, max_frame_pixels=9_000_000,
                  decode_budget_pixels=9_000_000)
    for i in range(4):
        frame(node, header(f"evil{i}", 1, width=3000, height=3000, intrinsics=None), jpeg_claiming(3000, 3000))
    assert len(node.intake.slots) == 4
    step(node)
    assert len(decodes) == 4  # libjpeg "decodes" each (filling grey), at 1/4 (750x750: max_working_pixels)...
    assert node.intake.decode_budget.peak == 750 * 750  # ...one at a time: never two images in flight
    assert node.intake.decode_budget.in_flight == 0


def test_impossible_intrinsics_and_poses_are_refused_with_counters_and_create_no_node() -> None:
    node = mapper(**TIGHT)
    good = encode_jpeg(view(EYES[0], 1).image)
    body = header("robot1", 1).model_dump()
    for i, (field, value) in enumerate([("fx", math.inf), ("cx", math.nan), ("fy", -math.inf)]):
        raw_frame(node, "robot1", good, {**body, "seq": 10 + i, "intrinsics": {**body["intrinsics"], field: value}})
    for seq, update in ((20, {"fx": 1e-300}), (21, {"fx": 1e7}), (22, {"cy": 1e4})):
        frame(node, header("robot1", seq, intrinsics=INTR.model_copy(update=update)), good)
    # A replayed valid frame with its pose shifted 50 m: outside the site's box.
    T = view(EYES[0], 1).T_world_cam
    assert T is not None
    shifted = T.copy()
    shifted[0, 3] += 50.0
    valid_frame(node, EYES[0], 30, pose=shifted)
    step(node)
    c = node.counters.snapshot()
    assert c["header_errors"] == 3 and c["frames_bad_intrinsics"] == 3 and c["frames_outside_site"] == 1
    assert c.get("frames_processed", 0) == 0 and node.core.counters.get("views_in", 0) == 0
    assert node.core.version == 0 and len(node.core.store.nodes) == 0
    # The real frame of the replay still maps.
    valid_frame(node, EYES[0], 31)
    step(node)
    assert node.counters.get("frames_processed") == 1 and len(node.core.store.nodes) > 0


def test_a_flood_of_bad_frames_logs_one_line_per_reason_then_a_summary(caplog: pytest.LogCaptureFixture) -> None:
    node = mapper()
    now = [0.0]
    node.intake.bad_input = RateLimitedLog(logging.getLogger("mapper.node"), 10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="mapper.node"):
        for i in range(1000):
            frame(node, header(f"evil{i % 50}", i, width=9000, height=9000, intrinsics=None), jpeg_claiming(9000, 9000))
            node.intake.on_frame(Sample(KEYS.robot_frame("evil"), zenoh.ZBytes(b"x"), zenoh.ZBytes(b"\x93garbage")))
        now[0] = 10.0
        step(node)  # flushes the summary
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 3, lines
    assert lines[0].startswith("refused a frame from evil0#0: frame header claims 9000x9000")
    assert lines[1].startswith("bad frame sample on")
    assert lines[2] == ("1998 more bad inputs in the last 10 s (not logged one by one): frames_too_large x999, "
                        "header_errors x999")


def test_an_oversized_payload_is_refused_before_it_is_copied() -> None:
    node = mapper(max_frame_bytes=4096, max_buffered_frame_bytes=8192)

    class Payload:
        def __len__(self) -> int:
            return 5000

        def to_bytes(self) -> bytes:
            raise AssertionError("the payload was copied")

    node.intake.on_frame(Sample(KEYS.robot_frame("big"), Payload(), zenoh.ZBytes(encode(header("big", 1)))))  # type: ignore[arg-type]
    assert node.counters.get("frames_too_large") == 1 and node.counters.get("frame_errors") == 0


# --- the core, for in-process callers (explorer, benchmarks) ----------------------------------------------
def test_core_refuses_impossible_views_and_creates_no_node() -> None:
    cfg = MapperConfig(geometry=GeometryConfig(backend="oracle"),
                       perception=PerceptionConfig(segmenter="sim", embedder="sim"), limits=InputLimits(**TIGHT))
    core = MapperCore(cfg)
    v = view(EYES[0], 1)
    assert v.T_world_cam is not None
    far = v.T_world_cam.copy()
    far[:3, 3] += (50.0, 0.0, 0.0)
    inf_intr = Intrinsics.model_construct(**{**INTR.model_dump(), "fx": math.inf})
    bad = [
        v.__class__(**{**v.__dict__, "T_world_cam": far}),
        v.__class__(**{**v.__dict__, "seq": 2, "intrinsics": INTR.model_copy(update={"fx": 1e-300})}),
        v.__class__(**{**v.__dict__, "seq": 3, "intrinsics": inf_intr}),
    ]
    for b in bad:
        assert view_problem(b, cfg.limits) is not None
        assert core.ingest(b) is None
        assert core.mark_processed(b) is None  # a refused view is not reported as processed either
    assert core.counters["views_refused"] == 3
    assert core.counters["frames_outside_site"] == 1 and core.counters["frames_bad_intrinsics"] == 2
    assert core.counters.get("keyframes", 0) == 0 and len(core.store.nodes) == 0 and core.version == 0
    assert core.ingest(v) is not None and len(core.store.nodes) > 0


@pytest.mark.parametrize("launch", ["demo", "demo-oracle", "demo-rgb-only"])
def test_the_demo_stacks_refuse_a_frame_shifted_50_m(launch: str) -> None:
    """Issue 19: a replayed frame shifted 50 m created 6 ghost nodes in the demo; its mapper now knows the site."""
    from pathlib import Path

    from deploy.up import load_launch

    spec = next(p for p in load_launch(Path(f"deploy/launch/{launch}.toml")).process if p.name == "mapper")
    settings = {k: v for k, v in (spec.settings or {}).items() if k not in ("site", "zenoh")}
    limits = MapperConfig.model_validate(settings).limits
    T = np.eye(4)
    for xyz in ((0.0, 0.0, 0.0), (12.0, 9.0, 3.0), (5.0, 4.0, 1.2)):  # the simulated worlds' extent
        T[:3, 3] = xyz
        assert pose_problem(T, limits) is None
        for axis in range(2):
            T2 = T.copy()
            T2[axis, 3] += 50.0
            assert pose_problem(T2, limits) is not None
