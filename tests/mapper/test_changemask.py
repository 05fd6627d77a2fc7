"""What changed in a fixed camera's view, people left out (mapper.changemask)."""

from __future__ import annotations

import numpy as np

from mapper.changemask import ChangeMask, small_mask
from protocol.poses import look_at

H, W = 240, 320  # the background is 160 x 120: 2 x 2 px each
T = look_at([0.0, 0.0, 2.0], [3.0, 0.0, 0.5])


def _room(seed: int = 0) -> np.ndarray:
    """A textured view, flat per 10 x 10 px block."""
    grid = np.random.default_rng(seed).uniform(40, 200, (24, 32, 3))
    return np.repeat(np.repeat(grid, 10, 0), 10, 1).astype(np.uint8)


def _box(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[r0:r1, c0:c1] = True
    return m


def _paint(img: np.ndarray, m: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    out = img.copy()
    out[m] = rgb
    return out


CHAIR = _box(100, 140, 50, 80)
ELSEWHERE = _box(100, 140, 200, 230)
PERSON = _box(40, 200, 120, 150)
RED = (230, 30, 30)


def test_the_first_keyframe_is_all_new_and_an_unchanged_one_changes_nothing() -> None:
    cm = ChangeMask()
    assert cm.update("cam", T, 1, _paint(_room(), CHAIR, RED), []) is None
    ch = cm.update("cam", T, 2, _paint(_room(), CHAIR, RED), [])
    assert ch is not None and not ch.touches(CHAIR) and not ch.touches(ELSEWHERE)


def test_a_moved_object_changed_where_it_went_and_nothing_else_did() -> None:
    cm = ChangeMask()
    cm.update("cam", T, 1, _paint(_room(), CHAIR, RED), [])
    ch = cm.update("cam", T, 2, _paint(_room(), ELSEWHERE, RED), [])
    assert ch is not None and ch.touches(ELSEWHERE) and ch.touches(CHAIR)  # its old place is floor now
    assert not ch.touches(_box(0, 30, 0, 30))


def test_an_object_of_the_floors_grey_changed_its_colour() -> None:
    """A bag put down on a floor of the same grey (the keyframe selector's grey thumbnail barely moves)."""
    floor = np.full((H, W, 3), (90, 120, 150), np.uint8)
    bag = _box(150, 165, 100, 112)  # 180 px
    grey = float(np.dot((90, 120, 150), (0.299, 0.587, 0.114)))
    cm = ChangeMask()
    cm.update("cam", T, 1, floor, [])
    ch = cm.update("cam", T, 2, _paint(floor, bag, (int(grey) + 40, int(grey) - 5, int(grey) - 30)), [])
    assert ch is not None and ch.touches(bag)


def test_a_passer_by_changes_nothing_coming_or_going() -> None:
    cm = ChangeMask()
    room = _paint(_room(), CHAIR, RED)
    cm.update("cam", T, 1, room, [])
    half = CHAIR & ~PERSON
    ch = cm.update("cam", T, 2, _paint(room, PERSON | _box(40, 200, 70, 80), (5, 5, 5)),
                   [PERSON | _box(40, 200, 70, 80)])  # in front of the chair's right edge
    assert ch is not None and not ch.touches(half) and not ch.touches(ELSEWHERE)
    ch = cm.update("cam", T, 3, room, [])  # gone again: the background kept what the person hid
    assert ch is not None and not ch.touches(CHAIR) and not ch.touches(PERSON)


def test_an_object_put_down_behind_a_passer_by_changed_once_the_person_left() -> None:
    cm = ChangeMask()
    room = _room()
    cm.update("cam", T, 1, room, [])
    bag = _box(170, 190, 125, 145)  # where the person stands
    ch = cm.update("cam", T, 2, _paint(_paint(room, bag, RED), PERSON, (5, 5, 5)), [PERSON])
    assert ch is not None and not ch.touches(bag)  # hidden: nothing to place from here
    ch = cm.update("cam", T, 3, _paint(room, bag, RED), [])
    assert ch is not None and ch.touches(bag)


def test_what_was_only_ever_seen_behind_a_person_is_new() -> None:
    cm = ChangeMask(person_margin_px=0)
    room = _room()
    assert cm.update("cam", T, 1, _paint(room, PERSON, (5, 5, 5)), [PERSON]) is None
    ch = cm.update("cam", T, 2, room, [])
    assert ch is not None and ch.touches(PERSON) and not ch.touches(CHAIR)


def test_a_moved_camera_starts_again_and_an_older_view_learns_nothing() -> None:
    cm = ChangeMask()
    room = _room()
    cm.update("cam", T, 5, room, [])
    assert cm.update("cam", T, 4, _room(1), []) is None  # a deferred keyframe retried: older than the background
    ch = cm.update("cam", T, 6, room, [])
    assert ch is not None and not ch.touches(CHAIR)
    turned = look_at([0.0, 0.0, 2.0], [3.0, 0.3, 0.5])
    assert cm.update("cam", turned, 7, room, []) is None
    assert cm.update("other", T, 1, room, []) is None  # per camera


def test_backgrounds_are_bounded() -> None:
    cm = ChangeMask(max_sources=2)
    for i in range(5):
        cm.update(f"cam{i}", T, 1, _room(), [])
    assert cm.update("cam0", T, 2, _room(), []) is None  # forgotten
    assert cm.update("cam4", T, 2, _room(), []) is not None


def test_small_masks_keep_a_pixel() -> None:
    tiny = np.zeros((H, W), bool)
    tiny[101, 51] = True
    assert small_mask(tiny, (120, 160)).sum() == 1
    assert small_mask(CHAIR, (120, 160)).sum() == 20 * 15
