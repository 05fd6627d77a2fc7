"""Source-view selection by parallax (mapper.geometry.viewselect) and the keyframe policy built on it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mapper.config import KeyframeConfig
from mapper.geometry.contract import View
from mapper.geometry.viewselect import Candidate, overlap_fraction, score_sources, select_sources, triangulation_deg
from mapper.keyframes import KeyframeSelector, KeyframeStore
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(320, 240, 70.0)
TARGET = np.array([0.0, 3.0, 1.0])  # the surface everyone looks at, 3 m in front of the reference


def cam(x: float, y: float = 0.0, z: float = 1.0, target: np.ndarray = TARGET) -> np.ndarray:
    return look_at([x, y, z], target)


def test_triangulation_angle_exact() -> None:
    assert triangulation_deg(2.0, 1.0) == pytest.approx(90.0)
    assert triangulation_deg(0.0, 1.0) == 0.0


def test_overlap_fraction_in_front_and_behind() -> None:
    T = cam(0.0)
    ahead = np.array([[0.0, 3.0, 1.0], [0.0, 2.0, 1.0]])
    behind = np.array([[0.0, -3.0, 1.0]])
    assert overlap_fraction(ahead, T, INTR) == 1.0
    assert overlap_fraction(behind, T, INTR) == 0.0
    assert overlap_fraction(np.zeros((0, 3)), T, INTR) == 0.0


def test_picks_parallax_neighbours_from_a_mixed_robot_and_fixed_camera_set() -> None:
    """A robot's video frames 1 cm apart give no parallax; the robot keyframe 30 cm away and the calibrated
    fixed camera on the wall that sees the same surface do. A camera looking elsewhere is no source."""
    ref = cam(0.0)
    cands = [
        Candidate(0, cam(0.01), INTR),  # robot video frame, 1 cm: 0.2 deg at 3 m
        Candidate(1, cam(0.02), INTR),  # 2 cm
        Candidate(2, cam(0.30), INTR),  # robot keyframe 30 cm away: 5.7 deg
        Candidate(3, cam(-0.6, 0.3, 1.8), INTR),  # fixed camera high on the wall, same surface: ~19 deg
        Candidate(4, look_at([0.6, 0.0, 1.0], [3.0, 0.0, 1.0]), INTR),  # looks the other way
        Candidate(5, cam(3.0, 0.0, 1.0), INTR),  # 3 m to the side: ~53 deg, too wide to match
    ]
    chosen = select_sources(ref, INTR, 3.0, cands, k=3)
    assert {s.index for s in chosen} == {2, 3}
    scores = {s.index: s for s in score_sources(ref, INTR, 3.0, cands)}
    assert 0 not in scores and 1 not in scores and 4 not in scores and 5 not in scores
    assert scores[2].triangulation_deg == pytest.approx(triangulation_deg(0.30, 3.0), rel=1e-9)


def test_redundant_sources_are_skipped() -> None:
    ref = cam(0.0)
    cands = [Candidate(0, cam(0.30), INTR), Candidate(1, cam(0.305), INTR), Candidate(2, cam(-0.30), INTR)]
    chosen = select_sources(ref, INTR, 3.0, cands, k=2)
    # 0 and 1 are one direction (5 mm apart); the second source is the one on the other side.
    assert sorted(s.index for s in chosen) in ([0, 2], [1, 2])


def _view(T: np.ndarray, seq: int, source: str = "robot") -> View:
    img = np.random.default_rng(seq).integers(0, 255, (240, 320, 3), dtype=np.uint8)
    return View(img, source, INTR, T, seq=seq, stamp_ns=seq * 33_000_000)


def test_video_rate_frames_become_keyframes_by_parallax_not_arrival() -> None:
    cfg = KeyframeConfig(min_baseline_ratio=0.05, assumed_depth_m=1.0, min_translation_m=10.0)
    sel = KeyframeSelector(cfg)
    # ~1 cm per frame: with a 1 m scene depth a keyframe every 5 cm.
    kf = [k for k in range(21) if sel.consider(_view(cam(0.0101 * k), k))]
    assert kf == [0, 5, 10, 15, 20]
    # Once the source's depth is known to be 2 m, keyframes come every 10 cm.
    sel.observe_depth("robot", 2.0)
    kf2 = [k for k in range(21, 61) if sel.consider(_view(cam(0.0101 * k), k))]
    assert kf2 == [30, 40, 50, 60]


def test_a_slowly_moving_camera_keyframes_by_parallax_and_a_still_one_by_change() -> None:
    """Frames 2 s apart (a recording replayed at 0.5 Hz), each image new: a camera moving 1 cm per frame keyframes
    by parallax only (refresh_s is for static cameras; every frame a keyframe gave its windows no parallax), while
    a camera that does not move keyframes at every frame its image changed."""
    cfg = KeyframeConfig(min_baseline_ratio=0.05, assumed_depth_m=1.0, min_translation_m=10.0)
    sel = KeyframeSelector(cfg)
    two_s = 2_000_000_000

    def at(T: np.ndarray, k: int, source: str) -> View:  # each image a new grey: changed everywhere
        grey = np.full((240, 320, 3), 30 + 40 * (k % 5), np.uint8)
        return dataclasses.replace(_view(T, k, source), image=grey, stamp_ns=k * two_s)

    assert [k for k in range(11) if sel.consider(at(cam(0.0101 * k), k, "moving"))] == [0, 5, 10]
    assert [k for k in range(4) if sel.consider(at(cam(0.0), k, "still"))] == [0, 1, 2, 3]
    moving_after = KeyframeSelector(cfg.model_copy(update={"moving_refresh_s": 30.0}))
    kf = [k for k in range(0, 40, 16) if moving_after.consider(at(cam(0.001 * k), k, "slow"))]
    assert kf == [0, 16, 32]  # still reconsidered after moving_refresh_s (32 s apart), as before


def test_a_still_camera_keyframes_on_a_change_of_colour_alone() -> None:
    """A bag of the floor's grey put down in a fixed camera's view: the grey thumbnail barely moves (below
    change_threshold), its colour does."""
    sel = KeyframeSelector(KeyframeConfig())
    floor = np.full((240, 320, 3), (90, 120, 150), np.uint8)
    bag = floor.copy()
    bag[150:170, 100:120] = (137, 112, 90)  # grey 117 vs 114 (0..255)
    frames = [floor, floor, bag, bag]
    kf = [k for k, img in enumerate(frames)
          if sel.consider(dataclasses.replace(_view(cam(0.0), k, "cam"), image=img, stamp_ns=k * 2_000_000_000))]
    assert kf == [0, 2]


def test_store_neighbours_come_from_all_sources_by_parallax() -> None:
    store = KeyframeStore(KeyframeConfig(window_neighbours=2))
    for k in range(5):  # a robot's frames 1 cm apart, then one 40 cm away
        store.add(_view(cam(0.01 * k), k))
    store.add(_view(cam(0.40), 10))
    store.add(_view(cam(-0.6, 0.3, 1.8), 0, source="cam-01"))
    got = store.neighbours(_view(cam(0.0), 99), depth_m=3.0)
    assert {(v.source_id, v.seq) for v in got} == {("robot", 10), ("cam-01", 0)}
    # Storing the same frame again replaces it (no duplicates in the window).
    store.add(_view(cam(0.40), 10))
    assert len(store) == 7


def test_store_fills_with_the_nearest_views_that_have_parallax() -> None:
    # An overlap demand no candidate meets: the ideal selection is empty and the fill takes over.
    store = KeyframeStore(KeyframeConfig(window_neighbours=2, source_min_overlap=0.99))
    store.add(_view(cam(0.01), 1))  # 1 cm: no parallax, never a source
    store.add(_view(cam(0.30), 2))
    store.add(_view(cam(0.60), 3))
    store.add(_view(cam(1.50), 4))
    got = store.neighbours(_view(cam(0.0), 99), depth_m=3.0)
    assert [v.seq for v in got] == [2, 3]


def test_second_source_covers_what_the_first_does_not() -> None:
    """Two near-twin sources that see the left of the reference's view score best one by one; the
    depth check needs a second view of the right part too, so the pick after the first is the one that
    sees it, not the twin."""
    ref = cam(0.0)
    left, right = TARGET + np.array([-1.2, 0.0, 0.0]), TARGET + np.array([1.6, 0.0, 0.0])
    cands = [Candidate(0, cam(0.4, target=left), INTR), Candidate(1, cam(0.55, target=left), INTR),
             Candidate(2, cam(-0.4, target=right), INTR)]
    scores = {s.index: s.score for s in score_sources(ref, INTR, 3.0, cands)}
    assert min(scores[0], scores[1]) > scores[2]  # one by one, the twins win
    chosen = [s.index for s in select_sources(ref, INTR, 3.0, cands, k=2)]
    assert chosen[0] in (0, 1) and chosen[1] == 2
    # With every ray weighed alike whatever covers it, the selection is by score alone: the twins.
    flat = [s.index for s in select_sources(ref, INTR, 3.0, cands, k=2, coverage_weights=(1.0,))]
    assert sorted(flat) == [0, 1]


def test_recent_frames_of_a_moving_camera_are_sources_until_its_next_keyframe() -> None:
    """A robot turning at video rate: its last keyframe looks elsewhere, the frames it streamed since
    (not keyframes) already see the new keyframe's view with parallax: they are its sources."""
    store = KeyframeStore(KeyframeConfig(window_neighbours=2, recent_sources=2))
    away = TARGET + np.array([-3.0, 0.0, 0.0])
    store.add(_view(cam(-0.5, target=away), 0))  # the last keyframe: it sees none of the new view
    for k in range(1, 5):  # frames on the way, 10 cm apart, turning towards the target
        store.note_frame(_view(cam(-0.5 + 0.1 * k, target=TARGET), k))
    assert [v.seq for v in store.views()] == [0, 3, 4]  # the ring keeps the last 2
    got = store.neighbours(_view(cam(0.0), 5), depth_m=3.0)
    assert {v.seq for v in got} == {3, 4}
    # The next keyframe of that robot replaces its recent frames.
    store.add(_view(cam(0.0), 5))
    assert [v.seq for v in store.views()] == [0, 5]
    # Without the option only the old keyframe that looks elsewhere is left (the nearest-view fill).
    plain = KeyframeStore(KeyframeConfig(window_neighbours=2, recent_sources=0))
    plain.add(_view(cam(-0.5, target=away), 0))
    for k in range(1, 5):
        plain.note_frame(_view(cam(-0.5 + 0.1 * k, target=TARGET), k))
    assert [v.seq for v in plain.neighbours(_view(cam(0.0), 5), depth_m=3.0)] == [0]


def test_a_static_cameras_frames_are_not_kept_and_sources_are_bounded() -> None:
    cfg = KeyframeConfig(recent_sources=2, max_keyframes=3)
    store = KeyframeStore(cfg)
    store.add(_view(cam(0.0), 0, source="cam-01"))
    for k in range(1, 6):  # a fixed camera: same pose every frame
        store.note_frame(_view(cam(0.0), k, source="cam-01"))
    store.note_frame(View(_view(cam(0.0), 9).image, "no-pose", INTR, None, seq=9))
    assert [v.seq for v in store.views()] == [0]
    for i in range(6):  # more moving sources than max_keyframes: the oldest are forgotten
        store.note_frame(_view(cam(0.1 * i), i, source=f"robot{i}"))
    assert sorted({v.source_id for v in store.views()}) == ["cam-01", "robot3", "robot4", "robot5"]
