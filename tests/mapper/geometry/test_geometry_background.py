"""Single-view placements behind the depth their own view measured around them (mapper.geometry.background)."""

from __future__ import annotations

import numpy as np

from mapper.geometry.background import behind_background, ring_depths
from mapper.geometry.singleview import PlacedBox, pixel_rays, ray_box_depth
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(320, 240, 70.0)
K = INTR.K()
T = look_at([0.0, 0.0, 1.2], [0.0, 3.0, 1.0])  # looking at a wall 3 m away (y = 3)
WALL_Y = 3.0


def _box(y: float) -> PlacedBox:
    """A 0.4 m monitor-sized box straight ahead, its centre at depth ~``y``."""
    return PlacedBox(np.array([0.0, y, 1.0]), np.array([0.4, 0.2, 0.4]), 0.0, -1, 0)


def _mask_and_wall() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mask of the box as seen at 2 m, and the wall's z-depth everywhere with confidence 1."""
    vs, us = np.mgrid[0:240, 0:320].astype(float)
    cam_rays = pixel_rays(K, us.ravel(), vs.ravel())
    d = cam_rays @ T[:3, :3].T
    t = T[:3, 3]
    mask = np.isfinite(ray_box_depth(t, d, _box(2.0))).reshape(240, 320)
    s = (WALL_Y - t[1]) / d[:, 1]  # ray parameter to the wall; rays have camera z = 1, so s is z-depth
    return mask, s.reshape(240, 320).astype(np.float32), np.ones((240, 320), np.float32)


def _behind(box: PlacedBox, depth: np.ndarray, conf: np.ndarray, mask: np.ndarray) -> bool:
    return behind_background(box, mask, depth, conf, K, T, min_confidence=0.5)


def test_a_placement_behind_the_wall_seen_around_it_is_refused() -> None:
    mask, depth, conf = _mask_and_wall()
    assert _behind(_box(7.0), depth, conf, mask)  # read as standing on the floor 7 m away: through the wall
    assert not _behind(_box(2.0), depth, conf, mask)  # in front of the wall: fine
    assert not _behind(_box(3.05), depth, conf, mask)  # against the wall, within the margin: fine


def test_occluders_in_front_do_not_hide_the_wall_behind() -> None:
    mask, depth, conf = _mask_and_wall()
    near = depth.copy()
    near[:, :150] = 1.0  # half the ring is an object in front (a chair back at 1 m)
    assert not _behind(_box(2.0), near, conf, mask)
    assert _behind(_box(7.0), near, conf, mask)


def test_no_confident_depth_around_the_mask_says_nothing() -> None:
    mask, depth, conf = _mask_and_wall()
    assert not _behind(_box(7.0), depth, np.zeros_like(conf), mask)  # a textureless wall: no evidence
    holes = depth.copy()
    holes[:] = np.nan
    assert not _behind(_box(7.0), holes, conf, mask)


def test_the_ring_leaves_the_mask_out() -> None:
    mask, depth, conf = _mask_and_wall()
    depth = np.where(mask, 10.0, depth).astype(np.float32)  # the mask's own depth is never its background
    around = ring_depths(mask, depth, conf, 0.5, 8)
    assert len(around) > 0 and float(around.max()) < 4.0
