"""Objects placed on the level surface measured under their masks (mapper.geometry.support)."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.geometry.singleview import PlacedBox, pixel_rays, ray_box_depth
from mapper.geometry.support import MappedTop, measured_support, place_on_mapped_support, place_on_measured_support
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(320, 240, 70.0)
K = INTR.K()
T = look_at([0.0, 0.0, 1.4], [0.0, 2.0, 0.75])  # a robot camera looking down at a table top
TRUE = PlacedBox(np.array([0.1, 2.0, 0.75 + 0.125]), np.array([0.2, 0.2, 0.25]), 0.3, -1, 0)


def _rays() -> np.ndarray:
    vs, us = np.mgrid[0:240, 0:320].astype(float)
    return pixel_rays(K, us.ravel(), vs.ravel()) @ T[:3, :3].T


def _scene(surface: str = "table") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mask of the box, world points of what each pixel sees behind it (a level table top at 0.75 m or
    a wall at y = 2.1 m), and where that surface has confident depth (none on the object itself)."""
    d, t = _rays(), T[:3, 3]
    box_s = ray_box_depth(t, d, TRUE)
    mask = np.isfinite(box_s).reshape(240, 320)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (0.75 - t[2]) / d[:, 2] if surface == "table" else (2.1 - t[1]) / d[:, 1]
    pts = (t + s[:, None] * d).reshape(240, 320, 3)
    valid = (np.isfinite(s) & (s > 0)).reshape(240, 320) & ~mask
    return mask, pts, valid


def test_an_object_without_depth_stands_on_the_table_measured_under_it() -> None:
    mask, pts, valid = _scene()
    found = measured_support(mask, pts, valid)
    assert found is not None and found[0] == pytest.approx(0.75, abs=1e-6)
    box = place_on_measured_support(mask, np.zeros_like(mask), pts, valid, K, T)
    assert box is not None
    assert box.center[2] - 0.5 * box.extent[2] == pytest.approx(0.75, abs=0.01)  # its base on the table
    assert box.extent[2] == pytest.approx(0.25, abs=0.05)
    assert np.linalg.norm(box.center[:2] - TRUE.center[:2]) < 0.1


def test_no_level_surface_no_placement() -> None:
    mask, pts, valid = _scene("wall")  # a picture on a wall: what lies under it is the wall, not level
    assert measured_support(mask, pts, valid) is None
    mask, pts, _ = _scene()
    assert measured_support(mask, pts, np.zeros_like(mask)) is None  # the table has no confident depth either
    cut = np.zeros_like(mask)
    cut[200:, 100:140] = True  # an object cut by the image's bottom border: nothing under it is seen
    assert measured_support(cut, pts, np.ones_like(mask)) is None


TABLE = MappedTop(np.array([0.0, 2.2]), np.array([0.6, 0.45]), 0.0, 0.75)


def _table_mask() -> np.ndarray:
    """Pixels whose rays meet the table's top face (the table top seen in the image), outside the object."""
    d, t = _rays(), T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (0.75 - t[2]) / d[:, 2]
    P = t + s[:, None] * d
    on = (s > 0) & (np.abs(P[:, 0] - 0.0) <= 0.6) & (np.abs(P[:, 1] - 2.2) <= 0.45)
    return on.reshape(240, 320)


def test_an_object_stands_on_the_mapped_table_when_nothing_under_it_has_depth() -> None:
    mask, _, _ = _scene()
    table = _table_mask() & ~mask
    box = place_on_mapped_support(mask, table, [TABLE], K, T)
    assert box is not None
    assert box.center[2] - 0.5 * box.extent[2] == pytest.approx(0.75, abs=0.01)
    assert np.linalg.norm(box.center[:2] - TRUE.center[:2]) < 0.1
    # What lies under it is no object's mask (the floor, a wall): no mapped support is assumed.
    assert place_on_mapped_support(mask, np.zeros_like(mask), [TABLE], K, T) is None
    # A table elsewhere is no support.
    far = MappedTop(np.array([2.0, 4.0]), np.array([0.6, 0.45]), 0.0, 0.75)
    assert place_on_mapped_support(mask, table, [far], K, T) is None
    # A large object whose lowest pixels end on the table top is not stood on it.
    assert place_on_mapped_support(mask, table, [TABLE], K, T, max_side_m=0.1) is None
