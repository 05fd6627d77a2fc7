"""Objects placed on a measured surface (pure numpy, no I/O).

Stereo often gives a small or textureless object no confident depth of its own (a picture frame on a
dresser, a bowl on a table) while the surface it stands on has some: the pixels just under the object's
mask, where its lowest pixels meet its support. When those pixels' 3D points are level (the plane through
them faces up, within ``max_tilt_deg``, and they keep one height within ``max_spread_m``), the object
stands on that plane: the rays through its lowest pixels meet the plane at
its contact points, and ``singleview.box_from_contacts`` makes the upright box that stands there and
reaches the mask's top row. The estimate is coarse (like the floor placement of single-view geometry),
but measured: the plane comes from this keyframe's own depth, not from a guess below a guess.

Where the surface under the object has no confident depth either (a plain dresser top), the map may
still know it: ``place_on_mapped_support`` stands the object on the top face of the mapped node (a
measured node's box) that the rays through its lowest pixels meet first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapper.geometry.singleview import PlacedBox, SingleViewParams, box_from_contacts, lowest_pixels, pixel_rays

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SupportParams:
    """What counts as a measured level surface under a mask."""

    band_px: int = 4  # rows under each column's lowest mask pixel that may show the support
    min_columns: int = 3  # contact columns with a measured support point
    max_spread_m: float = 0.03  # half the inter-quartile range of the support points' heights
    max_tilt_deg: float = 25.0  # the plane through the band's points: its normal this close to vertical
    min_width_m: float = 0.02  # ... and the points must span this much both ways (else the plane is undecided)


def measured_support(mask: np.ndarray, points_world: np.ndarray, valid: np.ndarray,
                     p: SupportParams = SupportParams()) -> tuple[float, F64, F64] | None:
    """Height of the level surface just under ``mask`` (H, W bool) from the confident points
    (``points_world`` (H, W, 3) where ``valid``), and the mask's contact columns over it (u, v of each
    column's lowest pixel); None when too few columns see a support or it is not level."""
    h = mask.shape[0]
    cols, low = lowest_pixels(mask, border_px=0)  # a column ending on the last row has nothing under it
    us, vs, zs, band = [], [], [], []
    for c, r in zip(cols, low, strict=True):
        rows = np.arange(r + 1, min(r + 1 + p.band_px, h))
        rows = rows[valid[rows, c] & ~mask[rows, c]]
        if len(rows) == 0:
            continue
        us.append(float(c))
        vs.append(float(r))
        zs.append(float(points_world[rows[0], c, 2]))  # the first measured pixel under the object
        band.append(points_world[rows, c])
    if len(zs) < p.min_columns:
        return None
    q1, med, q3 = np.percentile(zs, [25, 50, 75])
    if 0.5 * (q3 - q1) > p.max_spread_m or not _faces_up(np.concatenate(band), p):
        return None
    return float(med), np.asarray(us), np.asarray(vs)


def _faces_up(points: F64, p: SupportParams) -> bool:
    """Whether the plane through ``points`` (N, 3) is level: a wall under a picture is not."""
    if len(points) < 3:
        return False
    evals, evecs = np.linalg.eigh(np.cov((points - points.mean(axis=0)).T))
    if float(np.sqrt(max(evals[1], 0.0))) < 0.5 * p.min_width_m:  # on a line: no plane to judge
        return False
    return abs(float(evecs[2, 0])) >= float(np.cos(np.radians(p.max_tilt_deg)))


def place_on_measured_support(mask: np.ndarray, others: np.ndarray, points_world: np.ndarray, valid: np.ndarray,
                              K: F64, T_world_cam: F64, sv: SingleViewParams | None = None,
                              p: SupportParams = SupportParams()) -> PlacedBox | None:
    """The upright box of ``mask`` standing on the level surface measured under it (see the module
    docstring), or None; masks, points and ``K`` at one resolution."""
    sv = sv or SingleViewParams()
    found = measured_support(mask, points_world, valid, p)
    if found is None:
        return None
    z, us, vs = found
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = pixel_rays(K, us, vs + 0.5) @ R.T  # through the bottom edge of each lowest pixel
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z - t[2]) / d[:, 2]
    ok = np.isfinite(s) & (s > 0) & (s * np.linalg.norm(d, axis=1) <= sv.max_range_m)
    if int(ok.sum()) < p.min_columns:
        return None
    pts = t + s[ok, None] * d[ok]
    return box_from_contacts(pts, mask, others, K, T_world_cam, -1, sv)


@dataclass(frozen=True)
class MappedTop:
    """The top face of a mapped node's gravity-aligned box: centre (x, y), half extents, yaw and height."""

    centre_xy: F64
    half_xy: F64
    yaw_rad: float
    z: float


def place_on_mapped_support(mask: np.ndarray, others: np.ndarray, tops: list[MappedTop], K: F64, T_world_cam: F64,
                            sv: SingleViewParams | None = None, p: SupportParams = SupportParams(),
                            margin_m: float = 0.05, max_side_m: float = 0.45) -> PlacedBox | None:
    """The upright box of ``mask`` standing on the mapped top face that most of the rays through its lowest
    pixels meet first (within ``margin_m`` of the face's footprint), or None when fewer than ``min_columns``
    rays meet one face. Only columns whose pixels just below belong to another object's mask (``others``)
    count: a support is an object too; and only small objects are placed (no side over ``max_side_m``): a
    large one whose lowest pixels end on a table top is more likely standing behind it."""
    sv = sv or SingleViewParams()
    cols, low = lowest_pixels(mask)
    h = mask.shape[0]
    under = np.zeros(len(cols), bool)
    for k in range(1, p.band_px + 1):
        under |= others[np.minimum(low + k, h - 1), cols]
    us, vs = cols[under].astype(np.float64), low[under].astype(np.float64)
    if len(us) < p.min_columns or not tops:
        return None
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = pixel_rays(K, us, vs + 0.5) @ R.T
    best_s = np.full(len(us), np.inf)
    best_j = np.full(len(us), -1)
    for j, top in enumerate(tops):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (top.z - t[2]) / d[:, 2]
        P = t[:2] + s[:, None] * d[:, :2] - top.centre_xy
        c, sn = np.cos(top.yaw_rad), np.sin(top.yaw_rad)
        local = np.stack([c * P[:, 0] + sn * P[:, 1], -sn * P[:, 0] + c * P[:, 1]], axis=1)
        hit = (np.isfinite(s) & (s > 0) & np.all(np.abs(local) <= top.half_xy + margin_m, axis=1)
               & (s * np.linalg.norm(d, axis=1) <= sv.max_range_m))
        closer = hit & (s < best_s)
        best_s[closer], best_j[closer] = s[closer], j
    if int((best_j >= 0).sum()) < p.min_columns:
        return None
    j = int(np.bincount(best_j[best_j >= 0]).argmax())
    sel = best_j == j
    if int(sel.sum()) < p.min_columns:
        return None
    pts = t + best_s[sel, None] * d[sel]
    box = box_from_contacts(pts, mask, others, K, T_world_cam, -1, sv)
    return box if box is not None and float(np.max(box.extent)) <= max_side_m else None
