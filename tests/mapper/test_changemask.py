"""A fixed camera's changed cells, people left out (mapper.changemask)."""

from __future__ import annotations

import numpy as np

from mapper.changemask import GRID, ChangeMask, cells, touches
from protocol.poses import look_at

H, W = 240, 320  # 10 x 10 px per thumbnail cell
T = look_at([0.0, 0.0, 2.0], [3.0, 0.0, 0.5])


def _room(seed: int = 0) -> np.ndarray:
    """A textured image, flat per thumbnail cell (so a changed patch changes exactly its cells)."""
    grid = np.random.default_rng(seed).uniform(40, 200, GRID)
    return np.repeat(np.repeat(grid, 10, 0), 10, 1)[..., None].repeat(3, 2).astype(np.uint8)


def _box(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """A mask over thumbnail cells rows r0..r1-1, columns c0..c1-1."""
    m = np.zeros((H, W), bool)
    m[10 * r0:10 * r1, 10 * c0:10 * c1] = True
    return m


def _paint(img: np.ndarray, m: np.ndarray, value: int) -> np.ndarray:
    out = img.copy()
    out[m] = value
    return out


def test_the_first_keyframe_is_all_new_and_an_unchanged_one_changes_nothing() -> None:
    cm = ChangeMask()
    assert cm.update("cam", T, 1, _room(), []) is None
    changed = cm.update("cam", T, 2, _room(), [])
    assert changed is not None and changed.shape == GRID and not changed.any()


def test_a_moved_object_changes_its_cells_only() -> None:
    cm = ChangeMask()
    room = _room()
    chair = _box(10, 14, 5, 8)
    cm.update("cam", T, 1, _paint(room, chair, 250), [])
    moved = _box(10, 14, 20, 23)
    changed = cm.update("cam", T, 2, _paint(room, moved, 250), [])
    assert changed is not None
    assert np.array_equal(changed, cells(chair) | cells(moved))
    assert touches(moved, changed) and not touches(_box(0, 3, 0, 3), changed)


def test_a_passer_by_changes_nothing_coming_or_going() -> None:
    cm = ChangeMask()
    room = _room()
    cm.update("cam", T, 1, room, [])
    person = _box(4, 20, 12, 15)
    changed = cm.update("cam", T, 2, _paint(room, person, 5), [person])
    assert changed is not None and not changed.any()
    # gone again: the background kept what the person hid
    changed = cm.update("cam", T, 3, room, [])
    assert changed is not None and not changed.any()


def test_an_object_moved_behind_a_passer_by_shows_once_the_person_left() -> None:
    cm = ChangeMask()
    room = _room()
    cm.update("cam", T, 1, room, [])
    person = _box(4, 20, 12, 16)
    bag = _box(16, 19, 13, 15)  # put down where the person stands
    changed = cm.update("cam", T, 2, _paint(_paint(room, bag, 250), person, 5), [person])
    assert changed is not None and not changed.any()
    changed = cm.update("cam", T, 3, _paint(room, bag, 250), [])
    assert changed is not None and np.array_equal(changed, cells(bag))


def test_cells_only_ever_seen_behind_a_person_are_new() -> None:
    cm = ChangeMask(person_margin_cells=0)
    room = _room()
    person = _box(4, 20, 12, 15)
    assert cm.update("cam", T, 1, _paint(room, person, 5), [person]) is None
    changed = cm.update("cam", T, 2, room, [])
    assert changed is not None and np.array_equal(changed, cells(person))


def test_a_moved_camera_starts_again_and_an_older_view_learns_nothing() -> None:
    cm = ChangeMask()
    room = _room()
    cm.update("cam", T, 5, room, [])
    assert cm.update("cam", T, 4, _room(1), []) is None  # a deferred keyframe retried: older than the background
    changed = cm.update("cam", T, 6, room, [])
    assert changed is not None and not changed.any()
    turned = look_at([0.0, 0.0, 2.0], [3.0, 0.3, 0.5])
    assert cm.update("cam", turned, 7, room, []) is None
    assert cm.update("other", T, 1, room, []) is None  # per camera


def test_backgrounds_are_bounded() -> None:
    cm = ChangeMask(max_sources=2)
    for i in range(5):
        cm.update(f"cam{i}", T, 1, _room(), [])
    assert cm.update("cam0", T, 2, _room(), []) is None  # forgotten
    assert cm.update("cam4", T, 2, _room(), []) is not None
