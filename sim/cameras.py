"""Fixed infrastructure cameras: high in room corners, looking down into the room.

Each camera is placed in a room corner just below the ceiling and aimed at the room's interior; among
the corners the one that sees the most object centroids (checked by ray casting) wins, with the seed
breaking ties and choosing among near-best corners. The true pose is always known to the simulator;
``pose_known`` says whether Argus is given it (a surveyed camera) or must estimate it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.messages import Intrinsics
from protocol.poses import invert, look_at


@dataclass(frozen=True, eq=False)
class FixedCamera:
    """A fixed camera: id, intrinsics, TRUE pose, whether the pose is given to Argus, its room."""

    camera_id: str
    intrinsics: Intrinsics
    T_world_cam: np.ndarray
    pose_known: bool
    room: str


def visible_objects(scene: Any, renderer: Any, intrinsics: Intrinsics, T_world_cam: np.ndarray) -> list[int]:
    """Ids of objects whose centroid is in the image and not hidden behind other geometry."""
    T_cam_world = invert(T_world_cam)
    ids = []
    origin = T_world_cam[:3, 3]
    cents = np.array([o.centroid for o in scene.objects]) if scene.objects else np.zeros((0, 3))
    if len(cents) == 0:
        return []
    pc = cents @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    K = intrinsics
    with np.errstate(divide="ignore", invalid="ignore"):
        u = pc[:, 0] / pc[:, 2] * K.fx + K.cx
        v = pc[:, 1] / pc[:, 2] * K.fy + K.cy
    inview = (pc[:, 2] > 0.1) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
    idx = np.nonzero(inview)[0]
    if len(idx) == 0:
        return []
    dirs = cents[idx] - origin
    _, inst = renderer.cast(np.broadcast_to(origin, dirs.shape), dirs)
    for k, i in enumerate(idx):
        o = scene.objects[i]
        # the ray may hit the object itself or something it supports / holds (still "seen")
        if inst[k] == o.obj_id or (inst[k] > 0 and scene.object_by_id(int(inst[k])).parent_id == o.obj_id):
            ids.append(o.obj_id)
    return ids


def place_fixed_cameras(scene: Any, n: int, seed: int, intrinsics: Intrinsics | None = None,
                        pose_known: bool | Sequence[bool] = True, renderer: Any = None) -> list[FixedCamera]:
    """``n`` (1..3) cameras high in room corners: one per room in decreasing room size for apartments
    (living room first), distinct corners of the one room for a furnished room."""
    if not 1 <= int(n) <= 3:
        raise ValueError("n must be 1, 2 or 3")
    n = int(n)
    K = intrinsics or Intrinsics.from_fov(640, 480, 90.0)
    known = [bool(pose_known)] * n if isinstance(pose_known, bool) else [bool(v) for v in pose_known]
    if len(known) != n:
        raise ValueError("pose_known needs one flag per camera")
    if renderer is None:
        from sim.render import Renderer

        renderer = Renderer(scene)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xCA3])
    rooms = sorted(scene.rooms, key=lambda r: -r.area_m2)
    H = float(getattr(scene, "wall_height_m", 2.6))
    cams: list[FixedCamera] = []
    used: set[tuple[str, int]] = set()
    for i in range(n):
        room = rooms[i % len(rooms)]
        lo, hi = room.xy_min, room.xy_max
        corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
        centre = (lo + hi) / 2
        candidates = []
        for ci, c in enumerate(corners):
            if (room.name, ci) in used:
                continue
            corner = np.asarray(c, float)
            inward = (centre - corner) / max(np.linalg.norm(centre - corner), 1e-9)
            eye = np.array([*(corner + inward * 0.25), H - 0.2])
            jitter = rng.uniform(-0.3, 0.3, 2)
            target = np.array([*(centre + inward * 0.3 + jitter), 0.3])
            T = look_at(eye, target)
            score = len(visible_objects(scene, renderer, K, T)) + float(rng.uniform(0, 1.5))
            candidates.append((score, ci, T))
        candidates.sort(key=lambda s: -s[0])
        score, ci, T = candidates[0]
        used.add((room.name, ci))
        cams.append(FixedCamera(camera_id=f"cam{i}", intrinsics=K, T_world_cam=T, pose_known=known[i],
                                room=room.name))
    return cams
