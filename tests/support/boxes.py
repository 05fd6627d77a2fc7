"""A tiny analytic world of axis-aligned boxes (a table, a basket on it, a chair) for mapper tests:
its ray caster (depth and instance per pixel), posed views with ORACLE depth and instances, and an oracle
MapperCore. Stands in for geometry and the simulator where a test needs exact, fast inputs."""

from __future__ import annotations

import numpy as np

from mapper.config import GeometryConfig, MapperCoreConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.geometry.contract import OracleData, View
from protocol.messages import Intrinsics
from protocol.poses import look_at, transform_points

INTR = Intrinsics.from_fov(96, 72, 90.0)


def raycast(T_world_cam: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """(depth_m (H, W), box index per pixel (-1 = none)) of axis-aligned boxes (lo, hi) in the world."""
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    d_cam = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1)
    d_world = d_cam @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    best = np.full(u.shape, np.inf)
    idx = np.full(u.shape, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (lo, hi) in enumerate(boxes):
            t1 = (lo - o) / d_world
            t2 = (hi - o) / d_world
            tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (tmax >= tmin) & (tmin > 0) & (tmin < best)
            best[hit] = tmin[hit]
            idx[hit] = k
    depth = np.where(np.isfinite(best), best, 0.0)  # t along d_cam (z = 1) is the z-depth
    return depth.astype(np.float32), idx


def world_points(T_world_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
    v, u = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    pc = np.stack([(u - INTR.cx) / INTR.fx * depth, (v - INTR.cy) / INTR.fy * depth, depth], -1)
    return transform_points(T_world_cam, pc).astype(np.float32)


BOXES = [
    (np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.8, 0.75])),  # table
    (np.array([0.4, 0.2, 0.75]), np.array([0.75, 0.55, 1.0])),  # basket on the table
    (np.array([1.35, 0.1, 0.0]), np.array([1.8, 0.55, 0.9])),  # chair beside it
]
LABELS = {1: "table", 2: "basket", 3: "chair"}


def view(eye, seq: int, source: str = "robot1", posed: bool = True) -> View:
    T = look_at(eye, [0.7, 0.3, 0.5])
    depth, idx = raycast(T, BOXES)
    rgb = np.full((INTR.height, INTR.width, 3), 90, np.uint8)
    rgb[idx >= 0] = (np.array([[200, 40, 40], [40, 200, 40], [40, 40, 200]])[idx[idx >= 0]]).astype(np.uint8)
    oracle = OracleData(depth_m=depth, T_world_cam_true=T, instance_id=(idx + 1).astype(np.int32), labels=LABELS)
    return View(
        image=rgb, source_id=source, intrinsics=INTR, T_world_cam=T if posed else None,
        stamp_ns=seq * 1000, seq=seq, oracle=oracle,
    )


def oracle_core(**fusion) -> MapperCore:
    cfg = MapperCoreConfig(
        geometry=GeometryConfig(backend="oracle"),
        perception=PerceptionConfig(segmenter="sim", embedder="sim"),
    )
    cfg.fusion = cfg.fusion.model_copy(update=fusion)
    return MapperCore(cfg)


EYES = [[0.6, -2.0, 1.6], [1.6, -1.8, 1.5], [-0.6, -1.5, 1.7], [2.4, -0.8, 1.5]]


TABLE, BASKET, CHAIR = BOXES
SHIFTED = (BASKET[0] + [0.0, -0.6, -0.75], BASKET[1] + [0.0, -0.6, -0.75])  # a basket on the floor, 0.6 m off


def scene_view(eye: list[float], seq: int, boxes: dict[str, tuple[np.ndarray, np.ndarray]]) -> View:
    """A posed view (ORACLE depth and instances) of ``boxes`` (label -> (min corner, max corner))."""
    T = look_at(eye, [0.7, 0.3, 0.5])
    depth, idx = raycast(T, list(boxes.values()))
    rgb = np.full((INTR.height, INTR.width, 3), 90, np.uint8)
    rgb[idx >= 0] = (40 + 50 * idx[idx >= 0, None]).astype(np.uint8)
    labels = {i + 1: lab for i, lab in enumerate(boxes)}
    oracle = OracleData(depth_m=depth, T_world_cam_true=T, instance_id=(idx + 1).astype(np.int32), labels=labels)
    return View(image=rgb, source_id="robot1", intrinsics=INTR, T_world_cam=T, stamp_ns=seq * 1000, seq=seq,
                oracle=oracle)


