"""Codec: every message round-trips; hostile bytes only ever raise DecodeError."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import arrays as wire_arrays
from protocol.codec import MAGIC, DecodeError, decode, encode
from protocol.messages import (
    ALL_MESSAGES,
    FrameHeader,
    GoalStatus,
    GraphDelta,
    GraphEdge,
    GraphNode,
    GraphSnapshot,
    Intrinsics,
    LabelScore,
    NbvGoal,
    OracleFrame,
    OrientedBox,
    PointMap,
    RobotState,
    Status,
    Viewpoint,
    ViewpointSet,
    WorkAck,
    WorkDetection,
    WorkFrame,
    WorkJob,
    WorkResult,
    rows,
)
from protocol.messages import vec3 as as_vec3
from protocol.poses import camera_pose_from_base

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
pos = st.floats(min_value=1e-3, max_value=1e4, allow_nan=False)
ids = st.from_regex(r"[A-Za-z0-9_.\-]{1,20}", fullmatch=True)
stamps = st.integers(min_value=0, max_value=2**63 - 1)
vec3 = st.tuples(finite, finite, finite)


@st.composite
def poses(draw: st.DrawFn) -> list[list[float]]:
    yaw, pitch = draw(st.floats(-3.2, 3.2)), draw(st.floats(-80, 80))
    T = camera_pose_from_base(draw(finite), draw(finite), yaw, draw(pos), pitch)
    return T.tolist()


@st.composite
def arrays(draw: st.DrawFn, dtype: str = "float32", cols: int | None = 3) -> np.ndarray:
    n = draw(st.integers(0, 20))
    shape = (n, cols) if cols else (n,)
    data = draw(st.lists(st.floats(-1e3, 1e3, width=32), min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))
    return np.asarray(data, dtype=dtype).reshape(shape)


intrinsics = st.builds(Intrinsics, width=st.integers(1, 4096), height=st.integers(1, 4096), fx=pos, fy=pos,
                       cx=finite, cy=finite)
boxes = st.builds(OrientedBox, center=vec3, extent=st.tuples(pos, pos, pos), yaw_rad=st.floats(-3.2, 3.2))
nodes = st.builds(
    GraphNode, node_id=ids, label=st.text(max_size=30), label_confidence=st.floats(0, 1),
    label_alternatives=st.lists(
        st.builds(LabelScore, label=st.text(max_size=10), score=st.floats(0, 1)), max_size=3
    ),
    centroid=vec3, box=boxes, point_count=st.integers(0, 10**6), observation_count=st.integers(0, 10**4),
    sources=st.lists(ids, max_size=3), first_seen_ns=stamps, last_seen_ns=stamps,
    embedding=st.one_of(st.none(), arrays(cols=None)),
)
edges = st.builds(GraphEdge, subject_id=ids, object_id=ids,
                  predicate=st.sampled_from(["on_top_of", "under", "over", "inside", "next_to"]))

work_frames = st.builds(WorkFrame, source_id=ids, seq=st.integers(0, 2**40), stamp_ns=stamps,
                        width=st.integers(1, 4096), height=st.integers(1, 4096),
                        intrinsics=st.one_of(st.none(), intrinsics), T_world_cam=st.one_of(st.none(), poses()),
                        pose_trusted=st.booleans())
work_dets = st.builds(WorkDetection, mask_png=st.binary(max_size=64), label=st.text(max_size=10),
                      confidence=st.floats(0, 1), descriptor=arrays(cols=None),
                      alternatives=st.lists(st.tuples(st.text(max_size=5), finite), max_size=2),
                      instance_key=st.integers(0, 10**6))
work_jobs = st.lists(work_frames, min_size=1, max_size=4).flatmap(lambda w: st.builds(
    WorkJob, job_id=ids, attempt=st.integers(1, 9), window=st.just(w), target_index=st.integers(0, len(w) - 1),
    jpeg=st.binary(max_size=64), perception=st.booleans(),
    core_config=st.dictionaries(ids, st.one_of(finite, st.text(max_size=5)), max_size=3),
    config_digest=st.text(max_size=32)))

STRATEGIES = {
    Intrinsics: intrinsics,
    FrameHeader: st.builds(FrameHeader, source_id=ids, source_kind=st.sampled_from(["fixed", "robot"]),
                           seq=st.integers(0, 2**40), stamp_ns=stamps, width=st.integers(1, 8000),
                           height=st.integers(1, 8000), intrinsics=st.one_of(st.none(), intrinsics),
                           T_world_cam=st.one_of(st.none(), poses()), pose_trusted=st.booleans()),
    RobotState: st.builds(RobotState, robot_id=ids, stamp_ns=stamps,
                          status=st.sampled_from(
                              ["idle", "moving", "arrived", "failed", "refused", "budget_exhausted"]),
                          x=finite, y=finite, yaw_rad=finite, T_world_cam=poses(), goal_id=st.one_of(st.none(), ids),
                          distance_m=pos, steps=st.integers(0, 1000),
                          travel_cost_m=st.one_of(st.none(), arrays(cols=None))),
    Viewpoint: st.builds(Viewpoint, vp_id=st.integers(0, 10**6), x=finite, y=finite, yaw_rad=finite),
    ViewpointSet: st.builds(ViewpointSet, robot_id=ids, camera_height_m=pos, intrinsics=intrinsics,
                            viewpoints=st.lists(st.builds(Viewpoint, vp_id=st.integers(0, 99), x=finite, y=finite,
                                                          yaw_rad=finite), max_size=5)),
    NbvGoal: st.builds(NbvGoal, goal_id=ids, robot_id=ids, stamp_ns=stamps, x=finite, y=finite, yaw_rad=finite,
                       expected_gain=finite, strategy=st.sampled_from(["see", "asp"])),
    OrientedBox: boxes,
    LabelScore: st.builds(LabelScore, label=st.text(max_size=10), score=finite),
    GraphNode: nodes,
    GraphEdge: edges,
    GraphSnapshot: st.builds(GraphSnapshot, version=st.integers(0, 2**40), stamp_ns=stamps,
                             nodes=st.lists(nodes, max_size=3), edges=st.lists(edges, max_size=3)),
    GraphDelta: st.builds(GraphDelta, version=st.integers(1, 2**40), stamp_ns=stamps,
                          upserted=st.lists(nodes, max_size=3), removed=st.lists(ids, max_size=3),
                          edges_added=st.lists(edges, max_size=3)),
    PointMap: arrays().flatmap(lambda pts: st.builds(
        PointMap, version=st.integers(0, 100), stamp_ns=stamps, voxel_m=pos, points=st.just(pts),
        counts=st.one_of(st.none(), st.lists(st.integers(0, 65535), min_size=len(pts), max_size=len(pts)).map(
            lambda v: np.asarray(v, np.uint16))))),
    Status: st.builds(Status, role=ids, node_id=ids, stamp_ns=stamps,
                      counters=st.dictionaries(ids, finite, max_size=5), last_error=st.one_of(st.none(), st.text())),
    OracleFrame: st.builds(OracleFrame, source_id=ids, seq=st.integers(0, 100), stamp_ns=stamps,
                           T_world_cam_true=poses(), ids_png=st.one_of(st.none(), st.binary(max_size=64)),
                           labels=st.dictionaries(st.from_regex(r"[0-9]{1,4}", fullmatch=True), st.text(max_size=8))),
    GoalStatus: st.builds(GoalStatus, robot_id=ids, stamp_ns=stamps, goal_id=st.one_of(st.none(), ids),
                          accepted=st.booleans(), reason=st.text(max_size=40), received=st.integers(0, 10**6),
                          suppressed=st.integers(0, 10**6)),
    WorkFrame: work_frames,
    WorkJob: work_jobs,
    WorkAck: st.builds(WorkAck, job_id=ids, attempt=st.integers(1, 9), worker_id=ids),
    WorkDetection: work_dets,
    WorkResult: st.builds(WorkResult, job_id=ids, attempt=st.integers(1, 9), worker_id=ids, ok=st.booleans(),
                          error=st.one_of(st.none(), st.text(max_size=20)), anchored=st.booleans(),
                          T_world_cam=st.one_of(st.none(), poses()), intrinsics=st.one_of(st.none(), intrinsics),
                          depth_png=st.one_of(st.none(), st.binary(max_size=64)), depth_unit_m=pos,
                          confidence_png=st.one_of(st.none(), st.binary(max_size=64)),
                          detections=st.one_of(st.none(), st.lists(work_dets, max_size=2)),
                          timings_s=st.dictionaries(ids, finite, max_size=3)),
}


def test_every_message_has_a_strategy() -> None:
    assert set(STRATEGIES) == set(ALL_MESSAGES)


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
def test_round_trip(cls: type) -> None:
    @settings(max_examples=25, deadline=None)
    @given(STRATEGIES[cls])
    def check(msg) -> None:  # noqa: ANN001
        assert decode(encode(msg), cls) == msg
        assert decode(encode(msg)) == msg

    check()


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_only_raise_decode_error(data: bytes) -> None:
    try:
        decode(data)
    except DecodeError:
        pass


def _sample_messages() -> list:
    pose = camera_pose_from_base(1.0, 2.0, 0.3, 1.0, -15.0)
    node = GraphNode(node_id="n1", label="chair", label_confidence=0.9, centroid=(1, 2, 0.4),
                     box=OrientedBox(center=(1, 2, 0.4), extent=(0.5, 0.5, 0.9)), point_count=10,
                     observation_count=2, first_seen_ns=1, last_seen_ns=2,
                     embedding=np.arange(8, dtype=np.float32))
    return [
        FrameHeader(source_id="cam0", source_kind="fixed", seq=3, stamp_ns=5, width=640, height=480,
                    intrinsics=Intrinsics.from_fov(640, 480, 90), T_world_cam=pose),
        GraphSnapshot(version=3, stamp_ns=9, nodes=[node], edges=[GraphEdge(subject_id="n1", predicate="next_to",
                                                                           object_id="n2")]),
        PointMap(version=1, stamp_ns=1, voxel_m=0.05, points=np.random.default_rng(0).random((50, 3), np.float32)),
    ]


@pytest.mark.parametrize("msg", _sample_messages(), ids=lambda m: type(m).__name__)
def test_every_truncation_raises_decode_error(msg) -> None:  # noqa: ANN001
    data = encode(msg)
    for cut in range(0, len(data), max(1, len(data) // 200)):
        with pytest.raises(DecodeError):
            decode(data[:cut])


@pytest.mark.parametrize("msg", _sample_messages(), ids=lambda m: type(m).__name__)
def test_bit_flips_never_escape(msg) -> None:  # noqa: ANN001
    data = bytearray(encode(msg))
    rng = np.random.default_rng(1)
    for _ in range(300):
        corrupt = bytearray(data)
        for i in rng.integers(0, len(corrupt), size=3):
            corrupt[i] ^= int(rng.integers(1, 256))
        try:
            decode(bytes(corrupt))
        except DecodeError:
            pass


def _envelope(kind: str, major: int, minor: int, body: dict) -> bytes:
    return msgpack.packb([MAGIC, kind, major, minor, body], use_bin_type=True)


def test_unknown_major_version_is_refused() -> None:
    body = encode(Status(role="r", node_id="n", stamp_ns=1))
    env = msgpack.unpackb(body, raw=False)
    with pytest.raises(DecodeError, match="major"):
        decode(_envelope(env[1], env[2] + 1, 0, env[4]))


def test_older_minor_is_accepted_and_newer_minor_drops_unknown_fields() -> None:
    env = msgpack.unpackb(encode(Status(role="r", node_id="n", stamp_ns=1)), raw=False)
    older = decode(_envelope(env[1], env[2], 0, env[4]))
    assert older == Status(role="r", node_id="n", stamp_ns=1)
    newer = decode(_envelope(env[1], env[2], env[3] + 1, {**env[4], "added_in_1_1": 7}))
    assert newer == older


def test_wrong_kind_is_refused() -> None:
    data = encode(Status(role="r", node_id="n", stamp_ns=1))
    with pytest.raises(DecodeError, match="expected"):
        decode(data, FrameHeader)


def test_schema_violation_is_refused() -> None:
    env = msgpack.unpackb(encode(Status(role="r", node_id="n", stamp_ns=1)), raw=False)
    with pytest.raises(DecodeError, match="validation"):
        decode(_envelope(env[1], env[2], env[3], {**env[4], "stamp_ns": -5}))
    with pytest.raises(DecodeError):
        decode(_envelope("frame_header", 1, 0, {"source_id": "a/b"}))


def test_non_finite_pose_is_refused() -> None:
    with pytest.raises(ValueError):
        FrameHeader(source_id="c", source_kind="fixed", seq=0, stamp_ns=0, width=1, height=1,
                    T_world_cam=np.full((4, 4), np.nan))


def test_oversized_array_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    pm = PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.zeros((100, 3), np.float32))
    data = encode(pm)
    monkeypatch.setattr(wire_arrays, "MAX_ARRAY_ELEMENTS", 299)
    with pytest.raises(DecodeError, match="cap"):
        decode(data)


def test_array_with_wrong_byte_length_is_refused() -> None:
    ext = msgpack.ExtType(1, msgpack.packb(["<f4", [10, 3], b"\x00" * 8], use_bin_type=True))
    with pytest.raises(DecodeError, match="byte length"):
        decode(_envelope("point_map", 1, 0, {"version": 1, "stamp_ns": 1, "voxel_m": 0.1, "points": ext}))


def test_object_dtype_array_is_refused() -> None:
    ext = msgpack.ExtType(1, msgpack.packb(["|O", [1], b"\x00" * 8], use_bin_type=True))
    with pytest.raises(DecodeError, match="dtype"):
        decode(_envelope("point_map", 1, 0, {"version": 1, "stamp_ns": 1, "voxel_m": 0.1, "points": ext}))


def test_arrays_keep_dtype_and_shape() -> None:
    pts = np.arange(12, dtype=np.float32).reshape(4, 3)
    counts = np.array([1, 2, 3, 4], dtype=np.uint16)
    back = decode(encode(PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=pts, counts=counts)), PointMap)
    assert back.points.dtype == np.float32 and back.points.shape == (4, 3)
    assert np.array_equal(back.points, pts) and back.counts.dtype == np.uint16


def test_json_dump_of_arrays_gives_lists() -> None:
    pm = PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.ones((2, 3), np.float32))
    assert '"points":[[1.0,1.0,1.0],[1.0,1.0,1.0]]' in pm.model_dump_json()


@pytest.mark.parametrize("points", [np.zeros((5, 2), np.float32), np.zeros((5,), np.float32),
                                    np.full((2, 3), np.nan, np.float32), np.zeros((2, 3), np.uint8)])
def test_point_map_with_bad_points_is_refused(points: np.ndarray) -> None:
    with pytest.raises(ValueError):
        PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=points)


def test_point_map_counts_must_match_points() -> None:
    with pytest.raises(ValueError, match="counts"):
        PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.zeros((3, 3), np.float32),
                 counts=np.zeros(4, np.uint16))


class TestMatrixAndVectorFieldValues:
    """``rows`` / ``vec3`` turn ndarrays into what Mat4 / Vec3 fields hold, so typed code passes field values."""

    def test_rows_gives_the_same_field_as_the_array_and_round_trips(self) -> None:
        T = camera_pose_from_base(1.0, 2.0, 0.3, 1.2, -15.0)
        r = rows(T)
        assert isinstance(r, list) and all(isinstance(v, float) for row in r for v in row)
        kw = dict(source_id="c", source_kind="fixed", seq=0, stamp_ns=0, width=4, height=3)
        assert FrameHeader(**kw, T_world_cam=r) == FrameHeader(**kw, T_world_cam=T)  # type: ignore[arg-type]
        assert np.array_equal(np.asarray(decode(encode(FrameHeader(**kw, T_world_cam=r))).T_world_cam), T)

    def test_rows_leaves_shape_and_finiteness_to_the_field(self) -> None:
        kw = dict(source_id="c", source_kind="fixed", seq=0, stamp_ns=0, width=4, height=3)
        with pytest.raises(ValueError, match="4x4"):
            FrameHeader(**kw, T_world_cam=rows(np.eye(3)))  # type: ignore[arg-type]
        bad = np.eye(4)
        bad[0, 3] = np.nan
        with pytest.raises(ValueError, match="finite"):
            FrameHeader(**kw, T_world_cam=rows(bad))  # type: ignore[arg-type]

    def test_vec3_gives_three_floats_and_refuses_other_shapes(self) -> None:
        v = as_vec3(np.array([1, 2, 3], dtype=np.int64))
        assert v == (1.0, 2.0, 3.0) and all(type(c) is float for c in v)
        assert OrientedBox(center=as_vec3(np.zeros(3)), extent=as_vec3([1, 1, 1])).extent == (1.0, 1.0, 1.0)
        for bad in ([1.0, 2.0], np.zeros((1, 3)), [1, 2, 3, 4]):
            with pytest.raises(ValueError, match="3 numbers"):
                as_vec3(bad)
