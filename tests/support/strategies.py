"""Hypothesis strategies: one for every wire message (``STRATEGIES``), and the value strategies they are
built from. Used by the codec round trips and the fuzz campaign."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from protocol.messages import (
    FrameHeader,
    GoalStatus,
    GraphDelta,
    GraphEdge,
    GraphNode,
    GraphSnapshot,
    Intrinsics,
    LabelScore,
    NbvGoal,
    NodeMove,
    OracleFrame,
    OrientedBox,
    PointMap,
    RetiredNode,
    RobotState,
    Status,
    Viewpoint,
    ViewpointSet,
    WorkAck,
    WorkDetection,
    WorkFrame,
    WorkJob,
    WorkResult,
)
from protocol.poses import camera_pose_from_base
from protocol.rooms import RoomEdge, RoomLayer, RoomNode

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

node_moves = st.builds(NodeMove, node_id=ids, stamp_ns=stamps, from_centroid=vec3, to_centroid=vec3,
                       moves=st.integers(1, 10**6))
retired_nodes = st.builds(RetiredNode, node=nodes, retired_ns=stamps, version=st.integers(0, 2**40),
                          last_moved_ns=stamps)
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
    NodeMove: node_moves,
    RetiredNode: retired_nodes,
    GraphSnapshot: st.builds(GraphSnapshot, version=st.integers(0, 2**40), stamp_ns=stamps,
                             nodes=st.lists(nodes, max_size=3), edges=st.lists(edges, max_size=3),
                             moves=st.lists(node_moves, max_size=2), retired=st.lists(retired_nodes, max_size=2)),
    GraphDelta: st.builds(GraphDelta, version=st.integers(1, 2**40), stamp_ns=stamps,
                          upserted=st.lists(nodes, max_size=3), removed=st.lists(ids, max_size=3),
                          edges_added=st.lists(edges, max_size=3), moves=st.lists(node_moves, max_size=2),
                          retired=st.lists(retired_nodes, max_size=2)),
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

# The room layer's messages (protocol.rooms; registered with the codec beside protocol.messages' ALL_MESSAGES).
room_nodes = st.builds(RoomNode, room_id=ids, label=st.text(max_size=12), label_confidence=st.floats(0, 1),
                       polygon=st.lists(st.tuples(finite, finite), max_size=6), floor_z_m=finite, area_m2=pos,
                       observed_fraction=st.floats(0, 1), centroid=st.tuples(finite, finite))
room_edges = st.one_of(
    st.builds(RoomEdge, subject_id=ids, predicate=st.just("in_room"), object_id=ids),
    st.builds(RoomEdge, subject_id=ids, predicate=st.just("connects"), object_id=ids,
              position=st.tuples(finite, finite), width_m=pos))
ROOM_STRATEGIES = {
    RoomNode: room_nodes,
    RoomEdge: room_edges,
    RoomLayer: st.builds(RoomLayer, epoch=st.text(max_size=8), version=st.integers(0, 2**40), stamp_ns=stamps,
                         rooms=st.lists(room_nodes, max_size=3), edges=st.lists(room_edges, max_size=4)),
}
