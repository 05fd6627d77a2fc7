"""People in the embedded world: person-sized occluders that walk between rooms along the navigation graph.

A person is not furniture: never a ground-truth object, never an obstacle in the navigation map. They are drawn into
every frame (RGB, depth and the ORACLE semantic camera) through the renderer's overlay, with instance ids from
``PERSON_ID_BASE`` and the label ``"person"``, so a semantic camera can tell them from objects and a mapper can be
checked for not turning them into nodes, or into evidence that the objects they hide are gone.

Each person's walk is planned once, deterministic from a seed: from a free spot in one room along the shortest path
(:meth:`sim.nav.NavMap.path`) to a free spot in another room, a pause, the next room, and so on until the episode
ends. Example::

    nav = NavMap(scene)
    people = People(plan_walks(nav, n=2, duration_s=60.0, seed=0))
    frame = Renderer(scene).render(K, T_world_cam, overlay=people.layer(12.5))
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from sim.catalog import ball, concat, cyl
from sim.materials import Material, make_material

PERSON_LABEL = "person"
PERSON_ID_BASE = 10_000
"""Instance id of the first person (objects are numbered from 1 and stay far below)."""


@dataclass(frozen=True, eq=False)
class Walk:
    """One person's route: waypoint times ``times_s`` (K,) ascending and positions ``xy`` (K, 2); the person moves
    in a straight line between consecutive waypoints and stands at the first and last ones before and after."""

    person_id: int
    times_s: np.ndarray
    xy: np.ndarray

    def position(self, t_s: float) -> np.ndarray:
        """Where the person stands at ``t_s`` (xy, metres)."""
        ts = self.times_s
        if t_s <= ts[0]:
            return self.xy[0].copy()
        if t_s >= ts[-1]:
            return self.xy[-1].copy()
        i = int(np.searchsorted(ts, t_s, side="right")) - 1
        span = ts[i + 1] - ts[i]
        f = 0.0 if span <= 0 else (t_s - ts[i]) / span
        return self.xy[i] + f * (self.xy[i + 1] - self.xy[i])

    def heading(self, t_s: float) -> float:
        """The direction of travel at ``t_s`` (rad; the last one while standing)."""
        ts = self.times_s
        i = int(np.clip(np.searchsorted(ts, t_s, side="right") - 1, 0, len(ts) - 2)) if len(ts) > 1 else 0
        for k in range(i, -1, -1):
            d = self.xy[min(k + 1, len(self.xy) - 1)] - self.xy[k]
            if float(np.hypot(*d)) > 1e-9:
                return math.atan2(float(d[1]), float(d[0]))
        return 0.0


def plan_walks(nav: Any, n: int, duration_s: float, seed: int, speed_mps: float = 1.0,
               pause_s: tuple[float, float] = (1.0, 4.0)) -> list[Walk]:
    """``n`` walks over ``duration_s`` seconds in ``nav``'s scene: each person starts at a free spot of a random room
    and keeps walking to a free spot of another room (any room when the scene has one), pausing ``pause_s`` seconds
    (uniform) at each. Deterministic from ``seed``."""
    if n < 0 or duration_s < 0 or speed_mps <= 0:
        raise ValueError("n and duration_s must be >= 0 and speed_mps > 0")
    scene = nav.scene
    rooms = [r for r in scene.rooms if len(nav.room_cells(r))] or list(scene.rooms)
    cells = {r.name: nav.room_cells(r) for r in rooms}
    rooms = [r for r in rooms if len(cells[r.name])]
    if n and not rooms:
        raise ValueError("the scene has no free floor for people to walk on")
    walks = []
    for k in range(n):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, k, 0x9E0])
        room = rooms[int(rng.integers(len(rooms)))]
        at = cells[room.name][int(rng.integers(len(cells[room.name])))]
        times, pts = [0.0], [at]
        t = float(rng.uniform(0.0, pause_s[1]))
        for _ in range(1000):  # bounded: a walk that finds no path stands still
            if t >= duration_s:
                break
            others = [r for r in rooms if r.name != room.name] or rooms
            nxt = others[int(rng.integers(len(others)))]
            goal = cells[nxt.name][int(rng.integers(len(cells[nxt.name])))]
            path = nav.path((float(at[0]), float(at[1])), (float(goal[0]), float(goal[1])))
            if path is None or len(path) < 2:
                t += float(rng.uniform(*pause_s))
                continue
            times.append(t)
            pts.append(path[0])
            for a, b in zip(path[:-1], path[1:], strict=True):
                t += float(np.hypot(*(b - a))) / speed_mps
                times.append(t)
                pts.append(b)
            at, room = path[-1], nxt
            t += float(rng.uniform(*pause_s))
        walks.append(Walk(person_id=PERSON_ID_BASE + k, times_s=np.asarray(times, float),
                          xy=np.asarray(pts, float).reshape(-1, 2)))
    return walks


def person_mesh(height_m: float = 1.7, radius_m: float = 0.22) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A standing person in its local frame (feet at the origin, facing +x): legs, torso, arms and head; and each
    face's part (0 clothes, 1 skin)."""
    s = height_m / 1.7
    r = radius_m / 0.22
    clothes = [cyl(0.09 * r, 0.8 * s, 0.0, dy * 0.08 * r, 0.0, sections=8) for dy in (-1, 1)]  # legs that touch
    clothes.append(cyl(0.19 * r, 0.65 * s, 0.0, 0.0, 0.78 * s, sections=10))
    clothes += [cyl(0.05 * r, 0.6 * s, 0.0, dy * 0.24 * r, 0.8 * s, sections=6) for dy in (-1, 1)]
    body = concat(clothes)
    head = ball(0.11 * s, 0.0, 0.0, 1.48 * s, subdiv=1)
    mesh = concat([body, head])
    part = np.concatenate([np.zeros(len(body.faces), np.int32), np.ones(len(head.faces), np.int32)])
    return mesh, part


@dataclass(frozen=True, eq=False)
class PeopleLayer:
    """The people at one instant as the renderer's overlay (:class:`sim.render.Overlay`)."""

    caster: Any
    face_instance: np.ndarray
    face_normals: np.ndarray
    face_material: np.ndarray
    materials: list[Material]


@dataclass(eq=False)
class People:
    """Everyone walking through a scene: where each person is at a time, and the overlay that draws them."""

    walks: list[Walk]
    height_m: float = 1.7
    radius_m: float = 0.22
    seed: int = 0
    materials: list[Material] = field(init=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, 0x9E1])
        self.materials = []
        for _ in self.walks:  # clothes, then skin, per person
            self.materials.append(make_material(("fabric", "accent", "carpet")[int(rng.integers(3))], rng))
            self.materials.append(make_material("leather", rng))
        self._mesh, self._part = person_mesh(self.height_m, self.radius_m)
        self._last: tuple[tuple[float, str], PeopleLayer] | None = None

    @property
    def ids(self) -> list[int]:
        return [w.person_id for w in self.walks]

    def labels(self) -> dict[int, str]:
        """Instance id -> ``"person"``: what the ORACLE semantic camera reports for people."""
        return {w.person_id: PERSON_LABEL for w in self.walks}

    def positions(self, t_s: float) -> np.ndarray:
        """(N, 2) where each person stands at ``t_s``."""
        return np.array([w.position(t_s) for w in self.walks]).reshape(-1, 2)

    def layer(self, t_s: float, backend: str = "embree") -> PeopleLayer | None:
        """The renderer's overlay with everyone at ``t_s`` (None when nobody walks here)."""
        if not self.walks:
            return None
        if self._last is not None and self._last[0] == (t_s, backend):
            return self._last[1]  # every camera of one instant draws the same people
        from sim.render import BACKENDS

        v0 = np.asarray(self._mesh.vertices, np.float64)
        faces = np.asarray(self._mesh.faces)
        tris, inst, mats = [], [], []
        for k, w in enumerate(self.walks):
            xy, yaw = w.position(t_s), w.heading(t_s)
            c, s = math.cos(yaw), math.sin(yaw)
            v = v0 @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + np.array([xy[0], xy[1], 0.0])
            tris.append(v[faces])
            inst.append(np.full(len(faces), w.person_id, np.int32))
            mats.append(2 * k + self._part)
        triangles = np.concatenate(tris).astype(np.float32)
        e1 = (triangles[:, 1] - triangles[:, 0]).astype(np.float64)
        e2 = (triangles[:, 2] - triangles[:, 0]).astype(np.float64)
        n = np.cross(e1, e2)
        normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)).astype(np.float32)
        layer = PeopleLayer(caster=BACKENDS[backend](triangles), face_instance=np.concatenate(inst),
                            face_normals=normals, face_material=np.concatenate(mats).astype(np.int32),
                            materials=self.materials)
        self._last = ((t_s, backend), layer)
        return layer
