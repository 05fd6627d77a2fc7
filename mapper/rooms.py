"""Rooms from the mapper's own map (pure: no I/O, nothing from the simulator).

From the point map (its voxels seen by at least ``min_observations`` keyframes), the cameras' positions and the
object nodes, :func:`build_grid` makes a 2D grid of the floor (cell ``cell_m``): **wall** cells hold points in a
band of heights above the floor that furniture rarely reaches and doorways leave open (default 1.2-2.0 m: below
a door's lintel, above tables and beds); **free** cells are observed floor, the discs the cameras passed through
and the footprints of objects standing on the floor, minus walls. Observed floor and footprints count only
where one of the nearest cameras has them in sight, no wall between (:func:`in_sight`): nothing is seen through a
wall, and RGB-only depth and boxes stretched along the viewing rays put some behind walls. :func:`segment` splits
the free space into rooms the usual way: the filled free space's distance transform, one marker per h-maximum (a
room's middle: a doorway is a saddle well below it), watershed (scikit-image); two regions that meet where the
free space is at least ``door_max_m`` wide are one room (no doorway is that wide); rooms then take the unseen cells
inside their walls up to ``grow_m`` away, and the wall cells that face them: the ring next to each room, and in a
thick wall band (RGB-only depth scatters a wall's points across one) each cell up to ``wall_share_m`` deep whose
nearest cell outside the band is a room's, so the band splits down its middle. Walls are straight: a gap of up to
``wall_bridge_m`` between two stretches of one wall line (at the walls' dominant angle) that no camera passed
through is taken for wall the map did not see (:func:`bridge_walls`; a doorway the robot has not yet used closes
until it does; a map without a moving camera bridges nothing). :class:`RoomTracker` keeps room
ids across updates and finds doorways (where two rooms' cells touch); :class:`RoomMapper` runs it all on a
growing map, puts objects in rooms (by centroid) and names each room from its objects with the embedded indoor
prior (:class:`RoomLabeller`, protocol.prior).

The id rule (RoomTracker.update), written once here and tested:

- A room of the new segmentation takes the id of the old room it overlaps most (in cells); so a room that
  grows, or whose walls are seen better, keeps its id.
- When one new region covers two or more old rooms, it is split back along the old rooms (a watershed from
  their cells) unless the boundary between two of them is **seen open**: at least ``merge_open_m`` long (wider
  than any doorway) and observed floor along at least ``merge_floor_fraction`` of it, or, with no wall cell left
  in it, observed floor or a camera's passage along at least ``merge_free_fraction`` of it (RGB-only depth sees
  floor in patches; a camera that walked where the wall stood saw it open; an object's footprint is no such
  evidence: a box against a wall reaches over it). Only then do they merge;
  the merged room keeps the id of the one it overlaps most, the other id is retired. (A fresh segmentation joins
  regions across free space wider than ``door_max_m``; rooms it once split stay split until seen open, so a wall
  lost from the map, its floor never seen, merges nothing.)
- When an old room's cells split into two regions (a wall was seen), the larger keeps the id.
- Any other region gets a fresh id (``room<n>``, n counting up from 1, never reused in one tracker).
- A room left smaller than ``min_room_m2`` by the split-back (a sliver of an early, coarser segmentation that the
  segmentation itself would no longer make a room) is no room: its cells join the rooms it touches and its id is
  retired; one that touches no other room stays.

Frames: the grid's cell ``(i, j)`` covers world ``x in [(i0 + i) * cell_m, (i0 + i + 1) * cell_m)`` and the
same for y with ``j``; ``origin_ij = (i0, j0)`` are whole cells, so grids of different updates align.
Single storey: the floor is the lowest dense level of the map.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from mapper.geometry.kernels import compiled
from protocol.messages import GraphNode
from protocol.prior import IndoorPrior
from protocol.rooms import RoomLayer as RoomLayerMessage

UNKNOWN = "unknown"


@dataclass(frozen=True)
class RoomParams:
    """Thresholds of room extraction (the mapper's ``[rooms]`` config mirrors these)."""

    cell_m: float = 0.1
    floor_band_m: float = 0.1  # points within this of the floor height are floor
    wall_band_m: tuple[float, float] = (1.2, 2.0)  # heights above the floor whose points make walls
    min_observations: int = 2  # map points seen by fewer keyframes are left out (when their counts are known)
    wall_min_points: int = 6  # voxels in the band that make a cell a wall
    camera_free_m: float = 0.3  # radius of known-free space around each camera position
    camera_max_height_m: float = 1.8  # cameras higher than this above the floor (wall-mounted) free no space
    sight_cameras: int = 16  # observed floor and footprints count only in sight of one of this many nearest cameras
    grow_m: float = 1.5  # rooms take unseen cells inside their walls up to this far from known space
    close_m: float = 0.3  # gaps in observed floor up to this wide are filled (under furniture, sparse points)
    marker_h_m: float = 0.3  # a room's middle stands this far above the saddle to its neighbour (h-maxima)
    marker_min_m: float = 0.45  # ... and at least this far from any wall (narrower is a passage, not a room)
    min_room_m2: float = 1.5  # smaller regions join their neighbour
    door_min_m: float = 0.4  # two rooms touching along this much are connected (a doorway)
    merge_open_m: float = 1.5  # the seen-open rule: an opening this wide between two rooms merges them
    merge_floor_fraction: float = 0.7  # ... with observed floor along this much of it
    merge_free_fraction: float = 0.4  # ... or, no wall cell in it, with floor seen or passed along this much (0: off)
    assign_max_m: float = 0.6  # an object outside every room joins the nearest one within this distance
    wall_share_m: float = 0.3  # a wall cell up to this deep in a wall band joins the room nearest to it (0: a ring)
    wall_bridge_m: float = 2.5  # a gap up to this long in a straight wall that no camera passed is wall (0: off)
    wall_run_m: float = 1.0  # ... between two stretches of wall at least this long
    door_max_m: float = 2.4  # two regions joined by free space this wide (no doorway is) are one room (0: never)


@dataclass(frozen=True)
class FloorGrid:
    """One storey's 2D grid: ``wall``, observed ``floor``, known ``free`` cells and those a camera ``passed``
    through (bool, shape (nx, ny))."""

    origin_ij: tuple[int, int]
    cell_m: float
    floor_z_m: float
    wall: np.ndarray
    floor: np.ndarray
    free: np.ndarray
    passed: np.ndarray | None = None  # cells a camera passed through (within ``camera_free_m``; None: unknown)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.wall.shape[0]), int(self.wall.shape[1]))

    def cells_of(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) int grid indices of world points ``xy`` (N, 2) (may fall outside the grid)."""
        return np.floor(np.asarray(xy, np.float64).reshape(-1, 2) / self.cell_m).astype(np.int64) - np.asarray(
            self.origin_ij, np.int64)

    def xy_of(self, ij: np.ndarray) -> np.ndarray:
        """World xy of the centres of cells ``ij`` (N, 2)."""
        return (np.asarray(ij, np.float64).reshape(-1, 2) + np.asarray(self.origin_ij) + 0.5) * self.cell_m


def estimate_floor_z(points_world: np.ndarray, bin_m: float = 0.04, search_m: float = 1.5) -> float | None:
    """The floor height: the densest height bin within ``search_m`` above the map's 5th height percentile (RGB-only
    maps scatter points below the floor). None for an empty map."""
    z = np.asarray(points_world).reshape(-1, 3)[:, 2]
    if len(z) > 60_000:  # a strided sample finds the same floor in a fraction of the time
        z = z[:: len(z) // 50_000]
    z = z[np.isfinite(z)].astype(np.float64)
    if len(z) == 0:
        return None
    lo = float(np.quantile(z, 0.05)) - 0.1
    zz = z[(z >= lo) & (z <= lo + search_m)]
    hist, edges = np.histogram(zz, bins=max(1, int(math.ceil(search_m / bin_m))), range=(lo, lo + search_m))
    k = int(np.argmax(hist))
    sel = zz[(zz >= edges[k]) & (zz <= edges[k + 1])]
    return float(np.median(sel)) if len(sel) else float(0.5 * (edges[k] + edges[k + 1]))


def build_grid(points_world: np.ndarray, cameras_world: np.ndarray, footprints: np.ndarray,
               params: RoomParams = RoomParams(), floor_z_m: float | None = None) -> FloorGrid | None:
    """The floor grid from map points (N, 3), camera positions (M, 3) and object footprints ((F, 6): centre x, y,
    size x, y, yaw, bottom z, as :func:`footprints_of` gives); None while there is no map."""
    p = params
    pts = np.asarray(points_world).reshape(-1, 3)
    if pts.dtype.kind != "f":
        pts = pts.astype(np.float64)
    cams = np.asarray(cameras_world, np.float64).reshape(-1, 3)
    fz = estimate_floor_z(pts) if floor_z_m is None else float(floor_z_m)
    if fz is None:
        return None
    h = pts[:, 2] - pts.dtype.type(fz)  # NaN compares False: non-finite points fall in no band
    on_floor = np.abs(h) <= p.floor_band_m
    in_wall = (h >= p.wall_band_m[0]) & (h <= p.wall_band_m[1])
    idx = np.flatnonzero(on_floor | in_wall)  # 1-D selections: several times faster than pts[mask, :2]
    x, y, is_floor = pts[:, 0][idx], pts[:, 1][idx], on_floor[idx]
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.all():
        x, y, is_floor = x[ok], y[ok], is_floor[ok]
    cams = cams[(cams[:, 2] - fz > 0.0) & (cams[:, 2] - fz <= p.camera_max_height_m)]
    if len(x) == 0 and len(cams) == 0:
        return None
    c = p.cell_m
    pad = int(math.ceil(p.camera_free_m / c)) + 2
    xs, ys = np.concatenate([x, cams[:, 0]]), np.concatenate([y, cams[:, 1]])
    lo = np.floor(np.array([xs.min(), ys.min()]) / c).astype(np.int64) - pad
    hi = np.floor(np.array([xs.max(), ys.max()]) / c).astype(np.int64) + pad + 1
    origin = (int(lo[0]), int(lo[1]))
    shape = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
    # every point is inside the bounds by construction
    flat = ((np.floor(x * (1.0 / c)).astype(np.int64) - lo[0]) * shape[1]
            + (np.floor(y * (1.0 / c)).astype(np.int64) - lo[1]))
    floor = np.bincount(flat[is_floor], minlength=shape[0] * shape[1]).reshape(shape) > 0
    wall = np.bincount(flat[~is_floor], minlength=shape[0] * shape[1]).reshape(shape) >= p.wall_min_points
    foot = np.zeros(shape, np.uint8)
    fp = np.asarray(footprints, np.float64).reshape(-1, 6)
    fp = fp[fp[:, 5] - fz <= 0.3]  # higher: on something, or on a wall; says nothing about the floor
    if len(fp):
        cy, sy = np.cos(fp[:, 4]), np.sin(fp[:, 4])
        half = 0.5 * fp[:, 2:4]
        signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
        lx, ly = signs[None, :, 0] * half[:, None, 0], signs[None, :, 1] * half[:, None, 1]  # (F, 4)
        wx = fp[:, None, 0] + cy[:, None] * lx - sy[:, None] * ly
        wy = fp[:, None, 1] + sy[:, None] * lx + cy[:, None] * ly
        # cv2 wants (col, row) = (j, i) in 1/4 cells (shift=2)
        polys = np.round(np.stack([wy / c - lo[1], wx / c - lo[0]], 2) * 4).astype(np.int32)
        cv2.fillPoly(foot, list(polys), 1, lineType=cv2.LINE_8, shift=2)
    footb = foot.astype(bool)
    if p.sight_cameras > 0:
        # Nothing is seen through a wall: observed floor and footprints that no nearby camera has in sight (RGB-only
        # depth and stretched boxes put them behind walls) say nothing about free space. Walls are those of the
        # points alone here, so that a stretched footprint cannot first clear the wall it reaches through.
        all_cams = np.asarray(cameras_world, np.float64).reshape(-1, 3)
        all_cams = all_cams[np.isfinite(all_cams).all(axis=1)]
        blocked = _closing(wall, _SQUARE3) | wall
        ask = (floor | footb) & ~blocked
        hidden = ask & ~in_sight(ask, blocked, all_cams[:, :2] / c - lo, p.sight_cameras, p.camera_free_m / c)
        floor &= ~hidden
        footb &= ~hidden
    # Tall furniture standing in a room puts points in the wall band: inside its own footprint they are not a wall.
    wall &= ~_erosion(footb, _CROSS3)
    wall = _closing(wall, _SQUARE3) | wall
    visited = np.zeros(shape, bool)
    if len(cams):
        r = int(round(p.camera_free_m / c))
        ij = np.floor(cams[:, :2] / c).astype(np.int64) - lo
        visited[ij[:, 0], ij[:, 1]] = True
        visited = _dilation(visited, _disk(r))
    if p.wall_bridge_m > 0 and len(cams):
        # Gaps in straight walls that no camera passed through are wall the map did not see. Only on a map cameras
        # moved through: fixed cameras high on walls pass through nothing and would close every doorway. Sight
        # (above) keeps the gaps: a room seen through a doorway the robot has not used is still seen, as a room.
        wall |= bridge_walls(wall, visited, p.wall_bridge_m / c, p.wall_run_m / c)
    free = (floor | visited | footb) & ~wall
    return FloorGrid(origin, c, fz, wall, floor, free, visited & ~wall)


def dominant_angle(ij: np.ndarray, step_deg: float = 1.0) -> float:
    """The rotation (radians, [0, pi/2)) that lines the cells ``ij`` (N, 2) up best with the grid's axes: the
    angle whose rotated cells pile up into the fewest rows and columns (sum of squared row and column counts)."""
    best, best_score = 0.0, -1.0
    x, y = ij[:, 0].astype(np.float64), ij[:, 1].astype(np.float64)
    for t in np.deg2rad(np.arange(0.0, 90.0, step_deg)):
        ct, st = math.cos(t), math.sin(t)
        score = 0.0
        for v in (ct * x + st * y, -st * x + ct * y):
            k = np.round(v).astype(np.int64)
            score += float(np.sum(np.bincount(k - k.min()).astype(np.float64) ** 2))
        if score > best_score:
            best, best_score = float(t), score
    return best


def bridge_walls(wall: np.ndarray, visited: np.ndarray, gap_max: float, run_min: float) -> np.ndarray:
    """Cells (bool) that close the gaps of straight walls: along each row and column of the wall cells rotated to
    their dominant angle, a gap of at most ``gap_max`` cells between two runs of at least ``run_min`` cells that no
    ``visited`` cell lies on (no camera passed through: not a doorway it used)."""
    out = np.zeros_like(wall)
    ij = np.argwhere(wall)
    if len(ij) < 2:
        return out
    t = dominant_angle(ij)
    ct, st = math.cos(t), math.sin(t)
    uv = np.stack([ct * ij[:, 0] + st * ij[:, 1], -st * ij[:, 0] + ct * ij[:, 1]], 1)
    for axis in (0, 1):
        along, row = uv[:, axis], np.round(uv[:, 1 - axis]).astype(np.int64)
        order = np.lexsort((along, row))
        a, r = along[order], row[order]
        brk = np.concatenate([[True], (r[1:] != r[:-1]) | (a[1:] - a[:-1] > 2.5)])
        run = np.cumsum(brk) - 1
        starts = np.flatnonzero(brk)
        ends = np.concatenate([starts[1:], [len(a)]]) - 1
        length = a[ends] - a[starts] + 1.0
        for k in np.flatnonzero(brk[1:] & (r[1:] == r[:-1])):
            g = a[k + 1] - a[k]
            if g > gap_max + 1.0 or length[run[k]] < run_min or length[run[k + 1]] < run_min:
                continue
            s = np.arange(a[k], a[k + 1], 0.5)
            other = np.full_like(s, float(r[k]))
            uu, vv = (s, other) if axis == 0 else (other, s)
            ci = np.round(ct * uu - st * vv).astype(np.int64)
            cj = np.round(st * uu + ct * vv).astype(np.int64)
            ok = (ci >= 0) & (ci < wall.shape[0]) & (cj >= 0) & (cj < wall.shape[1])
            ci, cj = ci[ok], cj[ok]
            if not visited[ci, cj].any():
                out[ci, cj] = True
    return out


def _sight_loops(wall: np.ndarray, cells: np.ndarray, cams: np.ndarray, order: np.ndarray, skip: float
                 ) -> np.ndarray:  # pragma: no cover - compiled (the NumPy twin below is tested against it)
    # Every sample lies between a camera and a cell centre, both on the grid (in_sight clips the cameras): the
    # coordinates are positive and in bounds, so int() is floor() and no bounds test is needed.
    n = cells.shape[0]
    out = np.zeros(n, np.bool_)
    first = int(math.ceil(2.0 * skip))  # the first sample at d = 0.5 s >= skip
    for i in range(n):
        tx, ty = cells[i, 0] + 0.5, cells[i, 1] + 0.5
        for k in range(order.shape[1]):
            j = order[i, k]
            if j < 0:
                break
            ax, ay = cams[j, 0], cams[j, 1]
            length = math.hypot(tx - ax, ty - ay)
            clear = True
            if length > 1.0:
                ux, uy = (tx - ax) / length, (ty - ay) / length
                for s in range(first, int(math.floor(2.0 * (length - 1.0))) + 1):
                    d = 0.5 * s
                    if wall[int(ax + d * ux), int(ay + d * uy)]:
                        clear = False
                        break
            if clear:
                out[i] = True
                break
    return out


def _sight_numpy(wall: np.ndarray, cells: np.ndarray, cams: np.ndarray, order: np.ndarray, skip: float
                 ) -> np.ndarray:
    """What :func:`_sight_loops` computes, without numba: the same samples, a nearest-camera rank at a time (cells
    in chunks, to bound the memory of cells x samples)."""
    if len(cells) > 4096:
        return np.concatenate([_sight_numpy(wall, cells[i:i + 4096], cams, order[i:i + 4096], skip)
                               for i in range(0, len(cells), 4096)])
    out = np.zeros(len(cells), bool)
    for k in range(order.shape[1]):
        todo = np.flatnonzero(~out & (order[:, k] >= 0))
        if len(todo) == 0:
            break
        a, b = cams[order[todo, k]], cells[todo].astype(np.float64) + 0.5
        length = np.hypot(*(b - a).T)
        d = 0.5 * np.arange(int(2.0 * length.max()) + 1)
        ok = (d[None, :] <= length[:, None] - 1.0) & (d[None, :] >= skip)
        unit = (b - a) / np.maximum(length, 1e-12)[:, None]
        ij = np.floor(a[:, None, :] + d[None, :, None] * unit[:, None, :]).astype(np.int64)
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < wall.shape[0]) & (ij[..., 1] >= 0) & (ij[..., 1] < wall.shape[1])
        hit = ok & inside
        hit[hit] = wall[ij[..., 0][hit], ij[..., 1][hit]]
        out[todo[~hit.any(axis=1)]] = True
    return out


_sight_compiled = compiled(_sight_loops)  # None without numba (optional, the ``server`` extra)


def in_sight(mask: np.ndarray, wall: np.ndarray, cams_ij: np.ndarray, k: int, skip_cells: float) -> np.ndarray:
    """Which cells of ``mask`` one of their ``k`` nearest cameras sees: no ``wall`` cell on the straight line from
    the camera's cell centre to the cell's, sampled every half cell, leaving out the first ``skip_cells`` (a camera
    mounted on a wall stands in it) and the last cell (a line grazing the wall a cell stands against). ``cams_ij``:
    (M, 2) camera positions in cell units, the grid's frame (cameras off the grid count at its edge). Cells
    outside ``mask`` are False; with no camera at all, every cell of ``mask`` is in sight."""
    out = np.zeros(mask.shape, bool)
    cells = np.argwhere(mask)
    if len(cells) == 0:
        return out
    ij = np.floor(np.asarray(cams_ij, np.float64).reshape(-1, 2))
    ij = ij[np.isfinite(ij).all(axis=1)].astype(np.int64)
    if len(ij) == 0:
        out[mask] = True
        return out
    at = np.zeros(mask.shape, bool)  # one camera per cell: thousands of keyframes stand on a few hundred cells
    at[np.clip(ij[:, 0], 0, mask.shape[0] - 1), np.clip(ij[:, 1], 0, mask.shape[1] - 1)] = True
    cam_cells = np.argwhere(at)
    cams = cam_cells + 0.5
    number = np.full(mask.shape, -1, np.int64)
    number[cam_cells[:, 0], cam_cells[:, 1]] = np.arange(len(cam_cells))
    # the nearest camera first (a cell's own room's, mostly in sight), from one distance transform of the grid; the
    # k nearest (the first again among them) only for the cells it does not see
    near = ndimage.distance_transform_edt(~at, return_distances=False, return_indices=True)
    first = number[near[0][cells[:, 0], cells[:, 1]], near[1][cells[:, 0], cells[:, 1]]]
    sight = _sight_compiled if _sight_compiled is not None else _sight_numpy
    seen = sight(wall, cells, cams, first.reshape(-1, 1), float(skip_cells))
    k = min(int(k), len(cams))
    if k > 1 and not seen.all():
        from scipy.spatial import cKDTree

        rest = np.flatnonzero(~seen)
        _, order = cKDTree(cams).query(cells[rest] + 0.5, k=k)
        seen[rest] = sight(wall, cells[rest], cams, np.asarray(order, np.int64).reshape(len(rest), k),
                           float(skip_cells))
    out[cells[:, 0], cells[:, 1]] = seen
    return out


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with its holes filled (what ``ndimage.binary_fill_holes`` gives, 4-connected background), by one
    labelling of the background instead of a dilation run to convergence."""
    bg, n = ndimage.label(~mask)
    if n == 0:
        return mask.copy()
    edge = np.unique(np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]]))
    outside = np.zeros(n + 1, bool)
    outside[edge] = True
    outside[0] = False
    return mask | ~outside[bg] & (bg > 0)


_SQUARE3 = np.ones((3, 3), bool)
_CROSS3 = ndimage.generate_binary_structure(2, 1)


def _dilation(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """``ndimage.binary_dilation(mask, structure)`` (a symmetric ``structure``, nothing beyond the border) by OpenCV:
    the same cells, an order of magnitude faster (the room layer's update runs several per keyframe)."""
    k = np.asarray(structure, np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def _erosion(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """``ndimage.binary_erosion(mask, structure)`` (symmetric, the border counted empty as scipy does) by OpenCV."""
    k = np.asarray(structure, np.uint8)
    return cv2.erode(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def _closing(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """``ndimage.binary_closing(mask, structure)``: dilation then erosion, both as scipy does them at the border."""
    return _erosion(_dilation(mask, structure), structure)


def _disk(r: int) -> np.ndarray:
    return np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= r


def room_space(grid: FloorGrid, params: RoomParams = RoomParams()) -> np.ndarray:
    """The cells rooms may take: known free space with small gaps closed and enclosed holes filled, no walls."""
    r = max(1, int(round(params.close_m / grid.cell_m)))
    closed = _closing(np.pad(grid.free, r), _disk(r))[r:-r, r:-r]
    return _fill_holes(closed | grid.free) & ~grid.wall


def segment(grid: FloorGrid, params: RoomParams = RoomParams()) -> np.ndarray:
    """Room labels (int32, 0 = no room) of the grid's cells: distance transform + h-maxima markers + watershed;
    regions under ``min_room_m2`` join the neighbour they touch most (or vanish when they touch none)."""
    from skimage.morphology import local_maxima, reconstruction
    from skimage.segmentation import watershed

    space = room_space(grid, params)
    if not space.any():
        return np.zeros(grid.shape, np.int32)
    dt = ndimage.distance_transform_edt(space) * grid.cell_m
    # h-maxima as plateaus: the regional maxima of the reconstruction of dt - h under dt (one connected plateau
    # per dome; skimage's h_maxima returns only the tops, which may be several spots of one dome). On cells twice
    # as large (a room's middle needs no finer place; the reconstruction is the costliest step), then back.
    h = params.marker_h_m
    coarse = dt[::2, ::2]
    rec = reconstruction(np.maximum(coarse - h, 0.0), coarse, method="dilation")
    peaks = local_maxima(np.round(rec / grid.cell_m * 16).astype(np.int32), connectivity=2)
    small, n = ndimage.label(peaks, structure=np.ones((3, 3), bool))
    markers = np.repeat(np.repeat(small, 2, axis=0), 2, axis=1)[: grid.shape[0], : grid.shape[1]] * space
    if n:
        tall = ndimage.maximum(dt, markers, index=np.arange(1, n + 1)) >= params.marker_min_m
        markers = np.where(markers > 0, np.concatenate([[0], np.cumsum(tall) * tall])[markers], 0)
        n = int(tall.sum())
    if n == 0:  # nothing wide enough to be a room: the widest spot seeds one
        markers = np.zeros(grid.shape, np.int32)
        markers[np.unravel_index(int(np.argmax(dt)), dt.shape)] = 1
    labels = watershed(-dt, markers, mask=space).astype(np.int32)
    if params.door_max_m > 0:
        labels = _join_wide_necks(labels, dt, 0.5 * params.door_max_m)
    labels = _drop_small(labels, dt, space, params.min_room_m2 / grid.cell_m ** 2)
    return _grow(labels, grid, space, params)


def _join_wide_necks(labels: np.ndarray, dt: np.ndarray, half_width_m: float) -> np.ndarray:
    """``labels`` with each two regions that touch (4-neighbours) where the distance transform ``dt`` (metres to
    the nearest cell outside the free space) is at least ``half_width_m`` on both sides made one: an opening twice
    that wide is no doorway. h-maxima split wherever a room's middle stands ``marker_h_m`` above the saddle,
    however wide the neck: in one large room whose floor RGB-only saw in patches, a neck 2.5 m wide splits it."""
    n = int(labels.max())
    if n < 2:
        return labels
    groups = {k: k for k in range(1, n + 1)}
    for axis in (0, 1):
        a = labels[:-1, :] if axis == 0 else labels[:, :-1]
        b = labels[1:, :] if axis == 0 else labels[:, 1:]
        da = dt[:-1, :] if axis == 0 else dt[:, :-1]
        db = dt[1:, :] if axis == 0 else dt[:, 1:]
        m = (a > 0) & (b > 0) & (a != b) & (np.minimum(da, db) >= half_width_m)
        for x, y in set(zip(a[m].tolist(), b[m].tolist(), strict=True)):
            rx, ry = _root(groups, x), _root(groups, y)
            if rx != ry:
                groups[max(rx, ry)] = min(rx, ry)
    lut = np.array([0] + [_root(groups, k) for k in range(1, n + 1)], np.int32)
    return _compact(lut[labels])


def _grow(labels: np.ndarray, grid: FloorGrid, space: np.ndarray, params: RoomParams) -> np.ndarray:
    """Rooms reach out to their walls: unseen cells inside the walls (enclosed by walls and known space, at most
    ``grow_m`` from known space) join the nearest room."""
    from skimage.segmentation import watershed

    if params.grow_m <= 0 or not labels.any():
        return labels
    r = 2
    shell = _closing(np.pad(grid.wall | space, r), _disk(r))[r:-r, r:-r]
    inside = _fill_holes(shell) & ~grid.wall
    near = ndimage.distance_transform_edt(~space) * grid.cell_m <= params.grow_m
    dist = ndimage.distance_transform_edt(labels == 0)
    return watershed(dist, labels, mask=(inside & near) | (labels > 0)).astype(np.int32)


def _drop_small(labels: np.ndarray, dt: np.ndarray, space: np.ndarray, min_cells: float) -> np.ndarray:
    from skimage.segmentation import watershed

    sizes = np.bincount(labels.ravel())
    small = [k for k in range(1, len(sizes)) if 0 < sizes[k] < min_cells]
    if not small:
        return _compact(labels)
    keep = labels.copy()
    keep[np.isin(keep, small)] = 0
    if not keep.any():
        return np.zeros_like(labels)
    # small regions flood from their big neighbours; one with none (an island of free space) is dropped
    return _compact(watershed(-dt, keep, mask=labels > 0).astype(np.int32))


def _compact(labels: np.ndarray) -> np.ndarray:
    u = np.unique(labels)
    u = u[u > 0]
    lut = np.zeros(int(labels.max()) + 1, np.int32)
    lut[u] = np.arange(1, len(u) + 1, dtype=np.int32)
    return lut[labels]


# --- rooms, doorways, ids ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Room:
    """One room of the floor: its id, outline, floor height, area and how much of it was seen."""

    room_id: str
    polygon_xy: np.ndarray  # (P, 2) world metres, the outline of its cells (counter-clockwise)
    floor_z_m: float
    area_m2: float
    observed_fraction: float  # of its cells, those whose floor was seen or cameras passed through
    centroid_xy: tuple[float, float]
    label: str = UNKNOWN
    label_confidence: float = 0.0


@dataclass(frozen=True)
class Doorway:
    """Where two rooms' cells touch: the opening's middle (world xy) and its width."""

    room_a: str
    room_b: str
    position_xy: tuple[float, float]
    width_m: float


@dataclass
class RoomLayer:
    """The rooms of one update: the grid, its room labels (index into ``rooms`` + 1) and the doorways."""

    grid: FloorGrid | None
    labels: np.ndarray
    rooms: list[Room] = field(default_factory=list)
    doorways: list[Doorway] = field(default_factory=list)

    def room_of(self, xy: np.ndarray, max_m: float = RoomParams.assign_max_m) -> list[str | None]:
        """The room id of each world point ``xy`` (N, 2): the room of its cell, else the nearest room cell within
        ``max_m``, else None."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        if self.grid is None or not self.rooms or len(xy) == 0:
            return [None] * len(xy)
        g = self.grid
        ij = g.cells_of(xy)
        ok = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < g.shape[0]) & (ij[:, 1] < g.shape[1])
        i, j = np.where(ok, ij[:, 0], 0), np.where(ok, ij[:, 1], 0)
        k = np.where(ok, self.labels[i, j], 0)
        if (ok & (k == 0)).any():  # some fall outside every room: the nearest room cell within max_m
            d, idx = ndimage.distance_transform_edt(self.labels == 0, return_indices=True)
            near = ok & (k == 0) & (d[i, j] * g.cell_m <= max_m)
            k = np.where(near, self.labels[idx[0, i, j], idx[1, i, j]], k)
        ids = [r.room_id for r in self.rooms]
        return [ids[int(kk) - 1] if good and kk > 0 else None for kk, good in zip(k, ok, strict=True)]

    def room_by_id(self, room_id: str) -> Room | None:
        return next((r for r in self.rooms if r.room_id == room_id), None)


def _align(old: np.ndarray, old_origin: tuple[int, int], shape: tuple[int, int], origin: tuple[int, int]
           ) -> np.ndarray:
    """``old`` (a grid at ``old_origin``) cut and padded onto a grid of ``shape`` at ``origin`` (0 elsewhere)."""
    out = np.zeros(shape, old.dtype)
    di, dj = old_origin[0] - origin[0], old_origin[1] - origin[1]
    i0, j0 = max(0, di), max(0, dj)
    i1, j1 = min(shape[0], di + old.shape[0]), min(shape[1], dj + old.shape[1])
    if i1 > i0 and j1 > j0:
        out[i0:i1, j0:j1] = old[i0 - di:i1 - di, j0 - dj:j1 - dj]
    return out


def _touching(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cells of mask ``a`` with a 4-neighbour in mask ``b``."""
    nb = np.zeros_like(b)
    nb[1:] |= b[:-1]
    nb[:-1] |= b[1:]
    nb[:, 1:] |= b[:, :-1]
    nb[:, :-1] |= b[:, 1:]
    return a & nb


def _pair_boundaries(labels: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """For each pair of labels (a < b) that touch (4-neighbours), the (K, 2) midpoints (cell units) of the
    touching cell pairs."""
    out: dict[tuple[int, int], list[np.ndarray]] = {}
    for axis in (0, 1):
        a = labels[:-1, :] if axis == 0 else labels[:, :-1]
        b = labels[1:, :] if axis == 0 else labels[:, 1:]
        m = (a > 0) & (b > 0) & (a != b)
        if not m.any():
            continue
        ii, jj = np.nonzero(m)
        mid = np.stack([ii + (0.5 if axis == 0 else 0.0), jj + (0.5 if axis == 1 else 0.0)], 1)
        la, lb = a[m], b[m]
        lo, hi = np.minimum(la, lb), np.maximum(la, lb)
        for key in set(zip(lo.tolist(), hi.tolist(), strict=True)):
            sel = (lo == key[0]) & (hi == key[1])
            out.setdefault(key, []).append(mid[sel])
    return {k: np.concatenate(v) for k, v in out.items()}


def _opening_m(mid: np.ndarray, cell_m: float) -> float:
    """Length of a boundary given by its touching-pair midpoints (cells): its longer side's extent."""
    if len(mid) == 0:
        return 0.0
    ext = mid.max(0) - mid.min(0)
    return float((max(ext) + 1.0) * cell_m)


class RoomTracker:
    """Rooms with ids that stay stable as the map grows (the rule is in the module docstring)."""

    def __init__(self, params: RoomParams = RoomParams()) -> None:
        self.params = params
        self._next = 1
        self._ids: dict[int, str] = {}  # internal room number -> room id
        self._numbers: np.ndarray | None = None  # last update's cells' room numbers (0 none)
        self._origin: tuple[int, int] = (0, 0)
        self.layer = RoomLayer(None, np.zeros((0, 0), np.int32))
        self._outlines: dict[str, tuple[tuple[int | float, ...], np.ndarray]] = {}

    def _fresh(self) -> int:
        n = self._next
        self._next += 1
        self._ids[n] = f"room{n}"
        return n

    def update(self, grid: FloorGrid | None) -> RoomLayer:
        """Segment ``grid`` and carry the ids over from the last update; returns (and keeps) the layer."""
        p = self.params
        if grid is None:
            return self.layer
        labels = segment(grid, p)
        old = (np.zeros(grid.shape, np.int32) if self._numbers is None
               else _align(self._numbers, self._origin, grid.shape, grid.origin_ij))
        numbers = self._carry(labels, old, grid)
        self._numbers, self._origin = numbers, grid.origin_ij
        self.layer = self._layer(grid, numbers)
        return self.layer

    def _carry(self, labels: np.ndarray, old: np.ndarray, grid: FloorGrid) -> np.ndarray:
        """Room numbers of the new cells: split regions that cover old rooms not seen open to each other,
        then give each region the number it overlaps most (the larger overlap wins a contested number)."""
        from skimage.segmentation import watershed

        min_cells = max(4, int(0.5 / grid.cell_m ** 2))  # 0.5 m2 of an old room in a region counts
        out = np.zeros_like(labels)
        regions: list[tuple[np.ndarray, dict[int, int]]] = []
        space = labels > 0
        dt: np.ndarray | None = None  # only a region over several old rooms needs it
        for k in range(1, int(labels.max()) + 1):
            reg = labels == k
            ov = np.bincount(old[reg], minlength=1)
            olds = [int(n) for n in np.nonzero(ov)[0] if n > 0 and ov[n] >= min_cells]
            if len(olds) <= 1:
                regions.append((reg, {n: int(ov[n]) for n in olds}))
                continue
            marks = np.where(reg & np.isin(old, olds), old, 0)
            if dt is None:
                dt = ndimage.distance_transform_edt(space)
            split = watershed(-dt, marks, mask=reg).astype(np.int32)
            groups = {n: n for n in olds}  # union-find over old numbers seen open to each other
            root = functools.partial(_root, groups)
            near = {n: ndimage.binary_dilation(old == n, structure=np.ones((5, 5), bool)) for n in olds}
            for ai, a in enumerate(olds):
                for b in olds[ai + 1:]:
                    oa, ob = old == a, old == b
                    strip = ((old == 0) & near[a] & near[b]) | _touching(oa, ob) | _touching(ob, oa)
                    if self._seen_open(reg & strip, grid):
                        ra, rb = root(a), root(b)
                        if ra != rb:
                            big, small = (ra, rb) if ov[ra] >= ov[rb] else (rb, ra)
                            groups[small] = big
            for r in {root(n) for n in olds}:
                members = [n for n in olds if root(n) == r]
                part = reg & np.isin(split, members)
                # keep the survivor's overlap as the sum of its members', so contests weigh the whole room
                regions.append((part, {r: int(sum(ov[n] for n in members))}))
            rest = reg & (split == 0)
            if rest.any():
                regions.append((rest, {}))
        claims: dict[int, tuple[int, int]] = {}  # old number -> (overlap, region index)
        for idx, (_reg, ovs) in enumerate(regions):
            if ovs:
                n, c = max(ovs.items(), key=lambda t: (t[1], -t[0]))
                if n not in claims or c > claims[n][0]:
                    claims[n] = (c, idx)
        winner = {idx: n for n, (_c, idx) in claims.items()}
        for idx, (reg, _ovs) in enumerate(regions):
            out[reg] = winner[idx] if idx in winner else self._fresh()
        return _absorb_small(out, space, self.params.min_room_m2 / grid.cell_m ** 2)

    def _seen_open(self, between: np.ndarray, grid: FloorGrid) -> bool:
        """Whether the strip ``between`` two old rooms (cells that were in neither, next to both: where a wall
        stood; and where they touch) is seen open: observed floor along ``merge_floor_fraction`` of it, over
        ``merge_open_m``."""
        if not between.any():
            return False
        seen = between & grid.floor
        if seen.sum() < self.params.merge_floor_fraction * between.sum():
            ff = self.params.merge_free_fraction
            if ff <= 0 or grid.passed is None or (between & grid.wall).any():
                return False
            seen = between & (grid.floor | grid.passed)  # not footprints: a box against a wall reaches over it
            if seen.sum() < ff * between.sum():
                return False
        ij = np.argwhere(seen)
        return float((ij.max(0) - ij.min(0) + 1).max() * grid.cell_m) >= self.params.merge_open_m

    def _layer(self, grid: FloorGrid, numbers: np.ndarray) -> RoomLayer:
        """Rooms and doorways of the numbered cells. Doorways are where rooms' cells touch; then each room also
        takes the wall cells next to it (a wall's face belongs to the room it faces), for its outline and area."""
        p = self.params
        present = [int(n) for n in np.unique(numbers) if n > 0]
        index = {n: i + 1 for i, n in enumerate(present)}
        lut = np.zeros(int(numbers.max()) + 1, np.int32)
        for n, i in index.items():
            lut[n] = i
        open_labels = lut[numbers]
        c = grid.cell_m
        room_ids = [self._ids[n] for n in present]
        doors = []
        for (a, b), mid in sorted(_pair_boundaries(open_labels).items()):
            w = _opening_m(mid, c)
            if w < p.door_min_m:
                continue
            xy = grid.xy_of(mid.mean(0, keepdims=True))[0]
            ra, rb = sorted((room_ids[a - 1], room_ids[b - 1]), key=_id_order)
            doors.append(Doorway(ra, rb, (float(xy[0]), float(xy[1])), w))
        # A wall cell next to a room joins it (next to two: the larger label, a tie rule that keeps it cheap). Deeper
        # in a thick wall band (RGB-only depth scatters a wall's points across it), a cell joins the room whose cell
        # is its nearest cell outside the band, within wall_share_m: the band splits down its middle between the
        # rooms on either side, and between a room and the unknown beyond an outer wall.
        wall = (open_labels == 0) & grid.wall
        near = ndimage.grey_dilation(open_labels, footprint=np.ones((3, 3), bool))
        if p.wall_share_m > 0 and wall.any():
            depth, (ii, jj) = ndimage.distance_transform_edt(wall, return_indices=True)
            side = open_labels[ii, jj]
            # + 1e-6: 0.3 m / 0.1 m is 2.9999999999999996 in floats, and a cell 3 deep must count
            near = np.where(wall & (depth <= p.wall_share_m / c + 1e-6) & (side > 0), side, near)
        labels = np.where(wall, near, open_labels).astype(np.int32)
        seen = grid.free  # observed floor, crossed by a camera, or under an object standing on the floor
        rooms = []
        for i, rid in enumerate(room_ids, start=1):
            m = labels == i
            inner = open_labels == i
            cxy = grid.xy_of(np.argwhere(m).mean(0, keepdims=True))[0]
            rooms.append(Room(rid, self._outline(rid, m, grid), grid.floor_z_m, float(m.sum() * c * c),
                              float(seen[inner].mean()) if inner.any() else 0.0, (float(cxy[0]), float(cxy[1]))))
        self._outlines = {r.room_id: self._outlines[r.room_id] for r in rooms if r.room_id in self._outlines}
        return RoomLayer(grid, labels, rooms, doors)

    def _outline(self, room_id: str, mask: np.ndarray, grid: FloorGrid) -> np.ndarray:
        """:func:`_outline`, kept per room while its cells do not change."""
        ij = np.argwhere(mask)
        (i0, j0), (i1, j1) = ij.min(0), ij.max(0) + 1
        key = (grid.origin_ij[0] + int(i0), grid.origin_ij[1] + int(j0), int(i1 - i0), int(j1 - j0),
               hash(np.packbits(mask[i0:i1, j0:j1]).tobytes()), grid.cell_m)
        hit = self._outlines.get(room_id)
        if hit is not None and hit[0] == key:
            return hit[1]
        poly = _outline(mask, grid)
        self._outlines[room_id] = (key, poly)
        return poly


def _absorb_small(numbers: np.ndarray, space: np.ndarray, min_cells: float) -> np.ndarray:
    """``numbers`` with each room under ``min_cells`` cells flooded by the rooms it touches (a watershed over the
    free space's distance transform, as :func:`segment` treats its small regions); one touching none stays."""
    from skimage.segmentation import watershed

    sizes = np.bincount(numbers.ravel())
    sizes[0] = 0
    small = np.flatnonzero((sizes > 0) & (sizes < min_cells))
    if len(small) == 0 or len(small) == np.count_nonzero(sizes):
        return numbers
    is_small = np.isin(numbers, small)
    flooded = watershed(-ndimage.distance_transform_edt(space), np.where(is_small, 0, numbers),
                        mask=numbers > 0).astype(np.int32)
    return np.where(is_small & (flooded == 0), numbers, flooded)


def _root(groups: dict[int, int], n: int) -> int:
    while groups[n] != n:
        n = groups[n]
    return n


def _id_order(room_id: str) -> tuple[int, str]:
    digits = "".join(ch for ch in room_id if ch.isdigit())
    return (int(digits) if digits else 0, room_id)


def _outline(mask: np.ndarray, grid: FloorGrid) -> np.ndarray:
    """The outer outline of a room's cells as a counter-clockwise world polygon (its largest part): the
    0.5 level line of the mask, which runs along the cells' edges, simplified to within half a cell."""
    from skimage.measure import find_contours

    ij = np.argwhere(mask)
    if len(ij) == 0:
        return np.zeros((0, 2))
    (i0, j0), (i1, j1) = ij.min(0), ij.max(0) + 1
    contours = find_contours(np.pad(mask[i0:i1, j0:j1].astype(np.float32), 1), 0.5)
    if not contours:
        return np.zeros((0, 2))
    c = max(contours, key=len).astype(np.float32).reshape(-1, 1, 2)
    cnt = cv2.approxPolyDP(c, 0.5, True).reshape(-1, 2).astype(np.float64) - 1.0 + np.array([i0, j0])
    if len(cnt) > 1 and np.allclose(cnt[0], cnt[-1]):  # closed: last == first
        cnt = cnt[:-1]
    xy = (cnt + np.asarray(grid.origin_ij) + 0.5) * grid.cell_m
    area = 0.5 * float(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))
    return xy if area >= 0 else xy[::-1]


# --- objects and labels ------------------------------------------------------------------------------
class RoomLabeller:
    """Room kinds from object labels with the indoor prior (:func:`label_room`), with the prior's tables
    prepared once and labels canonicalised once each (a room of hundreds of objects is labelled in microseconds).
    The posterior is exactly ``IndoorPrior.kind_log_posterior``'s."""

    def __init__(self, prior: IndoorPrior, max_cached: int = 10_000) -> None:
        from protocol.prior import ABSENT_P

        self.prior = prior
        self.kinds = sorted(prior.rooms)
        known = sorted({e.label for es in prior.rooms.values() for e in es})
        self._col = {lab: i for i, lab in enumerate(known)}
        table = np.full((len(self.kinds), len(known)), math.log(ABSENT_P))
        for k, kind in enumerate(self.kinds):
            for e in prior.rooms[kind]:  # a label listed twice: the last row wins, as in kind_log_posterior
                table[k, self._col[e.label]] = math.log(max(e.p_present, 1e-9))
        self._table = table
        self._base = np.array([math.log(max(prior.room_kind_prior.get(k, 0.05), 1e-9)) for k in self.kinds])
        self._canon: dict[str, int] = {}  # label -> column (-1: says nothing about rooms)
        self._max = max_cached

    def column(self, label: str) -> int:
        c = self._canon.get(label)
        if c is None:
            c = self._col.get(self.prior.canonical_label(label), -1)
            if len(self._canon) < self._max:
                self._canon[label] = c
        return c

    def __call__(self, object_labels: Sequence[str]) -> tuple[str, float, dict[str, float]]:
        cols = [c for c in (self.column(lab) for lab in object_labels) if c >= 0]
        if not cols:
            return UNKNOWN, 0.0, {}
        counts = np.bincount(np.asarray(cols), minlength=self._table.shape[1])
        v = self._base + self._table @ counts
        post = np.exp(v - v.max())
        post /= post.sum()
        best = int(np.argmax(post))
        return self.kinds[best], float(post[best]), {k: float(x) for k, x in zip(self.kinds, post, strict=True)}


def label_room(object_labels: Sequence[str], prior: IndoorPrior) -> tuple[str, float, dict[str, float]]:
    """A room's kind from the labels of its objects: the indoor prior's posterior over room kinds (the kinds'
    base rates times each object's presence probability per kind, ``IndoorPrior.kind_log_posterior``), its
    probability and the whole posterior. ``("unknown", 0.0, {})`` while none of the labels says anything about
    rooms."""
    return RoomLabeller(prior)(object_labels)


def footprints_of(nodes: Sequence[GraphNode]) -> np.ndarray:
    """The objects' boxes seen from above: (F, 6) centre x, y, size x, y, yaw, bottom z (world, metres)."""
    return np.array([_footprint(n) for n in nodes], np.float64).reshape(-1, 6)


def _footprint(n: GraphNode) -> tuple[float, float, float, float, float, float]:
    b = n.box
    return (b.center[0], b.center[1], b.extent[0], b.extent[1], b.yaw_rad, b.center[2] - 0.5 * b.extent[2])


class RoomMapper:
    """The room layer of a growing map: camera positions kept as known-free space, rooms with stable ids
    (:class:`RoomTracker`), objects assigned to rooms and rooms labelled from their objects."""

    def __init__(self, params: RoomParams = RoomParams(), prior: IndoorPrior | None = None,
                 max_cameras: int = 20_000) -> None:
        from protocol.prior import load_prior

        self.params = params
        self.prior = prior if prior is not None else load_prior()
        self.labeller = RoomLabeller(self.prior)
        self.tracker = RoomTracker(params)
        self.cameras: collections.deque[tuple[float, float, float]] = collections.deque(maxlen=max_cameras)
        self.in_room: dict[str, str] = {}
        self._row_cache: dict[str, tuple[GraphNode, tuple[float, ...]]] = {}
        self._floor: tuple[int, float] | None = None  # (map size, floor height) of the last estimate

    @property
    def layer(self) -> RoomLayer:
        return self.tracker.layer

    def note_camera(self, xyz: np.ndarray) -> None:
        """A camera was here (world metres): the space around it is free."""
        p = np.asarray(xyz, np.float64).reshape(3)
        if np.all(np.isfinite(p)):
            self.cameras.append((float(p[0]), float(p[1]), float(p[2])))

    def update(self, points_world: np.ndarray, nodes: Sequence[GraphNode], counts: np.ndarray | None = None
               ) -> RoomLayer:
        """Rebuild the grid from the map, carry room ids over, assign ``nodes`` and label the rooms. ``counts``:
        how many keyframes observed each point (the voxel map's); points seen fewer than ``min_observations``
        times are left out (RGB-only depth scatters single-view outliers; surfaces are seen again), unless that
        would leave less than a fifth of the map."""
        if counts is not None and self.params.min_observations > 1:
            c = np.asarray(counts).reshape(-1)
            if len(c) == len(points_world):
                keep = c >= self.params.min_observations
                # A map mostly seen once (a fixed camera's, or the first keyframes) is kept whole: filtering it
                # would leave nothing to build rooms from.
                if keep.sum() >= 0.2 * len(keep):
                    points_world = np.asarray(points_world)[keep]
        rows = self._rows(nodes)
        size = len(points_world)
        if self._floor is None or abs(size - self._floor[0]) > 0.1 * max(self._floor[0], 1):
            # the floor height moves only as the map grows: re-estimated when the map changed size by 10 %
            fz = estimate_floor_z(points_world)
            self._floor = (size, fz) if fz is not None else None
        grid = build_grid(points_world, np.array(self.cameras, np.float64).reshape(-1, 3), rows[:, 2:8], self.params,
                          floor_z_m=self._floor[1] if self._floor is not None else None)
        layer = self.tracker.update(grid)
        ids = layer.room_of(rows[:, :2], self.params.assign_max_m)
        self.in_room = {n.node_id: r for n, r in zip(nodes, ids, strict=True) if r is not None}
        members: dict[str, list[str]] = {}
        for n in nodes:
            r = self.in_room.get(n.node_id)
            if r is not None:
                members.setdefault(r, []).append(n.label)
        layer.rooms = [dataclasses.replace(room, label=lab, label_confidence=conf)
                       for room in layer.rooms
                       for lab, conf, _ in [self.labeller(members.get(room.room_id, []))]]
        return layer

    def _rows(self, nodes: Sequence[GraphNode]) -> np.ndarray:
        """(N, 8) centroid x, y and footprint of each node; unchanged nodes (the same object as last time) are
        not read again."""
        cache: dict[str, tuple[GraphNode, tuple[float, ...]]] = {}
        old = self._row_cache
        out = []
        for n in nodes:
            hit = old.get(n.node_id)
            row = hit[1] if hit is not None and hit[0] is n else (n.centroid[0], n.centroid[1], *_footprint(n))
            cache[n.node_id] = (n, row)
            out.append(row)
        self._row_cache = cache
        return np.array(out, np.float64).reshape(-1, 8)

    def state(self) -> dict[str, Any]:
        """What a restart needs to keep room ids: the camera positions and the tracker's numbered cells."""
        t = self.tracker
        nums = t._numbers if t._numbers is not None else np.zeros((0, 0), np.int32)
        return {"cameras": np.array(self.cameras, np.float64).reshape(-1, 3).tobytes(), "next": t._next,
                "ids": {str(k): v for k, v in t._ids.items()}, "origin": list(t._origin),
                "shape": list(nums.shape), "numbers": nums.astype(np.int32).tobytes()}

    def load_state(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`state` (the layer itself is rebuilt at the next update)."""
        t = self.tracker
        cams = np.frombuffer(state["cameras"], np.float64).reshape(-1, 3)
        self.cameras.clear()
        self.cameras.extend((float(x), float(y), float(z)) for x, y, z in cams)
        t._next = int(state["next"])
        t._ids = {int(k): str(v) for k, v in state["ids"].items()}
        t._origin = (int(state["origin"][0]), int(state["origin"][1]))
        shape = tuple(int(x) for x in state["shape"])
        nums = np.frombuffer(state["numbers"], np.int32).reshape(shape).copy()
        t._numbers = nums if nums.size else None


def room_message(layer: RoomLayer, in_room: dict[str, str], version: int, epoch: str, stamp_ns: int
                 ) -> RoomLayerMessage:
    """The wire message of a room layer: its rooms, the objects' in_room edges and the doorways' connects edges."""
    from protocol.rooms import RoomEdge, RoomNode

    rooms = [RoomNode(room_id=r.room_id, label=r.label, label_confidence=min(1.0, max(0.0, r.label_confidence)),
                      polygon=[(round(float(x), 3), round(float(y), 3)) for x, y in r.polygon_xy],
                      floor_z_m=round(r.floor_z_m, 3), area_m2=round(r.area_m2, 3),
                      observed_fraction=min(1.0, max(0.0, r.observed_fraction)),
                      centroid=(round(r.centroid_xy[0], 3), round(r.centroid_xy[1], 3)))
             for r in sorted(layer.rooms, key=lambda r: _id_order(r.room_id))]
    edges = [RoomEdge(subject_id=n, predicate="in_room", object_id=r) for n, r in sorted(in_room.items())]
    edges += [RoomEdge(subject_id=d.room_a, predicate="connects", object_id=d.room_b,
                       position=(round(d.position_xy[0], 3), round(d.position_xy[1], 3)), width_m=round(d.width_m, 3))
              for d in layer.doorways]
    return RoomLayerMessage(epoch=epoch, version=version, stamp_ns=stamp_ns, rooms=rooms, edges=edges)
