"""Navigation in the embedded world: occupancy grid of free floor, shortest paths, geodesic distances,
navigable viewpoints.

The grid is measured from the geometry itself (two vertical rays per cell), so it works the same for
generated scenes and for scenes loaded from glTF: a cell is free floor when the floor is the first thing
below the robot's height and nothing hangs lower than that height above it; rugs and mats (< 3 cm)
are floor. Obstacles are then inflated by the robot radius.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from protocol.messages import Intrinsics, Viewpoint, ViewpointSet

FLOOR_TOL_M = 0.03


@dataclass(frozen=True, eq=False)
class DistanceField:
    """Geodesic distances (metres) from one start over the nav grid; call it with (x, y)."""

    grid: np.ndarray  # (H, W) float64, inf where unreachable
    origin_xy: np.ndarray
    cell_m: float

    def __call__(self, x: float, y: float) -> float:
        i = int(math.floor((x - self.origin_xy[0]) / self.cell_m))
        j = int(math.floor((y - self.origin_xy[1]) / self.cell_m))
        if not (0 <= j < self.grid.shape[0] and 0 <= i < self.grid.shape[1]):
            return math.inf
        return float(self.grid[j, i])


class NavMap:
    """Free-floor occupancy grid of a scene with 8-connected shortest paths."""

    def __init__(self, scene: Any, robot_radius_m: float = 0.25, cell_m: float = 0.05,
                 body_height_m: float = 1.2, renderer: Any = None):
        if robot_radius_m < 0 or cell_m <= 0:
            raise ValueError("robot_radius_m must be >= 0 and cell_m > 0")
        from sim.render import Renderer

        self.scene = scene
        self.robot_radius_m = float(robot_radius_m)
        self.cell_m = float(cell_m)
        self.renderer = renderer if renderer is not None else Renderer(scene)
        lo = np.floor(np.asarray(scene.bounds_min[:2]) / cell_m) * cell_m
        hi = np.asarray(scene.bounds_max[:2])
        self.origin_xy = lo
        nx = int(math.ceil((hi[0] - lo[0]) / cell_m))
        ny = int(math.ceil((hi[1] - lo[1]) / cell_m))
        self.shape = (ny, nx)
        xs = lo[0] + (np.arange(nx) + 0.5) * cell_m
        ys = lo[1] + (np.arange(ny) + 0.5) * cell_m
        gx, gy = np.meshgrid(xs, ys)
        n = gx.size
        h = float(body_height_m)
        o_down = np.stack([gx.ravel(), gy.ravel(), np.full(n, h)], axis=1)
        o_up = np.stack([gx.ravel(), gy.ravel(), np.full(n, FLOOR_TOL_M)], axis=1)
        down = np.tile([0.0, 0.0, -1.0], (n, 1))
        up = np.tile([0.0, 0.0, 1.0], (n, 1))
        t_d, p_d = self.renderer.caster.cast(o_down, down)
        t_u, p_u = self.renderer.caster.cast(o_up, up)
        nz = self.renderer.face_normals[:, 2]
        hit_d = p_d >= 0
        z_d = np.where(hit_d, h - t_d, np.inf)
        inside_d = hit_d & (nz[np.maximum(p_d, 0)] < 0)  # a downward ray leaving a solid through its bottom
        hit_u = p_u >= 0
        low_ceiling = hit_u & (FLOOR_TOL_M + t_u < h)
        inside_u = hit_u & (nz[np.maximum(p_u, 0)] > 0)
        floor = hit_d & ~inside_d & (np.abs(z_d) <= FLOOR_TOL_M) & ~low_ceiling & ~inside_u
        self.floor = floor.reshape(self.shape)
        clearance = ndimage.distance_transform_edt(self.floor) * cell_m
        # a cell is free when every obstacle cell centre is farther than the radius (+ half a cell)
        self.free = self.floor & (clearance > self.robot_radius_m + 0.5 * cell_m)
        lab, _ = ndimage.label(self.free, structure=np.ones((3, 3)))
        self._labels = lab
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        self.main_component = int(np.argmax(sizes)) if len(sizes) > 1 else 0
        self._graph: csr_matrix | None = None
        self._index: np.ndarray | None = None
        self._cache: tuple[tuple[int, int], np.ndarray, np.ndarray] | None = None

    # -- grid helpers ---------------------------------------------------------------------------
    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row j, column i) of the cell containing (x, y) (may be outside the grid)."""
        return (int(math.floor((y - self.origin_xy[1]) / self.cell_m)),
                int(math.floor((x - self.origin_xy[0]) / self.cell_m)))

    def center_of(self, j: int, i: int) -> np.ndarray:
        return self.origin_xy + (np.array([i, j], float) + 0.5) * self.cell_m

    def _inside(self, j: int, i: int) -> bool:
        return 0 <= j < self.shape[0] and 0 <= i < self.shape[1]

    def is_free(self, x: float, y: float) -> bool:
        """Whether the robot (its radius included) can stand at (x, y)."""
        j, i = self.cell_of(x, y)
        return self._inside(j, i) and bool(self.free[j, i])

    def snap(self, x: float, y: float, max_dist_m: float = 0.5) -> tuple[int, int] | None:
        """Nearest free cell to (x, y) within ``max_dist_m``, or None."""
        j, i = self.cell_of(x, y)
        if self._inside(j, i) and self.free[j, i]:
            return j, i
        r = int(math.ceil(max_dist_m / self.cell_m))
        j0, j1 = max(j - r, 0), min(j + r + 1, self.shape[0])
        i0, i1 = max(i - r, 0), min(i + r + 1, self.shape[1])
        if j0 >= j1 or i0 >= i1:
            return None
        sub = self.free[j0:j1, i0:i1]
        jj, ii = np.nonzero(sub)
        if len(jj) == 0:
            return None
        d2 = (jj + j0 - j) ** 2 + (ii + i0 - i) ** 2
        k = int(np.argmin(d2))
        if math.sqrt(d2[k]) * self.cell_m > max_dist_m:
            return None
        return int(jj[k] + j0), int(ii[k] + i0)

    def _build_graph(self) -> None:
        ny, nx = self.shape
        idx = -np.ones(self.shape, np.int64)
        free_cells = np.nonzero(self.free.ravel())[0]
        idx.ravel()[free_cells] = np.arange(len(free_cells))
        rows, cols, w = [], [], []
        F = self.free
        for dj, di in ((0, 1), (1, 0), (1, 1), (1, -1)):
            b = F[max(0, dj):ny + min(0, dj), max(0, di):nx + min(0, di)]
            a = F[max(0, -dj):ny - max(0, dj), max(0, -di):nx - max(0, di)]
            ok = a & b
            if dj and di:  # no corner cutting
                o1 = F[max(0, -dj):ny - max(0, dj), max(0, di):nx + min(0, di)]
                o2 = F[max(0, dj):ny + min(0, dj), max(0, -di):nx - max(0, di)]
                ok &= o1 & o2
            jj, ii = np.nonzero(ok)
            ja, ia = jj + max(0, -dj), ii + max(0, -di)
            jb, ib = ja + dj, ia + di
            u, v = idx[ja, ia], idx[jb, ib]
            cost = self.cell_m * (math.sqrt(2.0) if dj and di else 1.0)
            rows += [u, v]
            cols += [v, u]
            w += [np.full(len(u), cost), np.full(len(u), cost)]
        n = len(free_cells)
        self._graph = csr_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
        self._index = idx

    def _dijkstra(self, cell: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        if self._cache is not None and self._cache[0] == cell:
            return self._cache[1], self._cache[2]
        if self._graph is None:
            self._build_graph()
        assert self._index is not None
        src = int(self._index[cell])
        dist, pred = dijkstra(self._graph, indices=src, return_predecessors=True)
        self._cache = (cell, dist, pred)
        return dist, pred

    # -- public queries -------------------------------------------------------------------------
    def distances_from(self, start_xy: tuple[float, float]) -> DistanceField:
        """Geodesic distance field (metres) from ``start_xy`` to every cell (inf: unreachable)."""
        grid = np.full(self.shape, np.inf)
        s = self.snap(*start_xy)
        if s is not None:
            dist, _ = self._dijkstra(s)
            assert self._index is not None
            m = self._index >= 0
            grid[m] = dist[self._index[m]]
            grid += float(np.hypot(*(self.center_of(*s) - np.asarray(start_xy[:2], float))))
        return DistanceField(grid=grid, origin_xy=self.origin_xy.copy(), cell_m=self.cell_m)

    def geodesic(self, start_xy: tuple[float, float], goal_xy: tuple[float, float]) -> float:
        """Shortest free-floor path length in metres (inf when unreachable)."""
        p = self.path(start_xy, goal_xy)
        if p is None:
            return math.inf
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

    def path(self, start_xy: tuple[float, float], goal_xy: tuple[float, float]) -> np.ndarray | None:
        """Shortest path (K, 2) from start to goal (both included), smoothed by line of sight; None when
        the goal is not free floor or not reachable. A start slightly off free floor snaps to it."""
        s = self.snap(start_xy[0], start_xy[1], 0.5)
        g = self.snap(goal_xy[0], goal_xy[1], self.cell_m * 1.5)
        if s is None or g is None:
            return None
        if self._labels[s] != self._labels[g]:
            return None
        dist, pred = self._dijkstra(s)
        assert self._index is not None
        gi = int(self._index[g])
        if not np.isfinite(dist[gi]):
            return None
        free_idx = np.nonzero(self.free.ravel())[0]
        chain = [gi]
        while chain[-1] != self._index[s]:
            chain.append(int(pred[chain[-1]]))
        chain.reverse()
        flat = free_idx[np.array(chain)]
        jj, ii = np.unravel_index(flat, self.shape)
        pts = self.origin_xy + (np.stack([ii, jj], axis=1) + 0.5) * self.cell_m
        pts = np.vstack([np.asarray(start_xy[:2], float), pts, np.asarray(goal_xy[:2], float)])
        return self._smooth(pts)

    def _visible(self, a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / (self.cell_m * 0.5))) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        p = a + (b - a) * t
        j = np.floor((p[:, 1] - self.origin_xy[1]) / self.cell_m).astype(int)
        i = np.floor((p[:, 0] - self.origin_xy[0]) / self.cell_m).astype(int)
        ok = (j >= 0) & (j < self.shape[0]) & (i >= 0) & (i < self.shape[1])
        if not ok.all():
            return False
        return bool(self.free[j, i].all())

    def _smooth(self, pts: np.ndarray) -> np.ndarray:
        # keep exact start/goal, shortcut intermediate cells by line of sight (string pulling)
        out = [pts[0]]
        k = 0
        n = len(pts)
        while k < n - 1:
            nxt = k + 1
            lo, hi = k + 1, n - 1
            # farthest visible point (visibility is near-monotone along a grid path; binary search then scan)
            while lo <= hi:
                mid = (lo + hi) // 2
                if self._visible(pts[k], pts[mid]):
                    nxt = mid
                    lo = mid + 1
                else:
                    hi = mid - 1
            out.append(pts[nxt])
            k = nxt
        res = np.array(out)
        keep = np.ones(len(res), bool)
        keep[1:] = np.linalg.norm(np.diff(res, axis=0), axis=1) > 1e-9
        keep[-1] = True
        return res[keep]

    def viewpoints(self, spacing_m: float = 0.6, n_headings: int = 8) -> list[Viewpoint]:
        """Navigable base poses: free cells of the main component on a ``spacing_m`` lattice, each with
        ``n_headings`` evenly spaced yaws; ``room`` names where known."""
        if spacing_m <= 0 or n_headings < 1:
            raise ValueError("spacing_m must be > 0 and n_headings >= 1")
        step = max(1, int(round(spacing_m / self.cell_m)))
        out: list[Viewpoint] = []
        vid = 0
        # lattice on cell centres (never on a cell boundary, so is_free agrees exactly)
        for j in range(step // 2, self.shape[0], step):
            for i in range(step // 2, self.shape[1], step):
                if not (self.free[j, i] and self._labels[j, i] == self.main_component):
                    continue
                x, y = (float(v) for v in self.center_of(j, i))
                room = self.scene.room_at(x, y) if hasattr(self.scene, "room_at") else None
                for h in range(n_headings):
                    yaw = -math.pi + 2 * math.pi * h / n_headings
                    out.append(Viewpoint(vp_id=vid, x=x, y=y,
                                         yaw_rad=float(yaw), room=room.name if room else None))
                    vid += 1
        return out

    def viewpoint_set(self, robot_id: str, intrinsics: Intrinsics, camera_height_m: float = 1.0,
                      camera_pitch_deg: float = -15.0, spacing_m: float = 0.6, n_headings: int = 8) -> ViewpointSet:
        """The :class:`ViewpointSet` message a robot publishes for remote planners."""
        return ViewpointSet(robot_id=robot_id, camera_height_m=camera_height_m, camera_pitch_deg=camera_pitch_deg,
                            intrinsics=intrinsics, viewpoints=self.viewpoints(spacing_m, n_headings))

    def reachable(self, a_xy: tuple[float, float], b_xy: tuple[float, float]) -> bool:
        """Whether b can be reached from a (same connected component of free floor)."""
        a, b = self.snap(*a_xy), self.snap(*b_xy)
        return a is not None and b is not None and self._labels[a] == self._labels[b]

    def room_cells(self, room: Any) -> np.ndarray:
        """(N, 2) xy centres of free main-component cells inside ``room``."""
        jj, ii = np.nonzero(self.free & (self._labels == self.main_component))
        pts = self.origin_xy + (np.stack([ii, jj], 1) + 0.5) * self.cell_m
        m = ((pts[:, 0] >= room.xy_min[0]) & (pts[:, 0] <= room.xy_max[0])
             & (pts[:, 1] >= room.xy_min[1]) & (pts[:, 1] <= room.xy_max[1]))
        return pts[m]


def astar_cells(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]] | None:
    """Plain 8-connected A* on a boolean grid (a reference used by tests to cross-check Dijkstra)."""
    if not (free[start] and free[goal]):
        return None
    ny, nx = free.shape
    openq: list[tuple[float, float, tuple[int, int]]] = [(0.0, 0.0, start)]
    came: dict[tuple[int, int], tuple[int, int]] = {}
    g = {start: 0.0}
    while openq:
        _, gc, cur = heapq.heappop(openq)
        if cur == goal:
            path = [cur]
            while cur in came:
                cur = came[cur]
                path.append(cur)
            return path[::-1]
        if gc > g.get(cur, math.inf):
            continue
        for dj in (-1, 0, 1):
            for di in (-1, 0, 1):
                if not dj and not di:
                    continue
                nb = (cur[0] + dj, cur[1] + di)
                if not (0 <= nb[0] < ny and 0 <= nb[1] < nx) or not free[nb]:
                    continue
                if dj and di and not (free[cur[0] + dj, cur[1]] and free[cur[0], cur[1] + di]):
                    continue
                ng = gc + (math.sqrt(2.0) if dj and di else 1.0)
                if ng < g.get(nb, math.inf):
                    g[nb] = ng
                    came[nb] = cur
                    h = math.hypot(goal[0] - nb[0], goal[1] - nb[1])
                    heapq.heappush(openq, (ng + h, ng, nb))
    return None
