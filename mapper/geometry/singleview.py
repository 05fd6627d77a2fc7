"""Single-view geometry from a known pose and the floor plane (pure numpy + OpenCV, no weights).

A calibrated camera (surveyed height and tilt) knows where the floor is: the ray through a pixel on the
floor meets the plane ``z = floor_z_m``. Objects stand on the floor or on other objects, so each instance
mask can be placed in 3D from the pixels where it touches its support, under an upright-box assumption
(single-view metrology in the spirit of Hoiem et al.'s "photo pop-up"):

1. **Contact columns.** For every image column of a mask, its lowest pixel. When the pixels just below
   are background, the object touches the floor there (its ray meets the floor plane); when they belong to
   another, already placed mask, the object rests on (or in) that object (its ray meets that object's box).
   Columns that reach the image border are truncated and say nothing. Floor columns are kept only on the
   mask's lower convex envelope (a convex footprint projects to a convex outline, so columns that end
   higher, between a chair's legs or under a table top, see the floor *behind* the object), off steep
   silhouette sides, in runs, and, given the image, where the pixels below look like the floor under the
   view's other objects (so an object seen against a wall is not pushed through it); a view with two floors
   (another room's, through a doorway) has a colour model for each.
2. **Footprint.** The rectangle the contact points lie along (L-shape fitting): the two visible bottom
   edges of a box seen across a corner give the whole rectangle. A footprint seen edge-on (one visible
   side) gets the depth, away from the camera, whose box silhouette best matches the mask. Contacts that
   see the floor past the object's side (beyond a wall it stands against) lie behind it: the nearest
   contacts alone are tried too, and the box whose silhouette matches the mask best is kept.
3. **Height.** The upright box whose top projects to the mask's top row. The box is then refined to the
   mask (Nelder-Mead on centre, footprint, yaw and height, the silhouette's IoU with the mask, pixels of
   other masks not counted, the footprint kept on its contacts): a bottom edge partly hidden by an object
   in front no longer leaves the box short.
4. **Depth.** Each mask pixel's ray is cast into its box (the camera-facing faces); rays that miss it get
   the box centre's depth.

Objects are placed support-first (floor objects, then what rests on them, up to ``max_support_levels``).
``SeenView`` keeps what a calibrated camera saw (detections and the floor) so that other cameras' coarse
placements can be checked against it (``mapper.fusion.ObjectMap.check_coarse`` and ``forget_gone``).
A mask that touches neither the floor nor a placed object (a picture on a wall, an object cut by the image
border) gets no depth: it is left to multi-view geometry. The estimate is coarse (centimetres to decimetres)
and says so: its confidence is ``confidence``, below stereo depth, so other views refine it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from protocol.poses import invert, unproject

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class SingleViewParams:
    """Thresholds of single-view placement (metres, pixels, degrees)."""

    floor_z_m: float = 0.0
    max_range_m: float = 12.0  # floor contacts farther than this from the camera are not trusted
    min_contact_columns: int = 3  # fewer usable contact columns: the mask is not placed
    envelope_tol_px: float = 2.0  # floor columns this far above the lower convex envelope are dropped
    max_slope_px: float = 3.0  # columns where the lowest row changes faster (rows per column) are silhouette sides
    end_trim_px: int = 2  # columns this close to a steep one are dropped too (where a silhouette side begins)
    min_run: int = 2  # floor columns must come in runs of this many adjacent columns (no isolated hull corners)
    max_extent_m: float = 3.5  # a footprint longer than this is a wrong placement (contacts seen through a gap)
    below_px: int = 2  # how many pixels under a mask's lowest pixel decide what supports it
    border_px: int = 1  # columns whose lowest pixel is this close to the bottom border are truncated
    edge_on_ratio: float = 0.25  # footprint short/long side below which it is seen edge-on: depth fit to the mask
    min_extent_m: float = 0.05
    max_height_m: float = 3.0
    max_support_levels: int = 3
    confidence: float = 0.4  # below stereo depth (~0.5-1): a coarse estimate that other views refine
    trim_fractions: tuple[float, ...] = (1.0, 0.75, 0.5)  # nearest contact subsets tried (silhouette decides)
    trim_margin: float = 0.05  # IoU by which a trimmed subset must beat all the contacts
    floor_colour_sigma: float = 3.0  # contacts whose colour below is farther from the floor's (robust sigmas): dropped
    floor_cluster_share: float = 0.3  # a colour cluster this big of the floor sample is a floor too (> 0.5: off)
    other_floor: bool = True  # contacts unlike the floor: kept when unlike the background above the object too
    refine_evals: int = 300  # silhouette refinement of the box (0: off), cost evaluations
    refine_slack_m: float = 0.05  # contacts this far outside the refined footprint cost nothing
    refine_contact_weight: float = 1.0  # IoU per metre of a contact outside the refined footprint


@dataclass(frozen=True)
class PlacedBox:
    """An upright box: centre (3,), extents (3,) along its yawed x, y and world z, yaw about z (radians).

    ``support`` is -1 for the floor, else the index of the supporting mask; ``contacts`` how many contact
    columns placed it."""

    center: F64
    extent: F64
    yaw_rad: float
    support: int
    contacts: int

    def rotation(self) -> F64:
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def corners(self) -> F64:
        """(8, 3) world corners."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        return (signs * (0.5 * self.extent)) @ self.rotation().T + self.center


def pixel_rays(K: F64, us: np.ndarray, vs: np.ndarray) -> F64:
    """Camera-frame rays (N, 3) with z = 1 through pixel centres (u, v)."""
    return unproject(K, np.stack([us, vs], axis=-1), np.ones(len(us)))


def ray_box_depth(origin: F64, dirs_world: F64, box: PlacedBox) -> F64:
    """Ray parameter of the first hit of each ray (N, 3; camera rays with z = 1, so the parameter is the
    camera z-depth) with the box; NaN where a ray misses it (slab method in the box frame)."""
    R = box.rotation()
    o = (origin - box.center) @ R
    d = dirs_world @ R
    half = 0.5 * box.extent
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    lo = np.nanmax(np.minimum(t1, t2), axis=1)
    hi = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (hi >= lo) & (hi > 0)
    return np.where(hit, np.maximum(lo, 0.0), np.nan)


def _lower_envelope(us: F64, vs: F64) -> F64:
    """The lower convex envelope (largest v, image rows grow downwards) of points (u, v), evaluated at ``us``:
    the upper hull in a v-up frame, by Andrew's monotone chain."""
    order = np.lexsort((-vs, us))
    hull: list[tuple[float, float]] = []
    for u, v in zip(us[order], vs[order], strict=True):
        if hull and hull[-1][0] == u:
            continue  # the largest v of a column comes first
        while len(hull) >= 2:
            (u1, v1), (u2, v2) = hull[-2], hull[-1]
            # keep the chain concave (v as a function of u bulges downwards in the image)
            if (u2 - u1) * (v - v1) - (v2 - v1) * (u - u1) >= 0:
                hull.pop()
            else:
                break
        hull.append((float(u), float(v)))
    hu = np.array([h[0] for h in hull])
    hv = np.array([h[1] for h in hull])
    return np.interp(us, hu, hv)


def _slope(us: F64, vs: F64, keep: np.ndarray) -> F64:
    """Rows per column of the lowest-pixel outline at each kept column, between adjacent kept columns only
    (the steeper side where it bends): a vertical silhouette edge (the side of a bookshelf against a wall)
    is steep, a floor edge is not."""
    order = np.argsort(us)
    u, v, k = us[order], vs[order], keep[order]
    du, dv = np.diff(u), np.abs(np.diff(v))
    step = np.where((du == 1) & k[1:] & k[:-1], dv, 0.0)  # gaps between runs say nothing
    out = np.empty_like(v)
    out[order] = np.maximum(np.r_[0.0, step], np.r_[step, 0.0])
    return out


def _near(us: F64, flag: np.ndarray, k: int) -> np.ndarray:
    """Columns within ``k`` columns of a flagged one."""
    marks = np.sort(us[flag])
    if len(marks) == 0:
        return np.zeros(len(us), bool)
    i = np.clip(np.searchsorted(marks, us), 1, len(marks)) - 1
    j = np.clip(i + 1, 0, len(marks) - 1)
    return (np.abs(us - marks[i]) <= k) | (np.abs(us - marks[j]) <= k)


def _run_lengths(us: F64, keep: np.ndarray) -> np.ndarray:
    """For each column, the length of the run of adjacent kept columns it belongs to (0 when not kept)."""
    order = np.argsort(us)
    u, k = us[order], keep[order]
    run_id = np.cumsum(np.r_[True, (np.diff(u) != 1) | ~k[1:] | ~k[:-1]])
    lengths = np.bincount(run_id, weights=k.astype(float))[run_id]
    out = np.zeros(len(us))
    out[order] = np.where(k, lengths, 0.0)
    return out


def _footprint(points_xy: F64, cam_xy: F64, p: SingleViewParams) -> tuple[F64, F64, float, F64 | None]:
    """Centre (2,), extent (2,) and yaw of the minimum-area rectangle of contact points, and for a footprint
    seen edge-on (one visible bottom edge) the unit xy direction away from the camera its depth extends to
    (its extent along it is then only a minimum), else None."""
    yaw = _l_shape_yaw(points_xy)
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    local = points_xy @ rot
    lo, hi = local.min(axis=0), local.max(axis=0)
    ext = np.maximum(hi - lo, p.min_extent_m)
    centre = rot @ (0.5 * (lo + hi))
    short, long_ = int(np.argmin(ext)), int(np.argmax(ext))
    if ext[short] >= p.edge_on_ratio * ext[long_]:
        return centre, ext, yaw, None
    axis = np.array([np.cos(yaw), np.sin(yaw)]) if short == 0 else np.array([-np.sin(yaw), np.cos(yaw)])
    if float(axis @ (centre - cam_xy)) < 0:
        axis = -axis
    return centre, ext, yaw, axis


def _l_shape_yaw(points_xy: F64, d0: float = 0.01) -> float:
    """Yaw of the rectangle whose edges the points lie along (L-shape fitting with the closeness criterion of
    Zhang et al., 2017): the minimum-area rectangle is ambiguous for an L, whose hull is a triangle."""
    angles = np.radians(np.arange(0.0, 90.0, 1.0))
    e1 = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    e2 = np.stack([-np.sin(angles), np.cos(angles)], axis=1)
    c1, c2 = points_xy @ e1.T, points_xy @ e2.T  # (N, A)
    d1 = np.minimum(c1.max(0) - c1, c1 - c1.min(0))
    d2 = np.minimum(c2.max(0) - c2, c2 - c2.min(0))
    score = (1.0 / np.maximum(np.minimum(d1, d2), d0)).sum(axis=0)
    return float(angles[int(np.argmax(score))])


def _deepen(box_xy: tuple[F64, F64, float], axis: F64, depth: float) -> tuple[F64, F64, float]:
    """The footprint with its extent along ``axis`` set to ``depth``, its near edge kept in place."""
    centre, ext, yaw = box_xy
    i = int(np.argmax(np.abs([np.cos(yaw) * axis[0] + np.sin(yaw) * axis[1],
                              -np.sin(yaw) * axis[0] + np.cos(yaw) * axis[1]])))
    ext = ext.copy()
    centre = centre + axis * 0.5 * (depth - ext[i])
    ext[i] = depth
    return centre, ext, yaw


def _silhouette_score(box: PlacedBox, mask: np.ndarray, others: np.ndarray, K: F64, T_cam_world: F64) -> float:
    """IoU of the box's projected silhouette with the mask, where box pixels on other masks (which may hide
    the object) count neither way."""
    pc = box.corners() @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    if np.any(pc[:, 2] <= 1e-3):
        return 0.0
    uv = pc[:, :2] / pc[:, 2:3] * np.diag(K)[:2] + K[:2, 2]
    h, w = mask.shape
    if not np.all(np.isfinite(uv)) or np.any(np.abs(uv) > 4 * max(h, w)):
        return 0.0
    sil = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(sil, cv2.convexHull(np.round(uv).astype(np.int32)), 1)
    b = sil.astype(bool)
    inter = int(np.count_nonzero(b & mask))
    union = int(np.count_nonzero((b | mask) & ~(b & others & ~mask)))
    return inter / union if union else 0.0


def _project_top_row(box_xy: tuple[F64, F64, float], base_z: float, height: float, K: F64, T_cam_world: F64) -> float:
    centre, ext, yaw = box_xy
    box = PlacedBox(np.array([*centre, base_z + 0.5 * height]), np.array([*ext, height]), yaw, -1, 0)
    top = box.corners()[1::2]  # the four corners with +z
    pc = top @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    pc = pc[pc[:, 2] > 1e-6]
    if len(pc) == 0:
        return -np.inf
    return float(np.min(pc[:, 1] / pc[:, 2] * K[1, 1] + K[1, 2]))


def _height(box_xy: tuple[F64, F64, float], base_z: float, top_v: float, K: F64, T_cam_world: F64,
            p: SingleViewParams) -> float:
    """Height whose top projects to row ``top_v`` (bisection: the top rises in the image as it grows)."""
    lo, hi = p.min_extent_m, p.max_height_m
    if _project_top_row(box_xy, base_z, hi, K, T_cam_world) > top_v:
        return hi
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if _project_top_row(box_xy, base_z, mid, K, T_cam_world) > top_v:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def lowest_pixels(mask: np.ndarray, border_px: int = 1) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Column and row of each image column's lowest mask pixel, leaving out columns whose lowest pixel is
    within ``border_px`` of the bottom border (the object may go on below the image: truncated)."""
    h = mask.shape[0]
    cols = np.flatnonzero(mask.any(axis=0))
    low = (h - 1) - np.argmax(mask[::-1, cols], axis=0)
    keep = low < h - 1 - border_px
    return cols[keep], low[keep]


_OCCLUDED = -3
"""``owner`` of a pixel on an occluder (a passer-by): neither background (floor) nor a support."""


def place_objects(masks: Sequence[np.ndarray], K: F64, T_world_cam: F64,
                  params: SingleViewParams = SingleViewParams(), image: np.ndarray | None = None,
                  occluders: Sequence[np.ndarray] = (),
                  ) -> list[PlacedBox | None]:
    """One upright box per mask (None where it cannot be placed), masks (H, W) bool at the resolution of
    ``K``; see the module docstring. With the ``image`` (H, W, 3 RGB), floor contacts must also look like
    the floor under the other objects' feet: an object whose feet seem to stand on a wall (the TV above a
    stand, seen against the wall) is not pushed through it.

    ``occluders`` (H, W) bool: what stands in front of the scene and holds nothing up (people). A column whose
    lowest pixel has an occluder just below says nothing (the object goes on behind it): it is neither a floor
    contact nor a support, so an object behind a passer-by is not set on the passer-by's box; occluder pixels may
    hide the object (they do not count against its silhouette)."""
    p = params
    n = len(masks)
    if n == 0:
        return []
    h, w = masks[0].shape
    owner = np.full((h, w), -1, np.int32)
    for i, m in enumerate(masks):
        owner[m & (owner < 0)] = i
    for m in occluders:
        if m.shape != (h, w):
            raise ValueError(f"occluder mask {m.shape} is not the masks' shape {(h, w)}")
        owner[m & (owner == -1)] = _OCCLUDED
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    boxes: list[PlacedBox | None] = [None] * n
    # Per mask: contact columns and what lies just below each.
    contacts: list[tuple[F64, F64, np.ndarray] | None] = []
    for m in masks:
        if not m.any():
            contacts.append(None)
            continue
        cols, low = lowest_pixels(m, p.border_px)
        below = np.full(len(cols), -2, np.int64)  # -2: undecided, -1: background
        for k in range(1, p.below_px + 1):
            rows = np.minimum(low + k, h - 1)
            o = owner[rows, cols]
            below = np.where((below == -2) & ((o >= 0) | (o == _OCCLUDED)) & ~m[rows, cols], o, below)
        below = np.where(below == -2, -1, below)
        contacts.append((cols.astype(float), low.astype(float), below))
    floor_cols = [None if c is None else _floor_columns(*c, p) for c in contacts]
    if image is not None:
        seen_cols = _floor_looking(floor_cols, image, p)
        floor_cols = [_other_floor(g, c, masks[i], owner, image, p) for i, (g, c) in
                      enumerate(zip(floor_cols, seen_cols, strict=True))] if p.other_floor else seen_cols
    for level in range(p.max_support_levels + 1):
        placed_any = False
        for i, c in enumerate(contacts):
            if boxes[i] is not None or c is None:
                continue
            us, vs, below = c
            if level == 0:
                fc = floor_cols[i]
                pts, support = (None if fc is None else _floor_points(fc[0], fc[1], K, R, t, p)), -1
            else:
                pts, support = _support_points(us, vs, below, boxes, K, R, t, p)
            if pts is None or len(pts) < p.min_contact_columns:
                continue
            others = ((owner >= 0) & (owner != i)) | (owner == _OCCLUDED)
            box = box_from_contacts(pts, masks[i], others, K, T_world_cam, support, p)
            if box is None:
                continue
            boxes[i] = box
            placed_any = True
        if not placed_any and level > 0:
            break
    return boxes


class _SilhouetteFit:
    """IoU of upright boxes' silhouettes with one mask, on a crop around it downsampled to at most
    ``side_px`` pixels (cheap enough to optimise over); pixels on other masks (which may hide the object)
    count neither way. The box's silhouette area outside the crop counts as box only."""

    def __init__(self, mask: np.ndarray, others: np.ndarray, K: F64, T_cam_world: F64, side_px: int = 128) -> None:
        vs, us = np.nonzero(mask)
        h, w = mask.shape
        pad_u, pad_v = 0.5 * (us.max() - us.min() + 1), 0.5 * (vs.max() - vs.min() + 1)
        u0, u1 = int(max(us.min() - pad_u, 0)), int(min(us.max() + pad_u + 1, w))
        v0, v1 = int(max(vs.min() - pad_v, 0)), int(min(vs.max() + pad_v + 1, h))
        self.scale = min(1.0, side_px / max(u1 - u0, v1 - v0))
        sw, sh = max(1, round((u1 - u0) * self.scale)), max(1, round((v1 - v0) * self.scale))
        self.origin = np.array([u0, v0], float)
        self.mask = cv2.resize(mask[v0:v1, u0:u1].astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA) > 0.5
        hidden = others[v0:v1, u0:u1] & ~mask[v0:v1, u0:u1]
        self.hidden = cv2.resize(hidden.astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA) > 0.5
        self.mask_area = float(np.count_nonzero(self.mask))
        self.K, self.T = K, T_cam_world

    def iou(self, box: PlacedBox) -> float:
        pc = box.corners() @ self.T[:3, :3].T + self.T[:3, 3]
        if np.any(pc[:, 2] <= 1e-3):
            return 0.0
        uv = (pc[:, :2] / pc[:, 2:3] * np.diag(self.K)[:2] + self.K[:2, 2] - self.origin) * self.scale
        if not np.all(np.isfinite(uv)) or np.any(np.abs(uv) > 1e5):
            return 0.0
        hull = cv2.convexHull(uv.astype(np.float32))
        area = float(cv2.contourArea(hull))
        sil = np.zeros(self.mask.shape, np.uint8)
        cv2.fillConvexPoly(sil, np.round(hull).astype(np.int32), 1)
        b = sil.astype(bool)
        inter = float(np.count_nonzero(b & self.mask))
        hidden = float(np.count_nonzero(b & self.hidden))
        union = max(area - hidden, inter) + self.mask_area - inter
        return inter / union if union > 0 else 0.0


def _refine_box(box: PlacedBox, fit: _SilhouetteFit, contacts_xy: F64, p: SingleViewParams) -> PlacedBox:
    """The upright box on the same base whose silhouette best matches the mask (Nelder-Mead over its centre,
    footprint, yaw and height, from ``box``), its footprint kept on the contact points: a contact farther
    than ``p.refine_slack_m`` outside it costs ``p.refine_contact_weight`` IoU per metre. Returns ``box``
    unless the refined one scores better."""
    from scipy.optimize import minimize

    base_z = float(box.center[2] - 0.5 * box.extent[2])

    def make(x: np.ndarray) -> PlacedBox:
        ext = np.clip(np.exp(x[2:4]), p.min_extent_m, p.max_extent_m)
        height = float(np.clip(np.exp(x[5]), p.min_extent_m, p.max_height_m))
        return PlacedBox(np.array([x[0], x[1], base_z + 0.5 * height]), np.array([*ext, height]), float(x[4]),
                         box.support, box.contacts)

    def cost(x: np.ndarray) -> float:
        b = make(x)
        c, s = np.cos(b.yaw_rad), np.sin(b.yaw_rad)
        local = (contacts_xy - b.center[:2]) @ np.array([[c, -s], [s, c]])
        out = np.maximum(np.abs(local) - 0.5 * b.extent[:2], 0.0)
        miss = np.maximum(np.linalg.norm(out, axis=1) - p.refine_slack_m, 0.0)
        return -fit.iou(b) + p.refine_contact_weight * float(miss.mean())

    x0 = np.array([box.center[0], box.center[1], np.log(box.extent[0]), np.log(box.extent[1]), box.yaw_rad,
                   np.log(box.extent[2])])
    simplex = x0 + np.vstack([np.zeros(6), np.diag([0.1, 0.1, 0.3, 0.3, 0.3, 0.3])])
    res = minimize(cost, x0, method="Nelder-Mead",
                   options={"maxfev": p.refine_evals, "xatol": 1e-3, "fatol": 1e-4, "initial_simplex": simplex})
    return make(res.x) if float(res.fun) < cost(x0) else box


def _contact_subsets(pts: F64, cam_xy: F64, fractions: Sequence[float], min_count: int) -> list[F64]:
    """The contact points, and the nearest ``fractions`` of them by horizontal range from the camera (the
    floor seen past an object's side or between its legs lies behind it: its contacts are the far ones);
    subsets with fewer than ``min_count`` points or equal to a previous one are left out."""
    rng = np.linalg.norm(pts[:, :2] - cam_xy, axis=1)
    order = np.argsort(rng, kind="stable")
    out: list[F64] = []
    sizes: set[int] = set()
    for f in fractions:
        k = int(round(f * len(pts)))
        if k < min_count or k in sizes:
            continue
        sizes.add(k)
        out.append(pts[order[:k]])
    return out


def _fit_box(pts: F64, support: int, mask: np.ndarray, others: np.ndarray, top_v: float, K: F64,
             T_cam_world: F64, cam: F64, p: SingleViewParams) -> PlacedBox | None:
    """The upright box standing on contact points ``pts`` whose silhouette best matches the mask, over the
    contact subsets of ``_contact_subsets`` (``p.trim_fractions``) and, for a footprint seen edge-on, its
    depths; footprints longer than ``p.max_extent_m`` are not candidates. None when no candidate is left.
    A trimmed subset must beat the full set by ``p.trim_margin`` IoU."""
    best: tuple[float, PlacedBox, F64] | None = None
    for n_set, sub in enumerate(_contact_subsets(pts, cam[:2], p.trim_fractions, p.min_contact_columns)):
        base_z = float(np.median(sub[:, 2]))
        centre, ext, yaw, axis = _footprint(sub[:, :2], cam[:2], p)
        if float(np.max(ext)) > p.max_extent_m:
            continue
        fits = [(centre, ext, yaw)]
        if axis is not None:
            # One visible bottom edge: its depth is whatever makes the box's silhouette match the mask.
            deepest = min(max(2.0 * float(np.max(ext)), 1.0), p.max_extent_m)
            depths = np.linspace(max(float(np.min(ext)), p.min_extent_m), deepest, 12)
            fits = [_deepen((centre, ext, yaw), axis, float(d)) for d in depths]
        for box_xy in fits:
            height = _height(box_xy, base_z, top_v, K, T_cam_world, p)
            cand = PlacedBox(np.array([*box_xy[0], base_z + 0.5 * height]), np.array([*box_xy[1], height]),
                             box_xy[2], support, len(sub))
            score = _silhouette_score(cand, mask, others, K, T_cam_world) - (p.trim_margin if n_set else 0.0)
            if best is None or score > best[0]:
                best = (score, cand, sub)
    if best is None:
        return None
    if p.refine_evals > 0:
        return _refine_box(best[1], _SilhouetteFit(mask, others, K, T_cam_world), best[2][:, :2], p)
    return best[1]


def _floor_columns(us: F64, vs: F64, below: np.ndarray, p: SingleViewParams) -> tuple[F64, F64]:
    """The columns (u, lowest row) of one mask where it stands on the floor: background below, on the
    lower convex envelope, not on a steep silhouette side, in runs."""
    floor = below == -1
    us, vs = us[floor], vs[floor]
    if len(us) < p.min_contact_columns:
        return us[:0], vs[:0]
    env = _lower_envelope(us, vs)
    on_env = vs >= env - p.envelope_tol_px
    steep = on_env & (_slope(us, vs, on_env) > p.max_slope_px)
    on_env &= ~_near(us, steep, p.end_trim_px)
    on_env &= _run_lengths(us, on_env) >= p.min_run
    return us[on_env], vs[on_env]


def _robust_model(sample: F64) -> tuple[F64, F64]:
    """Median and robust spread (1.4826 MAD, clipped to 3..15 Lab units) of colour samples (N, 3)."""
    mu = np.median(sample, axis=0)
    return mu, np.clip(1.4826 * np.median(np.abs(sample - mu), axis=0), 3.0, 15.0)


def _two_means(sample: F64, iters: int = 10) -> np.ndarray:
    """Deterministic 2-means labels (0/1) of samples (N, 3): seeded at the median and the sample farthest from it."""
    med = np.median(sample, axis=0)
    centres = np.stack([med, sample[int(np.argmax(np.linalg.norm(sample - med, axis=1)))]])
    labels = np.zeros(len(sample), np.int64)
    for _ in range(iters):
        labels = np.argmin(np.linalg.norm(sample[:, None, :] - centres[None], axis=2), axis=1)
        for k in (0, 1):
            if np.any(labels == k):
                centres[k] = sample[labels == k].mean(axis=0)
    return labels


def _floor_models(sample: F64, min_share: float, min_sample: int) -> list[tuple[F64, F64]]:
    """The floor's colour models: the whole sample's, and (several floors in view: an apartment camera sees
    other rooms through doorways) each of its two 2-means clusters holding at least ``min_share`` of it."""
    models = [_robust_model(sample)]
    if min_share <= 0.5 and len(sample) >= 2 * min_sample:
        labels = _two_means(sample)
        for k in (0, 1):
            part = sample[labels == k]
            if len(part) >= max(min_share * len(sample), min_sample / 2):
                models.append(_robust_model(part))
    return models


def _floor_looking(cols: list[tuple[F64, F64] | None], image: np.ndarray, p: SingleViewParams,
                   min_sample: int = 30, max_sigma: float | None = None) -> list[tuple[F64, F64] | None]:
    """Floor columns whose pixels just below look like those below all floor columns of the view (Lab, median
    and robust spread, within ``max_sigma`` (default ``p.floor_colour_sigma``) of any of ``_floor_models``):
    contacts seen against a wall are dropped. Too small a sample keeps all."""
    sigma = p.floor_colour_sigma if max_sigma is None else max_sigma
    h = image.shape[0]
    picks = [(u.astype(int), np.minimum(v.astype(int) + 3, h - 1)) for u, v in (c for c in cols if c is not None)]
    if sum(len(u) for u, _ in picks) < min_sample:
        return cols
    lab = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2LAB).astype(np.float64)
    sample = np.concatenate([lab[v, u] for u, v in picks])
    models = _floor_models(sample, p.floor_cluster_share, min_sample)
    out: list[tuple[F64, F64] | None] = []
    for c in cols:
        if c is None:
            out.append(None)
            continue
        u, v = c
        x = lab[np.minimum(v.astype(int) + 3, h - 1), u.astype(int)]
        ok = np.zeros(len(x), bool)
        for mu, sd in models:
            ok |= (np.abs(x - mu) / sd).max(axis=1) <= sigma
        out.append((u[ok], v[ok]))
    return out


def _other_floor(geo: tuple[F64, F64] | None, seen: tuple[F64, F64] | None, mask: np.ndarray, owner: np.ndarray,
                 image: np.ndarray, p: SingleViewParams) -> tuple[F64, F64] | None:
    """The floor columns ``seen`` that passed the floor-colour test, or, when too few did, all the geometric
    floor columns ``geo`` if what lies under them is unlike what lies just above the object's top in the same
    columns (the background there, ``p.floor_colour_sigma`` robust sigmas apart in Lab): the object stands on
    a floor the view's other objects do not (another room's, seen through a doorway), not in front of a wall
    that goes on above and below it (a TV on a wall bracket)."""
    if geo is None or seen is None or len(seen[0]) >= p.min_contact_columns or len(geo[0]) < p.min_contact_columns:
        return seen
    h = image.shape[0]
    u = geo[0].astype(int)
    lab = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2LAB).astype(np.float64)
    under = lab[np.minimum(geo[1].astype(int) + 3, h - 1), u]
    rows = np.maximum(np.argmax(mask[:, u], axis=0) - 3, 0)  # just above each column's top pixel
    bg = owner[rows, u] == -1
    if int(bg.sum()) < p.min_contact_columns:
        return seen
    mu, sd = _robust_model(under)
    apart = float(np.max(np.abs(np.median(lab[rows[bg], u[bg]], axis=0) - mu) / sd))
    return geo if apart > p.floor_colour_sigma else seen


def box_from_contacts(pts: F64, mask: np.ndarray, others: np.ndarray, K: F64, T_world_cam: F64, support: int,
                      p: SingleViewParams = SingleViewParams()) -> PlacedBox | None:
    """The upright box standing on the contact points ``pts`` (N, 3; where the mask's lowest pixels meet
    its support) whose silhouette best matches the mask and whose top reaches its top row (``_fit_box``);
    pixels of ``others`` (other masks, which may hide the object) count neither way. None when no
    footprint fits."""
    top_v = float(np.flatnonzero(mask.any(axis=1))[0]) - 0.5  # the top edge of the top pixel
    return _fit_box(pts, support, mask, others, top_v, K, invert(T_world_cam), T_world_cam[:3, 3], p)


def _floor_points(us: F64, vs: F64, K: F64, R: F64, t: F64, p: SingleViewParams) -> F64 | None:
    """Where the floor columns' rays meet the floor (through the bottom edge of each lowest pixel)."""
    if len(us) == 0:
        return None
    d = pixel_rays(K, us, vs + 0.5) @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (p.floor_z_m - t[2]) / d[:, 2]
    ok = np.isfinite(s) & (s > 0) & (s * np.linalg.norm(d, axis=1) <= p.max_range_m)
    return (t + s[ok, None] * d[ok]) if ok.any() else None


def _support_points(us: F64, vs: F64, below: np.ndarray, boxes: Sequence[PlacedBox | None], K: F64, R: F64,
                    t: F64, p: SingleViewParams) -> tuple[F64 | None, int]:
    """Where the rays just under a mask enter the placed box below it: its top (a vase on a table) or its
    front (a book in a shelf; also an object hidden behind a nearer one, which is then placed too close: one
    view cannot tell the two apart)."""
    sup = below[below >= 0]
    sup = sup[[boxes[int(j)] is not None for j in sup]] if len(sup) else sup
    if len(sup) < p.min_contact_columns:
        return None, -1
    j = int(np.bincount(sup).argmax())
    box = boxes[j]
    assert box is not None
    sel = below == j
    d = pixel_rays(K, us[sel], vs[sel] + 1.0) @ R.T
    s = ray_box_depth(t, d, box)
    ok = np.isfinite(s)
    return (t + s[ok, None] * d[ok]) if ok.any() else None, j


def layout_depth(masks: Sequence[np.ndarray], boxes: Sequence[PlacedBox | None], K: F64, T_world_cam: F64,
                 confidence: float = 0.4) -> tuple[F32, F32]:
    """Depth (z, metres; 0 = none) and confidence maps from placed boxes: each mask pixel's ray cast into its
    box, the box centre's depth where the ray misses it. Masks are (H, W) bool at the resolution of ``K``."""
    if not masks:
        raise ValueError("layout_depth needs at least one mask")
    h, w = masks[0].shape
    depth = np.zeros((h, w), np.float32)
    conf = np.zeros((h, w), np.float32)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    for m, box in zip(masks, boxes, strict=True):
        if box is None:
            continue
        vs, us = np.nonzero(m & (depth == 0))
        if len(us) == 0:
            continue
        d = pixel_rays(K, us.astype(float), vs.astype(float)) @ R.T
        s = ray_box_depth(t, d, box)
        centre_z = float(R[:, 2] @ (box.center - t))
        s = np.where(np.isfinite(s), s, centre_z)
        ok = s > 0
        depth[vs[ok], us[ok]] = s[ok]
        conf[vs[ok], us[ok]] = confidence
    return depth, conf


def depth_to_world(depth_m: F32, K: F64, T_world_cam: F64) -> F32:
    """(H, W, 3) world points of a z-depth map (pixels without depth give the camera centre)."""
    h, w = depth_m.shape
    vs, us = np.mgrid[0:h, 0:w]
    rays = pixel_rays(K, us.reshape(-1).astype(float), vs.reshape(-1).astype(float))
    # A contiguous copy of the rotation: numpy multiplies by a strided (transposed 4x4 slice) matrix in a
    # generic loop ~100x slower than with a contiguous one, for the same result bit for bit.
    R_t = np.ascontiguousarray(T_world_cam[:3, :3].T)
    pts = (rays * depth_m.reshape(-1, 1)) @ R_t + T_world_cam[:3, 3]
    return pts.reshape(h, w, 3).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Free space seen by other calibrated cameras


def _on_grid(mask: np.ndarray, h: int, w: int) -> NDArray[np.bool_]:
    """``mask`` as an (h, w) boolean mask (nearest-neighbour resize when it is at another resolution)."""
    m = np.asarray(mask, bool)
    if m.shape == (h, w):
        return m
    return cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


@dataclass(frozen=True)
class SeenView:
    """What one calibrated camera saw, kept small to check other cameras' coarse placements against:
    ``owner`` (h, w) is the index of the detection covering each pixel (-1: nothing detected), ``floor`` (h, w)
    whether such a pixel looks like the floor next to the camera (so the camera saw the floor there, at a
    known depth, and nothing in front of it), ``descriptors`` (n, d) the detections' unit descriptors; ``K``
    is at the maps' size."""

    K: F64
    T_world_cam: F64
    owner: np.ndarray
    floor: np.ndarray
    descriptors: F32
    floor_z_m: float = 0.0
    people: np.ndarray | None = None  # (n,) bool: which detections are people; None: not known

    @classmethod
    def build(cls, image: np.ndarray, masks: Sequence[np.ndarray], descriptors: Sequence[np.ndarray], K: F64,
              T_world_cam: F64, floor_masks: Sequence[np.ndarray] = (), floor_z_m: float = 0.0, width: int = 160,
              max_colour_sigma: float = 3.0, people: Sequence[bool] | None = None) -> SeenView:
        """``image`` (H, W, 3) RGB and ``masks`` (H, W) at the resolution of ``K``; ``people``: which of them
        are people (None: not known). The floor's look is learnt
        from the undetected pixels just under ``floor_masks`` (the objects placed standing on the floor: what
        lies at their feet is floor); undetected pixels within ``max_colour_sigma`` robust standard deviations
        of it (Lab) count as floor. A wall, or another room seen through a doorway, differs and refutes
        nothing; with no floor-standing object nothing counts as floor."""
        h, w = image.shape[:2]
        sh = max(1, round(h * width / w))
        # Masks may come at another resolution than the image (a segmenter working at half size): bring them
        # to the image's grid first.
        masks = [_on_grid(m, h, w) for m in masks]
        floor_masks = [_on_grid(m, h, w) for m in floor_masks]
        owner = np.full((h, w), -1, np.int16)
        for i, m in enumerate(masks):
            owner[m & (owner < 0)] = i
        small = cv2.resize(owner, (width, sh), interpolation=cv2.INTER_NEAREST)
        lab = cv2.cvtColor(cv2.resize(image, (width, sh), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2LAB)
        Ks = K.copy()
        Ks[0] *= width / w
        Ks[1] *= sh / h
        feet = np.zeros((h, w), bool)
        for m in floor_masks:
            # a few pixels under the mask, where the object stands
            below = np.zeros_like(m)
            for k in range(2, 6):
                below[k:] |= m[:-k]
            feet |= below & (owner < 0)
        near = cv2.resize(feet.astype(np.uint8), (width, sh), interpolation=cv2.INTER_NEAREST).astype(bool)
        floor = np.zeros((sh, width), bool)
        if int(near.sum()) >= 20:
            x = lab.reshape(-1, 3).astype(np.float64)
            sample = x[near.reshape(-1)]
            mu = np.median(sample, axis=0)
            sd = np.clip(1.4826 * np.median(np.abs(sample - mu), axis=0), 2.0, 12.0)
            floor = ((np.abs(x - mu) / sd).max(axis=1) <= max_colour_sigma).reshape(sh, width) & (small < 0)
        desc = (np.stack([np.asarray(v, np.float32) for v in descriptors]) if len(descriptors)
                else np.zeros((0, 1), np.float32))
        who = None if people is None else np.asarray(people, bool).reshape(len(masks))
        return cls(Ks, T_world_cam.copy(), small, floor, desc, floor_z_m, who)

    def _pixels(self, points: F64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pixels (u, v: int) and depths (z) of the world ``points`` that project into this view, in front."""
        R, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        pc = (np.asarray(points, np.float64) - t) @ R
        h, w = self.owner.shape
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(pc[:, 0] / z * self.K[0, 0] + self.K[0, 2])
            v = np.round(pc[:, 1] / z * self.K[1, 1] + self.K[1, 2])
        ok = (z > 0.1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        return u[ok].astype(int), v[ok].astype(int), z[ok]

    def _similar(self, own: np.ndarray, descriptor: np.ndarray, min_similarity: float) -> np.ndarray:
        """Whether each owner index ``own`` (-1: none) is a detection with a descriptor like ``descriptor``."""
        same = np.zeros(len(own), bool)
        if len(self.descriptors) and (own >= 0).any():
            sims = self.descriptors @ np.asarray(descriptor, np.float32)
            same[own >= 0] = sims[own[own >= 0]] >= min_similarity
        return same

    def votes(self, points: F64, descriptor: np.ndarray, min_similarity: float, margin_m: float = 0.1,
              ) -> tuple[int, int, int]:
        """For world points of one object: how many project into this view (in front of it), how many land
        where this camera saw the floor behind them (free space: the object cannot be there) and how many land
        on a detection with a similar descriptor (it saw the object there)."""
        u, v, z = self._pixels(points)
        if len(u) == 0:
            return 0, 0, 0
        R, t = self.T_world_cam[:3, :3], self.T_world_cam[:3, 3]
        d = pixel_rays(self.K, u.astype(float), v.astype(float)) @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            floor = (self.floor_z_m - t[2]) / d[:, 2]
        free = self.floor[v, u] & (floor > 0) & (z < floor - margin_m)
        same = self._similar(self.owner[v, u], descriptor, min_similarity)
        return len(u), int(free.sum()), int(same.sum())

    def coverage(self, points: F64, descriptor: np.ndarray, min_similarity: float) -> Coverage:
        """Where the world ``points`` of one object land in this view (:class:`Coverage`)."""
        u, v, z = self._pixels(points)
        if len(u) == 0:
            return Coverage(0, 0, 0, 0, math.inf)
        same, other, people = self._tally(self.owner[v, u], descriptor, min_similarity)
        return Coverage(len(u), len(np.unique(v * self.owner.shape[1] + u)), same, other, float(np.median(z)), people)

    def coverage_pixels(self, pixels: np.ndarray, descriptor: np.ndarray, min_similarity: float) -> Coverage:
        """What this view shows at ``pixels`` (flat indices on its grid: where this camera detected an object
        before, :meth:`mapper.fusion.ObjectMap.remember_pixels`): a :class:`Coverage` counted in pixels (``points``
        = ``pixels``; no depth)."""
        px = np.asarray(pixels, np.int64).reshape(-1)
        px = px[(px >= 0) & (px < self.owner.size)]
        if len(px) == 0:
            return Coverage(0, 0, 0, 0, math.inf)
        same, other, people = self._tally(self.owner.reshape(-1)[px], descriptor, min_similarity)
        return Coverage(len(px), len(px), same, other, math.inf, people)

    def _tally(self, own: np.ndarray, descriptor: np.ndarray, min_similarity: float) -> tuple[int, int, int | None]:
        """Of owner indices ``own`` (-1: nothing detected): how many are on a detection like ``descriptor``, how
        many on another one, and how many of those on a person (None: the view does not know its people)."""
        same = self._similar(own, descriptor, min_similarity)
        other = (own >= 0) & ~same
        people = None
        if self.people is not None:
            people = int((other & self.people[np.maximum(own, 0)]).sum()) if len(self.people) else 0
        return int(same.sum()), int(other.sum()), people


@dataclass(frozen=True)
class Coverage:
    """How an object's points land in a :class:`SeenView`: how many project into it (in front), on how many
    distinct pixels (at the view's width), how many on a detection with a similar descriptor (seen there), how
    many on another detection (something else in front, or under: no evidence either way), their median
    depth (metres), and how many of ``other`` are on a person (None: the view does not know its people)."""

    points: int
    pixels: int
    same: int
    other: int
    depth_m: float
    people: int | None = None


def relocate_along_ray(points: F64, origin: F64, descriptor: np.ndarray, views: Sequence[SeenView],
                       min_similarity: float, max_range_m: float = 12.0, step_m: float = 0.05,
                       min_agree: float = 0.3, max_free: float = 0.3, below_floor_m: float = 0.05) -> F64 | None:
    """Where along the ray from ``origin`` through the points' centroid the object agrees best with
    ``views`` (most points on similar detections, few in free space): the shift to apply to the points,
    or None when no depth reaches ``min_agree`` with at most ``max_free`` in free space. Depths that would
    put the object's lowest point more than ``below_floor_m`` under the views' floor are not tried: a ray
    that goes on under the floor meets nothing (another object of the same kind, seen by another camera
    elsewhere along the ray's line of sight, agrees there only by chance)."""
    pts = np.asarray(points, np.float64)
    c = pts.mean(axis=0)
    ray = c - origin
    dist = float(np.linalg.norm(ray))
    if dist < 1e-6:
        return None
    ray /= dist
    floor = min((sv.floor_z_m for sv in views), default=-np.inf)
    low = float(pts[:, 2].min()) - float(c[2])  # the lowest point under the centroid
    best: tuple[float, float] | None = None
    for s in np.arange(0.3, max_range_m, step_m):
        if origin[2] + s * ray[2] + low < floor - below_floor_m:
            continue
        shifted = points + (origin + s * ray - c)
        n = agree = free = 0
        for sv in views:
            a, f, g = sv.votes(shifted, descriptor, min_similarity)
            n, free, agree = n + a, free + f, agree + g
        if n == 0 or free > max_free * n:
            continue
        frac = agree / n
        if frac >= min_agree and (best is None or frac > best[0] + 1e-9 or
                                  (abs(frac - best[0]) <= 1e-9 and abs(s - dist) < abs(best[1] - dist))):
            best = (frac, float(s))
    return None if best is None else (origin + best[1] * ray - c)
