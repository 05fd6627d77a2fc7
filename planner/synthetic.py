"""Small hand-made worlds (point maps, viewpoint sets, graphs) for planner tests and benchmarks.

Pure numpy, no simulator: boxes sampled as surface points on a voxel grid.
"""

from __future__ import annotations

import numpy as np

from protocol.messages import (
    GraphNode,
    GraphSnapshot,
    Intrinsics,
    OrientedBox,
    PointMap,
    RobotState,
    RobotStatus,
    Viewpoint,
    ViewpointSet,
    rows,
)
from protocol.poses import camera_pose_from_base

CAMERA_HEIGHT_M = 1.0
CAMERA_PITCH_DEG = -15.0


def plane_points(origin: np.ndarray, u: np.ndarray, v: np.ndarray, step_m: float) -> np.ndarray:
    """Grid points on the parallelogram ``origin + a u + b v`` (a, b in [0, 1])."""
    nu = max(1, int(round(np.linalg.norm(u) / step_m)))
    nv = max(1, int(round(np.linalg.norm(v) / step_m)))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    return np.asarray(origin)[None, :] + a.reshape(-1, 1) * np.asarray(u) + b.reshape(-1, 1) * np.asarray(v)


def box_points(
    center: tuple[float, float, float], extent: tuple[float, float, float], step_m: float
) -> np.ndarray:
    """Surface points of an axis-aligned box (all six faces)."""
    c, e = np.asarray(center, float), np.asarray(extent, float)
    lo = c - e / 2
    ex, ey, ez = np.diag(e)
    faces = [
        plane_points(lo, ex, ey, step_m),
        plane_points(lo + ez, ex, ey, step_m),
        plane_points(lo, ex, ez, step_m),
        plane_points(lo + ey, ex, ez, step_m),
        plane_points(lo, ey, ez, step_m),
        plane_points(lo + ex, ey, ez, step_m),
    ]
    return np.concatenate(faces)


def room_points(
    xy_min: tuple[float, float], xy_max: tuple[float, float], height_m: float, step_m: float
) -> np.ndarray:
    """Floor and four walls of a rectangular room."""
    x0, y0 = xy_min
    x1, y1 = xy_max
    dx, dy, dz = np.array([x1 - x0, 0, 0]), np.array([0, y1 - y0, 0]), np.array([0, 0, height_m])
    o = np.array([x0, y0, 0.0])
    return np.concatenate(
        [
            plane_points(o, dx, dy, step_m),
            plane_points(o, dx, dz, step_m),
            plane_points(o + dy, dx, dz, step_m),
            plane_points(o, dy, dz, step_m),
            plane_points(o + dx, dy, dz, step_m),
        ]
    )


def point_map(
    points: np.ndarray, voxel_m: float, counts: float | np.ndarray = 5.0, version: int = 1
) -> PointMap:
    """A PointMap of voxel-rounded unique points with the given observation counts."""
    P = (np.round(np.asarray(points, dtype=np.float64) / voxel_m) + 0.5) * voxel_m  # voxel centres
    P, idx = np.unique(P, axis=0, return_index=True)
    cnt = (
        np.broadcast_to(np.asarray(counts, dtype=np.float64), (points.shape[0],))[idx]
        if np.ndim(counts)
        else np.full(P.shape[0], float(counts))
    )
    return PointMap(
        version=version,
        stamp_ns=version,
        voxel_m=voxel_m,
        points=P.astype(np.float32),
        counts=cnt.astype(np.float32),
    )


def grid_viewpoints(
    robot_id: str,
    xy_min: tuple[float, float],
    xy_max: tuple[float, float],
    spacing_m: float = 0.6,
    n_headings: int = 8,
    room_of: object = None,
    intrinsics: Intrinsics | None = None,
    max_range_m: float = 6.0,
) -> ViewpointSet:
    """A grid of viewpoints with ``n_headings`` headings each; ``room_of(x, y) -> str | None`` names rooms."""
    xs = np.arange(xy_min[0], xy_max[0] + 1e-9, spacing_m)
    ys = np.arange(xy_min[1], xy_max[1] + 1e-9, spacing_m)
    vps: list[Viewpoint] = []
    for x in xs:
        for y in ys:
            for h in range(n_headings):
                room = room_of(float(x), float(y)) if callable(room_of) else None
                vps.append(
                    Viewpoint(
                        vp_id=len(vps), x=float(x), y=float(y), yaw_rad=2 * np.pi * h / n_headings, room=room
                    )
                )
    return ViewpointSet(
        robot_id=robot_id,
        camera_height_m=CAMERA_HEIGHT_M,
        camera_pitch_deg=CAMERA_PITCH_DEG,
        intrinsics=intrinsics or Intrinsics.from_fov(640, 480, 90.0),
        max_range_m=max_range_m,
        viewpoints=vps,
    )


def robot_state(
    robot_id: str, x: float, y: float, yaw_rad: float, status: RobotStatus = "arrived", goal_id: str | None = None
) -> RobotState:
    return RobotState(
        robot_id=robot_id,
        stamp_ns=1,
        status=status,
        x=x,
        y=y,
        yaw_rad=yaw_rad,
        T_world_cam=rows(camera_pose_from_base(x, y, yaw_rad, CAMERA_HEIGHT_M, CAMERA_PITCH_DEG)),
        goal_id=goal_id,
    )


def node(
    node_id: str, label: str, center: tuple[float, float, float], extent: tuple[float, float, float]
) -> GraphNode:
    return GraphNode(
        node_id=node_id,
        label=label,
        label_confidence=0.9,
        centroid=center,
        box=OrientedBox(center=center, extent=extent),
        point_count=100,
        observation_count=3,
        first_seen_ns=0,
        last_seen_ns=0,
    )


def snapshot(nodes: list[GraphNode], version: int = 1) -> GraphSnapshot:
    return GraphSnapshot(version=version, stamp_ns=version, nodes=nodes, edges=[])


def apartment(seed: int = 0, step_m: float = 0.05) -> dict:
    """A 3-room synthetic apartment: rooms, the full point cloud and its furniture nodes.

    Returns ``{"rooms": {name: (xy_min, xy_max)}, "points": (N,3), "nodes": [GraphNode]}``.
    """
    rng = np.random.default_rng(seed)
    rooms = {
        "living_room": ((0.0, 0.0), (6.0, 5.0)),
        "kitchen": ((6.0, 0.0), (10.0, 5.0)),
        "bedroom_1": ((0.0, 5.0), (6.0, 9.0)),
    }
    pts = [room_points(lo, hi, 2.6, step_m) for lo, hi in rooms.values()]
    furniture = [
        ("sofa", (1.5, 1.0, 0.42), (2.0, 0.9, 0.85)),
        ("coffee table", (2.0, 2.2, 0.22), (1.1, 0.6, 0.45)),
        ("refrigerator", (9.5, 4.5, 0.9), (0.8, 0.7, 1.8)),
        ("kitchen counter", (8.0, 0.4, 0.45), (2.5, 0.65, 0.9)),
        ("bed", (3.0, 7.5, 0.28), (1.6, 2.0, 0.55)),
        ("wardrobe", (5.6, 8.5, 1.0), (0.6, 1.2, 2.0)),
    ]
    nodes = []
    for i, (lab, c, e) in enumerate(furniture):
        pts.append(box_points(c, e, step_m))
        nodes.append(node(f"n{i}", lab, c, e))
    for _ in range(3):
        c = (float(rng.uniform(1.0, 5.0)), float(rng.uniform(3.0, 4.5)), 0.3)
        pts.append(box_points(c, (0.4, 0.4, 0.6), step_m))
    return {"rooms": rooms, "points": np.concatenate(pts), "nodes": nodes}


def room_namer(rooms: dict) -> object:
    def name(x: float, y: float) -> str | None:
        for n, ((x0, y0), (x1, y1)) in rooms.items():
            if x0 <= x <= x1 and y0 <= y <= y1:
                return n
        return None

    return name
