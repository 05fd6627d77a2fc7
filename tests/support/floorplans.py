"""Generated floor plans as map points (floor and wall faces on a voxel-like lattice) and object nodes in them:
the room layer's test data (tests/mapper/test_rooms.py, tests/bench/test_rooms_eval.py)."""

from __future__ import annotations

import numpy as np

from protocol.messages import GraphNode, OrientedBox

STEP = 0.08


def floor_points(x0: float, y0: float, x1: float, y1: float, z: float = 0.0) -> np.ndarray:
    xs, ys = np.arange(x0 + STEP / 2, x1, STEP), np.arange(y0 + STEP / 2, y1, STEP)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)


def wall_points(a: tuple[float, float], b: tuple[float, float], gaps: tuple[tuple[float, float], ...] = (),
          z: float = 0.0, height: float = 2.5) -> np.ndarray:
    """Points on a wall face from ``a`` to ``b`` (axis-aligned), minus doorway ``gaps`` (along-wall intervals)."""
    (ax, ay), (bx, by) = a, b
    n = max(2, int(np.hypot(bx - ax, by - ay) / STEP))
    t = np.linspace(0.0, 1.0, n)
    along = np.where(ax == bx, ay + t * (by - ay), ax + t * (bx - ax))
    keep = np.ones(n, bool)
    for lo, hi in gaps:
        keep &= ~((along >= lo) & (along <= hi))
    xy = np.stack([ax + t * (bx - ax), ay + t * (by - ay)], 1)[keep]
    zs = np.arange(z, z + height, STEP)
    return np.array([[x, y, zz] for x, y in xy for zz in zs]).reshape(-1, 3)


def two_rooms(door: tuple[float, float] | None = (1.5, 2.4), wall: bool = True, right_to_x: float = 8.0,
              floor_under_wall: bool = True) -> np.ndarray:
    """An 8 x 4 m plan split at x = 4 by a wall with a doorway (``door``: y interval) into two rooms; the right
    room seen up to ``right_to_x``; ``floor_under_wall``: the floor along the wall line observed (the wall gone)."""
    parts = [floor_points(0.0, 0.0, 4.0, 4.0), floor_points(4.1, 0.0, right_to_x, 4.0),
             wall_points((0.0, 0.0), (right_to_x, 0.0)), wall_points((0.0, 4.0), (right_to_x, 4.0)),
             wall_points((0.0, 0.0), (0.0, 4.0))]
    if right_to_x >= 8.0:
        parts.append(wall_points((8.0, 0.0), (8.0, 4.0)))
    if wall:
        parts.append(wall_points((4.05, 0.0), (4.05, 4.0), gaps=(door,) if door else ()))
    if floor_under_wall:
        parts.append(floor_points(3.95, 0.0, 4.15, 4.0))
    return np.concatenate(parts)


def node(nid: str, label: str, x: float, y: float, size: float = 0.6) -> GraphNode:
    return GraphNode(node_id=nid, label=label, label_confidence=0.9, centroid=(x, y, size / 2),
                     box=OrientedBox(center=(x, y, size / 2), extent=(size, size, size)), point_count=10,
                     observation_count=1, first_seen_ns=0, last_seen_ns=0)


NODES = [node("a", "bed", 1.5, 2.0, 1.2), node("b", "nightstand", 0.6, 3.3, 0.4),
         node("c", "refrigerator", 7.3, 3.4), node("d", "stove", 6.0, 0.5)]
