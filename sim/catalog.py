"""Object categories of the embedded world, built from trimesh primitives with believable proportions.

Each builder takes a numpy ``Generator`` and returns a :class:`Model` in its local frame: origin at the
centre of the footprint on the supporting plane (z = 0 is the bottom), front facing local +y, plus the
support surfaces other objects may stand on ("on", a top face) or in ("in", a shelf or a container's
floor). Pure geometry, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh

Rng = np.random.Generator


@dataclass(frozen=True)
class Surface:
    """A horizontal rectangle (local frame) objects can stand on (``kind='on'``) or in (``'in'``)."""

    x0: float
    y0: float
    x1: float
    y1: float
    z: float
    kind: str = "on"
    clear_m: float = 0.6


@dataclass
class Model:
    """Parts (local-frame closed meshes with a material kind each) and support surfaces."""

    parts: list[tuple[trimesh.Trimesh, str]] = field(default_factory=list)
    surfaces: list[Surface] = field(default_factory=list)
    _bounds: np.ndarray | None = None

    def add(self, mesh: trimesh.Trimesh, kind: str) -> Model:
        self.parts.append((mesh, kind))
        self._bounds = None
        return self

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) local axis-aligned bounds of all parts."""
        if self._bounds is None:
            v = np.vstack([np.asarray(m.vertices) for m, _ in self.parts])
            self._bounds = np.stack([v.min(axis=0), v.max(axis=0)])
        return self._bounds


@dataclass(frozen=True)
class Category:
    key: str
    label: str
    build: Callable[[Rng], Model]
    large: bool  # furniture standing on the floor (an obstacle) vs a small item on a surface


# ---------------------------------------------------------------------------------------------
# Primitive helpers: all take the bottom-centre position (x, y, z) of the primitive.


_BOX_V = np.array([[-1, -1, -1], [-1, -1, 1], [-1, 1, -1], [-1, 1, 1], [1, -1, -1], [1, -1, 1], [1, 1, -1], [1, 1, 1]],
                  dtype=np.float64) * 0.5
_BOX_F = np.array([[1, 3, 0], [4, 1, 0], [0, 3, 2], [2, 4, 0], [1, 7, 3], [5, 1, 4], [5, 7, 1], [3, 7, 2], [6, 4, 2],
                   [2, 7, 6], [6, 5, 4], [7, 5, 6]], dtype=np.int64)


def box(ex: float, ey: float, ez: float, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> trimesh.Trimesh:
    """Axis-aligned closed box (outward normals) with its bottom centre at (x, y, z)."""
    v = _BOX_V * np.array([ex, ey, ez]) + np.array([x, y, z + ez / 2.0])
    return trimesh.Trimesh(vertices=v, faces=_BOX_F.copy(), process=False)


def _ring(n: int) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def cyl(r: float, h: float, x: float = 0.0, y: float = 0.0, z: float = 0.0, sections: int = 20) -> trimesh.Trimesh:
    """Closed vertical cylinder with its bottom centre at (x, y, z)."""
    n = sections
    ring = _ring(n) * r
    v = np.zeros((2 * n + 2, 3))
    v[:n, :2], v[n:2 * n, :2] = ring, ring
    v[n:2 * n, 2] = h
    v[2 * n + 1, 2] = h
    i = np.arange(n)
    j = (i + 1) % n
    b, t = 2 * n, 2 * n + 1
    faces = np.concatenate([
        np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1),  # side
        np.stack([np.full(n, b), j, i], 1),  # bottom (facing down)
        np.stack([np.full(n, t), n + i, n + j], 1),  # top
    ])
    v += (x, y, z)
    return trimesh.Trimesh(vertices=v, faces=faces, process=False)


def tube(r_out: float, r_in: float, h: float, x: float = 0.0, y: float = 0.0, z: float = 0.0,
         sections: int = 20) -> trimesh.Trimesh:
    """Closed vertical tube (annulus) with its bottom centre at (x, y, z)."""
    n = sections
    ring = _ring(n)
    v = np.zeros((4 * n, 3))
    v[:n, :2], v[n:2 * n, :2] = ring * r_out, ring * r_out  # outer bottom, outer top
    v[2 * n:3 * n, :2], v[3 * n:, :2] = ring * r_in, ring * r_in  # inner bottom, inner top
    v[n:2 * n, 2] = h
    v[3 * n:, 2] = h
    i = np.arange(n)
    j = (i + 1) % n
    ob, ot, ib, it = 0, n, 2 * n, 3 * n
    faces = np.concatenate([
        np.stack([ob + i, ob + j, ot + j], 1), np.stack([ob + i, ot + j, ot + i], 1),  # outer side
        np.stack([ib + j, ib + i, it + i], 1), np.stack([ib + j, it + i, it + j], 1),  # inner side
        np.stack([ot + i, ot + j, it + j], 1), np.stack([ot + i, it + j, it + i], 1),  # top
        np.stack([ob + j, ob + i, ib + i], 1), np.stack([ob + j, ib + i, ib + j], 1),  # bottom
    ])
    v += (x, y, z)
    return trimesh.Trimesh(vertices=v, faces=faces, process=False)


def concat(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """Concatenate meshes without merging vertices (each part stays a closed component)."""
    if len(meshes) == 1:
        return meshes[0]
    vs, fs, off = [], [], 0
    for m in meshes:
        v = np.asarray(m.vertices)
        vs.append(v)
        fs.append(np.asarray(m.faces) + off)
        off += len(v)
    return trimesh.Trimesh(vertices=np.vstack(vs), faces=np.vstack(fs), process=False)


def ball(r: float, x: float = 0.0, y: float = 0.0, z: float = 0.0, subdiv: int = 2) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdiv, radius=r)
    m.apply_translation((x, y, z + r))
    return m


def tilted_box(ex: float, ey: float, ez: float, angle_x_rad: float, hinge: tuple[float, float, float]
               ) -> trimesh.Trimesh:
    """A box whose bottom-back edge sits at ``hinge``, rotated about the x axis (leaning back if > 0)."""
    m = trimesh.creation.box(extents=(ex, ey, ez))
    m.apply_translation((0.0, ey / 2.0, ez / 2.0))
    R = trimesh.transformations.rotation_matrix(angle_x_rad, (1.0, 0.0, 0.0))
    m.apply_transform(R)
    m.apply_translation(hinge)
    return m


def legs4(m: Model, w: float, d: float, h: float, t: float, kind: str, inset: float = 0.03) -> None:
    for sx in (-1, 1):
        for sy in (-1, 1):
            m.add(box(t, t, h, sx * (w / 2 - inset - t / 2), sy * (d / 2 - inset - t / 2), 0.0), kind)


def top_surface(w: float, d: float, z: float, margin: float = 0.04, clear: float = 1.2) -> Surface:
    return Surface(-w / 2 + margin, -d / 2 + margin, w / 2 - margin, d / 2 - margin, z, "on", clear)


# ---------------------------------------------------------------------------------------------
# Furniture.


def sofa(r: Rng) -> Model:
    w, d = r.uniform(1.8, 2.3), r.uniform(0.85, 0.95)
    m = Model()
    leg = 0.08
    legs4(m, w, d, leg, 0.05, "wood_dark", 0.06)
    arm = 0.18
    m.add(box(w, d, 0.22, 0, 0, leg), "fabric")  # base frame
    m.add(box(w - 2 * arm, d - 0.22, 0.14, 0, 0.11, leg + 0.22), "fabric")  # seat cushions
    m.add(box(w, 0.22, 0.55, 0, -d / 2 + 0.11, leg + 0.22), "fabric")  # back
    for sx in (-1, 1):
        m.add(box(arm, d - 0.22, 0.28, sx * (w / 2 - arm / 2), 0.11, leg + 0.22), "fabric")
    z = leg + 0.36
    m.surfaces.append(Surface(-w / 2 + arm + 0.05, -d / 2 + 0.25, w / 2 - arm - 0.05, d / 2 - 0.08, z, "on", 0.5))
    return m


def armchair(r: Rng) -> Model:
    w, d = r.uniform(0.75, 0.9), r.uniform(0.78, 0.88)
    m = Model()
    leg = 0.1
    legs4(m, w, d, leg, 0.04, "wood_dark", 0.05)
    arm = 0.15
    m.add(box(w, d, 0.2, 0, 0, leg), "fabric")
    m.add(box(w - 2 * arm, d - 0.2, 0.12, 0, 0.1, leg + 0.2), "fabric")
    m.add(box(w, 0.2, 0.55, 0, -d / 2 + 0.1, leg + 0.2), "fabric")
    for sx in (-1, 1):
        m.add(box(arm, d - 0.2, 0.3, sx * (w / 2 - arm / 2), 0.1, leg + 0.2), "fabric")
    m.surfaces.append(Surface(-w / 2 + arm + 0.04, -d / 2 + 0.24, w / 2 - arm - 0.04, d / 2 - 0.06,
                              leg + 0.32, "on", 0.5))
    return m


def table(w: float, d: float, h: float, top_t: float, leg_t: float, top_kind: str, leg_kind: str,
          shelf: bool = False) -> Model:
    m = Model()
    legs4(m, w, d, h - top_t, leg_t, leg_kind)
    m.add(box(w, d, top_t, 0, 0, h - top_t), top_kind)
    m.surfaces.append(top_surface(w, d, h))
    if shelf:
        m.add(box(w - 0.08 - 2 * leg_t, d - 0.08 - 2 * leg_t, 0.02, 0, 0, 0.12), leg_kind)
    return m


def coffee_table(r: Rng) -> Model:
    return table(r.uniform(0.9, 1.2), r.uniform(0.5, 0.65), r.uniform(0.38, 0.45), 0.04, 0.05,
                 "wood", "wood", shelf=bool(r.random() < 0.5))


def side_table(r: Rng) -> Model:
    s = r.uniform(0.4, 0.5)
    return table(s, s, r.uniform(0.5, 0.6), 0.03, 0.035, "wood", "wood_dark")


def dining_table(r: Rng) -> Model:
    return table(r.uniform(1.4, 1.8), r.uniform(0.8, 0.95), 0.75, 0.04, 0.07, "wood", "wood")


def desk(r: Rng) -> Model:
    w, d, h = r.uniform(1.2, 1.6), r.uniform(0.6, 0.72), 0.75
    m = Model()
    t = 0.03
    m.add(box(w, d, t, 0, 0, h - t), "wood")
    m.add(box(0.03, d - 0.04, h - t, -w / 2 + 0.035, 0, 0), "wood_dark")  # side panel
    m.add(box(0.4, d - 0.06, h - t - 0.02, w / 2 - 0.22, 0.0, 0.0), "wood_dark")  # drawer unit
    for k in range(3):
        m.add(box(0.34, 0.012, 0.18, w / 2 - 0.22, d / 2 - 0.024, 0.06 + k * 0.22), "plastic")
    m.add(box(w - 0.5, 0.02, 0.35, -0.16, -d / 2 + 0.04, h - t - 0.35), "wood_dark")  # modesty panel
    m.surfaces.append(top_surface(w, d, h))
    return m


def dining_chair(r: Rng) -> Model:
    s, hs = r.uniform(0.42, 0.48), 0.45
    m = Model()
    legs4(m, s, s, hs - 0.04, 0.035, "wood", 0.01)
    m.add(box(s, s, 0.04, 0, 0, hs - 0.04), "wood")
    m.add(box(s, 0.03, 0.45, 0, -s / 2 + 0.025, hs), "wood")
    m.surfaces.append(Surface(-s / 2 + 0.05, -s / 2 + 0.08, s / 2 - 0.05, s / 2 - 0.04, hs, "on", 0.4))
    return m


def chair(r: Rng) -> Model:
    m = dining_chair(r)
    return m


def bar_stool(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.2, 0.03, 0, 0, 0), "metal")
    m.add(cyl(0.025, 0.62, 0, 0, 0.03), "metal")
    m.add(cyl(r.uniform(0.17, 0.2), 0.06, 0, 0, 0.65), "leather")
    return m


def office_chair(r: Rng) -> Model:
    m = Model()
    for k in range(5):
        a = 2 * math.pi * k / 5
        b = box(0.3, 0.05, 0.04, 0.0, 0.0, 0.0)
        b.apply_translation((0.15, 0, 0))
        b.apply_transform(trimesh.transformations.rotation_matrix(a, (0, 0, 1)))
        m.add(b, "black")
    m.add(cyl(0.03, 0.4, 0, 0, 0.04), "metal")
    s = r.uniform(0.46, 0.52)
    m.add(box(s, s, 0.08, 0, 0, 0.44), "fabric")
    m.add(tilted_box(s - 0.04, 0.06, 0.55, 0.12, (0.0, -s / 2, 0.52)), "fabric")
    return m


def bookshelf(r: Rng) -> Model:
    w, d, h = r.uniform(0.8, 1.0), r.uniform(0.3, 0.36), r.uniform(1.75, 2.0)
    t = 0.02
    m = Model()
    m.add(box(t, d, h, -w / 2 + t / 2, 0, 0), "wood")
    m.add(box(t, d, h, w / 2 - t / 2, 0, 0), "wood")
    m.add(box(w - 2 * t, 0.01, h, 0, -d / 2 + 0.005, 0), "wood_dark")
    n = 5
    gap = (h - t) / n
    for k in range(n + 1):
        z = min(k * gap, h - t)
        m.add(box(w - 2 * t, d - 0.01, t, 0, 0.005, z), "wood")
    for k in range(n):
        z = k * gap + t
        m.surfaces.append(Surface(-w / 2 + t + 0.01, -d / 2 + 0.03, w / 2 - t - 0.01, d / 2 - 0.02, z, "in",
                                  gap - t - 0.01))
    return m


def tv_stand(r: Rng) -> Model:
    w, d, h = r.uniform(1.4, 1.8), r.uniform(0.38, 0.45), r.uniform(0.45, 0.55)
    m = Model()
    m.add(box(w, d, h - 0.06, 0, 0, 0.06), "wood")
    legs4(m, w, d, 0.06, 0.04, "metal")
    for sx in (-1, 1):
        m.add(box(w / 2 - 0.06, 0.012, h - 0.16, sx * w / 4, d / 2, 0.1), "wood_dark")
    m.surfaces.append(top_surface(w, d, h))
    return m


def kitchen_counter(r: Rng) -> Model:
    w, d, h = r.uniform(1.2, 2.2), 0.6, 0.9
    m = Model()
    m.add(box(w, d - 0.05, 0.1, 0, -0.025, 0), "black")  # toe kick
    m.add(box(w, d - 0.02, h - 0.14, 0, -0.01, 0.1), "wood")
    n = max(2, int(w / 0.5))
    for k in range(n):
        x = -w / 2 + (k + 0.5) * w / n
        m.add(box(w / n - 0.02, 0.01, h - 0.2, x, d / 2 - 0.015, 0.12), "white")
        m.add(box(0.1, 0.02, 0.015, x, d / 2 + 0.0, h - 0.2), "metal")  # handle
    m.add(box(w, d, 0.04, 0, 0, h - 0.04), "stone")
    m.surfaces.append(top_surface(w, d, h, 0.05))
    return m


def kitchen_sink(r: Rng) -> Model:
    w, d, h = r.uniform(1.0, 1.4), 0.6, 0.9
    bw, bd, bh = 0.5, 0.38, 0.2
    m = Model()
    m.add(box(w, d - 0.02, h - 0.04 - bh, 0, -0.01, 0), "wood")
    m.add(box(w - 0.02, 0.01, h - 0.3, 0, d / 2 - 0.015, 0.08), "white")
    top_z = h - 0.04
    # worktop around the basin hole
    side = (w - bw) / 2
    m.add(box(side, d, 0.04, -w / 2 + side / 2, 0, top_z), "stone")
    m.add(box(side, d, 0.04, w / 2 - side / 2, 0, top_z), "stone")
    m.add(box(bw, (d - bd) / 2, 0.04, 0, -d / 2 + (d - bd) / 4, top_z), "stone")
    m.add(box(bw, (d - bd) / 2, 0.04, 0, d / 2 - (d - bd) / 4, top_z), "stone")
    # basin: floor and four walls
    bz = h - bh
    m.add(box(bw, bd, 0.01, 0, 0, bz - 0.01), "metal")
    m.add(box(0.01, bd, bh - 0.04, -bw / 2 + 0.005, 0, bz), "metal")
    m.add(box(0.01, bd, bh - 0.04, bw / 2 - 0.005, 0, bz), "metal")
    m.add(box(bw - 0.02, 0.01, bh - 0.04, 0, -bd / 2 + 0.005, bz), "metal")
    m.add(box(bw - 0.02, 0.01, bh - 0.04, 0, bd / 2 - 0.005, bz), "metal")
    # faucet
    m.add(cyl(0.015, 0.3, 0, -d / 2 + 0.06, h), "metal")
    m.add(box(0.03, 0.18, 0.03, 0, -d / 2 + 0.14, h + 0.27), "metal")
    m.surfaces.append(Surface(-bw / 2 + 0.02, -bd / 2 + 0.02, bw / 2 - 0.02, bd / 2 - 0.02, bz, "in", 0.25))
    m.surfaces.append(Surface(w / 2 - side + 0.03, -d / 2 + 0.05, w / 2 - 0.04, d / 2 - 0.05, h, "on", 0.6))
    return m


def refrigerator(r: Rng) -> Model:
    w, d, h = r.uniform(0.6, 0.75), r.uniform(0.65, 0.72), r.uniform(1.75, 1.9)
    m = Model()
    m.add(box(w, d - 0.04, h, 0, -0.02, 0), "white")
    m.add(box(w - 0.01, 0.04, h * 0.3 - 0.01, 0, d / 2 - 0.02, h * 0.7), "white")
    m.add(box(w - 0.01, 0.04, h * 0.69, 0, d / 2 - 0.02, 0.0), "white")
    m.add(box(0.03, 0.04, 0.3, w / 2 - 0.06, d / 2 + 0.02, h * 0.45), "metal")
    m.add(box(0.03, 0.04, 0.2, w / 2 - 0.06, d / 2 + 0.02, h * 0.75), "metal")
    m.surfaces.append(top_surface(w, d - 0.04, h, 0.05, 0.3))
    return m


def stove(r: Rng) -> Model:
    w, d, h = 0.6, 0.6, 0.9
    m = Model()
    m.add(box(w, d - 0.02, h - 0.02, 0, -0.01, 0), "metal")
    m.add(box(w - 0.06, 0.01, 0.45, 0, d / 2 - 0.015, 0.15), "black")  # oven door
    m.add(box(w - 0.1, 0.03, 0.02, 0, d / 2 + 0.005, 0.62), "metal")
    m.add(box(w, d, 0.02, 0, 0, h - 0.02), "black")
    for sx in (-1, 1):
        for sy in (-1, 1):
            m.add(cyl(0.08, 0.004, sx * 0.14, sy * 0.14, h), "metal")
    m.surfaces.append(top_surface(w, d, h, 0.05))
    return m


def bed(r: Rng) -> Model:
    w, l = r.choice([1.4, 1.6, 1.8]) + r.uniform(-0.02, 0.02), r.uniform(2.0, 2.1)
    m = Model()
    m.add(box(w, l, 0.3, 0, 0, 0.0), "wood")  # frame
    m.add(box(w - 0.04, l - 0.08, 0.22, 0, 0.02, 0.3), "white")  # mattress
    m.add(box(w + 0.04, 0.06, 1.0, 0, -l / 2 + 0.03, 0), "wood_dark")  # headboard
    m.add(box(w - 0.02, l * 0.55, 0.04, 0, l / 2 - l * 0.275 - 0.02, 0.52), "fabric")  # duvet
    m.surfaces.append(Surface(-w / 2 + 0.08, -l / 2 + 0.12, w / 2 - 0.08, -l / 2 + 0.7, 0.52, "on", 0.4))
    return m


def nightstand(r: Rng) -> Model:
    w, d, h = r.uniform(0.4, 0.5), r.uniform(0.35, 0.42), r.uniform(0.5, 0.6)
    m = Model()
    m.add(box(w, d, h, 0, 0, 0), "wood")
    for k in range(2):
        m.add(box(w - 0.04, 0.012, h / 2 - 0.05, 0, d / 2, 0.04 + k * h / 2), "wood_dark")
    m.surfaces.append(top_surface(w, d, h, 0.03))
    return m


def wardrobe(r: Rng) -> Model:
    w, d, h = r.uniform(1.0, 1.6), r.uniform(0.55, 0.62), r.uniform(1.9, 2.1)
    m = Model()
    m.add(box(w, d - 0.02, h, 0, -0.01, 0), "wood")
    for sx in (-1, 1):
        m.add(box(w / 2 - 0.02, 0.012, h - 0.08, sx * w / 4, d / 2 - 0.01, 0.04), "wood_dark")
        m.add(box(0.02, 0.03, 0.3, sx * 0.05, d / 2 + 0.01, h * 0.5), "metal")
    return m


def dresser(r: Rng) -> Model:
    w, d, h = r.uniform(0.9, 1.2), r.uniform(0.45, 0.52), r.uniform(0.75, 0.9)
    m = Model()
    m.add(box(w, d - 0.01, h, 0, -0.005, 0), "wood")
    for k in range(3):
        m.add(box(w - 0.05, 0.012, h / 3 - 0.05, 0, d / 2 - 0.005, 0.03 + k * h / 3), "wood_dark")
        m.add(box(0.12, 0.02, 0.02, 0, d / 2 + 0.005, (k + 0.6) * h / 3), "metal")
    m.surfaces.append(top_surface(w, d, h, 0.04))
    return m


def filing_cabinet(r: Rng) -> Model:
    w, d, h = 0.45, 0.6, r.uniform(0.65, 0.75)
    m = Model()
    m.add(box(w, d - 0.01, h, 0, -0.005, 0), "metal")
    for k in range(3):
        m.add(box(w - 0.04, 0.012, h / 3 - 0.03, 0, d / 2 - 0.005, 0.015 + k * h / 3), "metal")
        m.add(box(0.1, 0.02, 0.02, 0, d / 2 + 0.005, (k + 0.7) * h / 3), "black")
    m.surfaces.append(top_surface(w, d, h, 0.03))
    return m


def toilet(r: Rng) -> Model:
    m = Model()
    m.add(box(0.22, 0.35, 0.38, 0, 0.05, 0), "white")  # pedestal
    m.add(cyl(0.2, 0.05, 0, 0.12, 0.38), "white")  # seat
    m.add(box(0.42, 0.18, 0.4, 0, -0.24, 0.38), "white")  # tank
    m.surfaces.append(Surface(-0.18, -0.325, 0.18, -0.155, 0.78, "on", 0.4))
    return m


def bathtub(r: Rng) -> Model:
    w, d, h = r.uniform(1.5, 1.7), r.uniform(0.7, 0.8), r.uniform(0.5, 0.58)
    t = 0.07
    m = Model()
    m.add(box(w, d, 0.06, 0, 0, 0), "white")
    m.add(box(t, d, h - 0.06, -w / 2 + t / 2, 0, 0.06), "white")
    m.add(box(t, d, h - 0.06, w / 2 - t / 2, 0, 0.06), "white")
    m.add(box(w - 2 * t, t, h - 0.06, 0, -d / 2 + t / 2, 0.06), "white")
    m.add(box(w - 2 * t, t, h - 0.06, 0, d / 2 - t / 2, 0.06), "white")
    m.add(cyl(0.015, 0.15, -w / 2 + 0.035, 0, h), "metal")
    m.surfaces.append(Surface(-w / 2 + t + 0.04, -d / 2 + t + 0.03, w / 2 - t - 0.03, d / 2 - t - 0.03, 0.06,
                              "in", h - 0.1))
    return m


def bathroom_sink(r: Rng) -> Model:
    w, d, h = r.uniform(0.7, 0.9), r.uniform(0.45, 0.52), 0.85
    m = Model()
    m.add(box(w, d - 0.02, h - 0.04, 0, -0.01, 0), "wood")
    m.add(box(w - 0.04, 0.012, h - 0.2, 0, d / 2 - 0.01, 0.1), "white")
    m.add(box(w, d, 0.04, 0, 0, h - 0.04), "ceramic")
    m.add(tube(0.2, 0.17, 0.1, 0, 0.02, h), "ceramic")  # basin rim above the top
    m.add(cyl(0.17, 0.01, 0, 0.02, h), "ceramic")
    m.add(cyl(0.015, 0.22, 0, -d / 2 + 0.05, h), "metal")
    m.add(box(0.025, 0.12, 0.025, 0, -d / 2 + 0.1, h + 0.2), "metal")
    m.surfaces.append(Surface(-w / 2 + 0.03, -d / 2 + 0.03, -0.22, d / 2 - 0.03, h, "on", 0.5))
    m.surfaces.append(Surface(0.22, -d / 2 + 0.03, w / 2 - 0.03, d / 2 - 0.03, h, "on", 0.5))
    return m


def floor_lamp(r: Rng) -> Model:
    h = r.uniform(1.5, 1.75)
    m = Model()
    m.add(cyl(0.15, 0.03, 0, 0, 0), "metal")
    m.add(cyl(0.015, h - 0.33, 0, 0, 0.03), "metal")
    m.add(tube(0.2, 0.19, 0.3, 0, 0, h - 0.3), "white")
    return m


def potted_plant(r: Rng) -> Model:
    pr, ph = r.uniform(0.14, 0.22), r.uniform(0.25, 0.4)
    m = Model()
    m.add(cyl(pr, ph, 0, 0, 0), "terracotta")
    fol = r.uniform(0.3, 0.45)
    m.add(ball(fol, 0, 0, ph - 0.02, 2), "plant")
    m.add(ball(fol * 0.7, 0.05, -0.03, ph + fol * 1.3, 2), "plant")
    return m


def rug(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(1.6, 2.4), r.uniform(1.2, 1.7), 0.006, 0, 0, 0), "carpet")
    return m


def bath_mat(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(0.6, 0.8), r.uniform(0.4, 0.5), 0.008, 0, 0, 0), "carpet")
    return m


def trash_can(r: Rng) -> Model:
    rad, h = r.uniform(0.13, 0.18), r.uniform(0.35, 0.55)
    m = Model()
    m.add(cyl(rad, h, 0, 0, 0), "plastic")
    m.add(cyl(rad + 0.01, 0.03, 0, 0, h), "black")
    return m


def laundry_basket(r: Rng) -> Model:
    rad, h = r.uniform(0.2, 0.25), r.uniform(0.4, 0.5)
    m = Model()
    m.add(cyl(rad, 0.02, 0, 0, 0), "plastic")
    m.add(tube(rad, rad - 0.015, h - 0.02, 0, 0, 0.02), "plastic")
    s = (rad - 0.03) / math.sqrt(2)
    m.surfaces.append(Surface(-s, -s, s, s, 0.02, "in", h - 0.04))
    return m


def kitchen_island(r: Rng) -> Model:
    w, d, h = r.uniform(1.2, 1.6), r.uniform(0.7, 0.9), 0.92
    m = Model()
    m.add(box(w - 0.1, d - 0.25, h - 0.04, 0, -0.1, 0), "wood")
    m.add(box(w, d, 0.04, 0, 0, h - 0.04), "stone")
    m.surfaces.append(top_surface(w, d, h, 0.05))
    return m


# ---------------------------------------------------------------------------------------------
# Small items (stand on a surface).


def television(r: Rng) -> Model:
    w = r.uniform(0.9, 1.3)
    h = w * 0.58
    m = Model()
    m.add(box(0.3, 0.2, 0.02, 0, 0, 0), "black")
    m.add(box(0.06, 0.04, 0.08, 0, 0, 0.02), "black")
    m.add(box(w, 0.05, h, 0, 0, 0.08), "black")
    m.add(box(w - 0.04, 0.005, h - 0.04, 0, 0.0275, 0.1), "screen")
    return m


def monitor(r: Rng) -> Model:
    w = r.uniform(0.5, 0.65)
    h = w * 0.6
    m = Model()
    m.add(box(0.22, 0.16, 0.015, 0, 0, 0), "black")
    m.add(box(0.04, 0.03, 0.12, 0, -0.02, 0.015), "black")
    m.add(box(w, 0.03, h, 0, 0, 0.1), "black")
    m.add(box(w - 0.03, 0.004, h - 0.03, 0, 0.017, 0.115), "screen")
    return m


def laptop(r: Rng) -> Model:
    w, d = r.uniform(0.3, 0.36), r.uniform(0.21, 0.24)
    m = Model()
    m.add(box(w, d, 0.018, 0, 0, 0), "metal")
    m.add(box(w - 0.04, d * 0.5, 0.002, 0, 0.03, 0.018), "black")  # keys
    m.add(tilted_box(w, 0.008, d * 0.98, 0.25, (0.0, -d / 2, 0.018)), "metal")
    return m


def keyboard(r: Rng) -> Model:
    m = Model()
    w = r.uniform(0.38, 0.45)
    m.add(box(w, 0.14, 0.018, 0, 0, 0), "black")
    m.add(box(w - 0.03, 0.11, 0.008, 0, 0, 0.018), "plastic")
    return m


def computer_mouse(r: Rng) -> Model:
    m = Model()
    m.add(box(0.06, 0.1, 0.025, 0, 0, 0), "black")
    m.add(box(0.05, 0.07, 0.01, 0, -0.005, 0.025), "plastic")
    return m


def desk_lamp(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.08, 0.025, 0, 0, 0), "metal")
    m.add(cyl(0.012, 0.35, 0, 0, 0.025), "metal")
    m.add(box(0.03, 0.25, 0.03, 0, 0.11, 0.36), "metal")
    m.add(cyl(0.06, 0.09, 0, 0.24, 0.28), "accent")
    return m


def table_lamp(r: Rng) -> Model:
    h = r.uniform(0.35, 0.5)
    rad = r.uniform(0.12, 0.17)
    m = Model()
    m.add(cyl(0.07, 0.04, 0, 0, 0), "ceramic")
    m.add(cyl(0.012, h - 0.2, 0, 0, 0.04), "metal")
    m.add(tube(rad, rad - 0.008, 0.2, 0, 0, h - 0.2), "fabric")
    return m


def book(r: Rng, standing: bool | None = None) -> Model:
    t, w, h = r.uniform(0.02, 0.05), r.uniform(0.13, 0.2), r.uniform(0.18, 0.28)
    m = Model()
    if standing is None:
        standing = False
    if standing:
        m.add(box(t, w, h, 0, 0, 0), "paper")
    else:
        m.add(box(w, h, t, 0, 0, 0), "paper")
    return m


def standing_book(r: Rng) -> Model:
    return book(r, standing=True)


def notebook(r: Rng) -> Model:
    m = Model()
    m.add(box(0.15, 0.21, 0.012, 0, 0, 0), "paper")
    return m


def magazine(r: Rng) -> Model:
    m = Model()
    m.add(box(0.21, 0.28, 0.006, 0, 0, 0), "paper")
    return m


def cup(r: Rng) -> Model:
    rad, h = r.uniform(0.035, 0.045), r.uniform(0.09, 0.12)
    m = Model()
    m.add(cyl(rad, 0.01, 0, 0, 0), "ceramic")
    m.add(tube(rad, rad - 0.005, h - 0.01, 0, 0, 0.01), "ceramic")
    return m


def mug(r: Rng) -> Model:
    rad, h = r.uniform(0.04, 0.048), r.uniform(0.09, 0.11)
    m = Model()
    m.add(cyl(rad, 0.01, 0, 0, 0), "ceramic")
    m.add(tube(rad, rad - 0.006, h - 0.01, 0, 0, 0.01), "ceramic")
    m.add(box(0.012, 0.045, 0.06, rad + 0.006, 0, 0.025), "ceramic")
    return m


def wine_glass(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.035, 0.005, 0, 0, 0), "glass")
    m.add(cyl(0.005, 0.1, 0, 0, 0.005), "glass")
    m.add(tube(0.04, 0.036, 0.1, 0, 0, 0.105), "glass")
    return m


def bowl(r: Rng, rad: float | None = None) -> Model:
    rad = rad or r.uniform(0.07, 0.1)
    h = rad * 0.65
    m = Model()
    m.add(cyl(rad * 0.6, 0.012, 0, 0, 0), "ceramic")
    m.add(tube(rad, rad - 0.007, h - 0.012, 0, 0, 0.012), "ceramic")
    s = (rad - 0.012) / math.sqrt(2)
    m.surfaces.append(Surface(-s, -s, s, s, 0.012, "in", 0.3))
    return m


def fruit_bowl(r: Rng) -> Model:
    return bowl(r, r.uniform(0.12, 0.15))


def plate(r: Rng) -> Model:
    m = Model()
    m.add(cyl(r.uniform(0.1, 0.13), 0.018, 0, 0, 0, 24), "ceramic")
    return m


def bottle(r: Rng) -> Model:
    rad, h = r.uniform(0.03, 0.04), r.uniform(0.2, 0.28)
    m = Model()
    m.add(cyl(rad, h * 0.7, 0, 0, 0), "glass")
    m.add(cyl(rad * 0.6, h * 0.1, 0, 0, h * 0.7), "glass")
    m.add(cyl(0.013, h * 0.2, 0, 0, h * 0.8), "glass")
    return m


def wine_bottle(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.037, 0.21, 0, 0, 0), "black")
    m.add(cyl(0.025, 0.03, 0, 0, 0.21), "black")
    m.add(cyl(0.013, 0.08, 0, 0, 0.24), "black")
    m.add(box(0.05, 0.005, 0.07, 0, 0.0345, 0.07), "paper")
    return m


def kettle(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.09, 0.02, 0, 0, 0), "black")
    m.add(cyl(0.08, 0.18, 0, 0, 0.02), "metal")
    m.add(box(0.03, 0.03, 0.14, 0.1, 0, 0.05), "black")
    m.add(box(0.05, 0.03, 0.02, 0.075, 0, 0.19), "black")
    m.add(box(0.06, 0.02, 0.02, -0.1, 0, 0.15), "metal")
    return m


def toaster(r: Rng) -> Model:
    m = Model()
    m.add(box(0.28, 0.17, 0.19, 0, 0, 0), "metal")
    m.add(box(0.02, 0.03, 0.02, 0.15, 0, 0.14), "black")
    return m


def coffee_maker(r: Rng) -> Model:
    m = Model()
    m.add(box(0.2, 0.25, 0.03, 0, 0.02, 0), "black")
    m.add(box(0.2, 0.1, 0.35, 0, -0.09, 0), "black")
    m.add(box(0.2, 0.22, 0.06, 0, 0.03, 0.29), "black")
    m.add(cyl(0.06, 0.12, 0, 0.05, 0.03), "glass")
    return m


def microwave(r: Rng) -> Model:
    m = Model()
    m.add(box(0.48, 0.36, 0.28, 0, 0, 0), "white")
    m.add(box(0.3, 0.005, 0.2, -0.06, 0.18, 0.04), "black")
    m.add(box(0.1, 0.005, 0.2, 0.17, 0.18, 0.04), "plastic")
    return m


def cutting_board(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(0.35, 0.45), r.uniform(0.22, 0.28), 0.02, 0, 0, 0), "wood")
    return m


def cooking_pot(r: Rng) -> Model:
    rad = r.uniform(0.1, 0.13)
    m = Model()
    m.add(cyl(rad, 0.01, 0, 0, 0), "metal")
    m.add(tube(rad, rad - 0.005, 0.14, 0, 0, 0.01), "metal")
    m.add(cyl(rad + 0.005, 0.01, 0, 0, 0.15), "metal")
    m.add(cyl(0.02, 0.02, 0, 0, 0.16), "black")
    for sx in (-1, 1):
        m.add(box(0.04, 0.025, 0.015, sx * (rad + 0.02), 0, 0.11), "black")
    return m


def frying_pan(r: Rng) -> Model:
    rad = r.uniform(0.12, 0.14)
    m = Model()
    m.add(cyl(rad, 0.01, 0, 0, 0), "black")
    m.add(tube(rad, rad - 0.005, 0.04, 0, 0, 0.01), "black")
    m.add(box(0.13, 0.03, 0.015, rad + 0.065, 0, 0.035), "black")
    return m


def apple(r: Rng) -> Model:
    m = Model()
    m.add(ball(r.uniform(0.035, 0.042), 0, 0, 0, 2), "fruit_red")
    return m


def orange(r: Rng) -> Model:
    m = Model()
    m.add(ball(r.uniform(0.036, 0.042), 0, 0, 0, 2), "fruit_orange")
    return m


def vase(r: Rng) -> Model:
    rad, h = r.uniform(0.05, 0.08), r.uniform(0.2, 0.32)
    m = Model()
    m.add(cyl(rad, h * 0.75, 0, 0, 0), "ceramic")
    m.add(tube(rad * 0.7, rad * 0.55, h * 0.25, 0, 0, h * 0.75), "ceramic")
    return m


def candle(r: Rng) -> Model:
    m = Model()
    m.add(cyl(r.uniform(0.03, 0.04), r.uniform(0.07, 0.14), 0, 0, 0), "white")
    return m


def remote_control(r: Rng) -> Model:
    m = Model()
    m.add(box(0.05, 0.18, 0.02, 0, 0, 0), "black")
    m.add(box(0.03, 0.06, 0.004, 0, 0.03, 0.02), "plastic")
    return m


def picture_frame(r: Rng) -> Model:
    w, h = r.uniform(0.13, 0.22), r.uniform(0.18, 0.27)
    m = Model()
    m.add(box(w, 0.02, h, 0, 0, 0), "wood_dark")
    m.add(box(w - 0.03, 0.004, h - 0.03, 0, 0.011, 0.015), "paper")
    m.add(box(0.03, 0.1, 0.01, 0, -0.06, 0), "wood_dark")  # stand foot
    return m


def speaker(r: Rng) -> Model:
    w, h = r.uniform(0.14, 0.2), r.uniform(0.25, 0.35)
    m = Model()
    m.add(box(w, w * 1.1, h, 0, 0, 0), "wood_dark")
    m.add(cyl(w * 0.32, 0.01, 0, 0, 0).apply_transform(
        trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0))).apply_translation(
        (0, w * 0.55 + 0.005, h * 0.35)), "black")
    return m


def alarm_clock(r: Rng) -> Model:
    m = Model()
    m.add(box(0.13, 0.06, 0.08, 0, 0, 0), "plastic")
    m.add(box(0.1, 0.004, 0.05, 0, 0.031, 0.015), "screen")
    return m


def pillow(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(0.4, 0.55), r.uniform(0.3, 0.38), r.uniform(0.1, 0.14), 0, 0, 0), "accent")
    return m


def blanket(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(0.5, 0.7), r.uniform(0.35, 0.45), 0.06, 0, 0, 0), "fabric")
    return m


def towel(r: Rng) -> Model:
    m = Model()
    m.add(box(r.uniform(0.25, 0.32), r.uniform(0.18, 0.24), r.uniform(0.05, 0.08), 0, 0, 0), "fabric")
    return m


def soap_dispenser(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.035, 0.14, 0, 0, 0), "plastic")
    m.add(cyl(0.01, 0.03, 0, 0, 0.14), "white")
    m.add(box(0.05, 0.012, 0.012, 0.02, 0, 0.165), "white")
    return m


def toothbrush_holder(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.035, 0.1, 0, 0, 0), "ceramic")
    m.add(cyl(0.004, 0.1, 0.012, 0, 0.1), "plastic")
    m.add(cyl(0.004, 0.09, -0.012, 0.005, 0.1), "accent")
    return m


def toilet_paper(r: Rng) -> Model:
    m = Model()
    m.add(tube(0.06, 0.022, 0.1, 0, 0, 0), "white")
    return m


def shampoo_bottle(r: Rng) -> Model:
    m = Model()
    m.add(box(0.08, 0.05, r.uniform(0.17, 0.22), 0, 0, 0), "plastic")
    m.add(cyl(0.015, 0.03, 0, 0, 0.2), "white")
    return m


def pen_holder(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.04, 0.01, 0, 0, 0), "metal")
    m.add(tube(0.04, 0.036, 0.1, 0, 0, 0.01), "metal")
    for k in range(3):
        m.add(cyl(0.004, 0.14, 0.012 * math.cos(k * 2.1), 0.012 * math.sin(k * 2.1), 0.01), "accent")
    return m


def printer(r: Rng) -> Model:
    m = Model()
    m.add(box(0.36, 0.3, 0.15, 0, 0, 0), "black")
    m.add(box(0.26, 0.1, 0.01, 0, 0.08, 0.15), "plastic")
    m.add(box(0.24, 0.09, 0.005, 0, -0.08, 0.15), "white")
    return m


def storage_box(r: Rng) -> Model:
    w, d, h = r.uniform(0.22, 0.32), r.uniform(0.18, 0.26), r.uniform(0.12, 0.2)
    m = Model()
    m.add(box(w, d, h, 0, 0, 0), "paper")
    return m


def small_plant(r: Rng) -> Model:
    m = Model()
    rad = r.uniform(0.05, 0.07)
    m.add(cyl(rad, 0.08, 0, 0, 0), "terracotta")
    m.add(ball(rad * 1.4, 0, 0, 0.07, 1), "plant")
    return m


def backpack(r: Rng) -> Model:
    m = Model()
    m.add(box(0.3, 0.16, 0.4, 0, 0, 0), "accent")
    m.add(box(0.22, 0.06, 0.2, 0, 0.11, 0.05), "accent")
    return m


def globe(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.07, 0.02, 0, 0, 0), "wood_dark")
    m.add(cyl(0.01, 0.06, 0, 0, 0.02), "metal")
    m.add(ball(0.12, 0, 0, 0.06, 2), "plant")
    return m


def headphones(r: Rng) -> Model:
    m = Model()
    for sx in (-1, 1):
        m.add(box(0.06, 0.08, 0.03, sx * 0.07, 0, 0), "black")
    m.add(box(0.2, 0.03, 0.015, 0, 0, 0.03), "black")
    return m


def basket(r: Rng) -> Model:
    w, d = r.uniform(0.25, 0.35), r.uniform(0.18, 0.25)
    m = Model()
    m.add(box(w, d, 0.01, 0, 0, 0), "wood")
    for sx in (-1, 1):
        m.add(box(0.01, d, 0.12, sx * (w / 2 - 0.005), 0, 0.01), "wood")
    for sy in (-1, 1):
        m.add(box(w - 0.02, 0.01, 0.12, 0, sy * (d / 2 - 0.005), 0.01), "wood")
    m.surfaces.append(Surface(-w / 2 + 0.02, -d / 2 + 0.02, w / 2 - 0.02, d / 2 - 0.02, 0.01, "in", 0.3))
    return m


def tissue_box(r: Rng) -> Model:
    m = Model()
    m.add(box(0.22, 0.12, 0.09, 0, 0, 0), "paper")
    return m


def clock(r: Rng) -> Model:
    m = Model()
    m.add(cyl(0.1, 0.03, 0, 0, 0).apply_transform(
        trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0))).apply_translation((0, 0, 0.1)), "white")
    m.add(box(0.1, 0.05, 0.01, 0, 0, 0), "black")
    return m


_DEFS: list[tuple[str, Callable[[Rng], Model], bool]] = [
    # furniture (floor-standing)
    ("sofa", sofa, True), ("armchair", armchair, True), ("coffee table", coffee_table, True),
    ("side table", side_table, True), ("dining table", dining_table, True), ("desk", desk, True),
    ("dining chair", dining_chair, True), ("chair", chair, True), ("bar stool", bar_stool, True),
    ("office chair", office_chair, True), ("bookshelf", bookshelf, True), ("tv stand", tv_stand, True),
    ("kitchen counter", kitchen_counter, True), ("kitchen sink", kitchen_sink, True),
    ("refrigerator", refrigerator, True), ("stove", stove, True), ("bed", bed, True),
    ("nightstand", nightstand, True), ("wardrobe", wardrobe, True), ("dresser", dresser, True),
    ("filing cabinet", filing_cabinet, True), ("toilet", toilet, True), ("bathtub", bathtub, True),
    ("bathroom sink", bathroom_sink, True), ("floor lamp", floor_lamp, True),
    ("potted plant", potted_plant, True), ("rug", rug, True), ("bath mat", bath_mat, True),
    ("trash can", trash_can, True), ("laundry basket", laundry_basket, True),
    ("kitchen island", kitchen_island, True),
    # small items
    ("television", television, False), ("monitor", monitor, False), ("laptop", laptop, False),
    ("keyboard", keyboard, False), ("computer mouse", computer_mouse, False), ("desk lamp", desk_lamp, False),
    ("table lamp", table_lamp, False), ("book", book, False), ("standing book", standing_book, False),
    ("notebook", notebook, False), ("magazine", magazine, False), ("cup", cup, False), ("mug", mug, False),
    ("wine glass", wine_glass, False), ("bowl", bowl, False), ("fruit bowl", fruit_bowl, False),
    ("plate", plate, False), ("bottle", bottle, False), ("wine bottle", wine_bottle, False),
    ("kettle", kettle, False), ("toaster", toaster, False), ("coffee maker", coffee_maker, False),
    ("microwave", microwave, False), ("cutting board", cutting_board, False),
    ("cooking pot", cooking_pot, False), ("frying pan", frying_pan, False), ("apple", apple, False),
    ("orange", orange, False), ("vase", vase, False), ("candle", candle, False),
    ("remote control", remote_control, False), ("picture frame", picture_frame, False),
    ("speaker", speaker, False), ("alarm clock", alarm_clock, False), ("pillow", pillow, False),
    ("blanket", blanket, False), ("towel", towel, False), ("soap dispenser", soap_dispenser, False),
    ("toothbrush holder", toothbrush_holder, False), ("toilet paper", toilet_paper, False),
    ("shampoo bottle", shampoo_bottle, False), ("pen holder", pen_holder, False), ("printer", printer, False),
    ("storage box", storage_box, False), ("small plant", small_plant, False), ("backpack", backpack, False),
    ("globe", globe, False), ("headphones", headphones, False), ("basket", basket, False),
    ("tissue box", tissue_box, False), ("clock", clock, False),
]

CATEGORIES: dict[str, Category] = {}
for _label, _fn, _large in _DEFS:
    _key = _label.replace(" ", "_")
    CATEGORIES[_key] = Category(key=_key, label="book" if _key == "standing_book" else _label, build=_fn,
                                large=_large)
