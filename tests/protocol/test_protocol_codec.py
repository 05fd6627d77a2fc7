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
    GraphEdge,
    GraphNode,
    GraphSnapshot,
    Intrinsics,
    OrientedBox,
    PointMap,
    Status,
    rows,
)
from protocol.messages import vec3 as as_vec3
from protocol.poses import camera_pose_from_base
from tests.support.strategies import (
    STRATEGIES,
)


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
