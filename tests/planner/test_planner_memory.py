"""The planner's memory stays bounded: the panoramas' transient arrays by ``panorama_batch_pairs`` (the same
z-buffers whatever the batch), and freed heap goes back to the system after each decision."""

from __future__ import annotations

import tracemalloc

import numpy as np

from planner.config import VisibilityConfig
from planner.geometry import Panoramas


def _scene(n_occluders: int = 20_000, n_positions: int = 40) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    occ = rng.uniform([0.0, 0.0, 0.0], [10.0, 8.0, 2.5], size=(n_occluders, 3))
    pos = rng.uniform([1.0, 1.0, 1.0], [9.0, 7.0, 1.2], size=(n_positions, 3))
    return occ, pos


def _build_peak(batch_pairs: int) -> tuple[np.ndarray, float]:
    occ, pos = _scene()
    pano = Panoramas(pos, occ, VisibilityConfig(panorama_batch_pairs=batch_pairs), far_m=8.0)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        pano._build(list(range(pos.shape[0])))
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    rows = np.stack([pano.row(i) for i in range(pos.shape[0])])
    return rows, peak


def test_panorama_batches_bound_the_transient_memory_and_give_the_same_z_buffers() -> None:
    big_rows, big_peak = _build_peak(4_000_000)  # the old fixed batch: all 40 x 20k pairs at once
    small_rows, small_peak = _build_peak(40_000)  # 2 positions per batch
    assert np.array_equal(big_rows, small_rows)
    stored = 40 * 6 * 48 * 48 * 4  # the z-buffers themselves (float32), kept either way
    assert big_peak > stored + 800_000 * 60  # > 60 bytes per pair held at once
    assert small_peak < stored + 40_000 * 200 + 2_000_000  # < 200 bytes per pair of one batch, plus slack
    assert small_peak < big_peak / 4


def test_one_position_per_batch_when_the_batch_is_smaller_than_the_occluders() -> None:
    occ, pos = _scene(1000, 3)
    one = Panoramas(pos, occ, VisibilityConfig(panorama_batch_pairs=1), far_m=8.0)
    all_ = Panoramas(pos, occ, VisibilityConfig(), far_m=8.0)
    for i in range(3):
        assert np.array_equal(one.row(i), all_.row(i))


def _rss_mb() -> float:
    for line in open("/proc/self/status").read().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


def test_release_free_heap_returns_freed_memory_that_glibc_kept() -> None:
    import ctypes

    import pytest

    from protocol.runtime import release_free_heap

    try:
        ctypes.CDLL(None).malloc_trim  # noqa: B018 - glibc only
    except AttributeError:
        pytest.skip("no glibc")
    release_free_heap()
    chunks = [bytes(2000) for _ in range(40_000)]  # 80 MB of malloc'ed (not pymalloc) blocks, heap not mmap
    pin = bytes(2000)  # allocated last, near the top of the heap: free() alone cannot shrink it
    del chunks
    before = _rss_mb()
    assert release_free_heap() is True
    after = _rss_mb()
    assert before - after > 40.0, (before, after)
    assert len(pin) == 2000


def _planner_node(release: bool):  # noqa: ANN202 - a PlannerNode with one robot due for a goal
    from planner.config import PlannerNodeConfig
    from planner.node import PlannerNode
    from protocol.messages import Intrinsics, RobotState, Viewpoint, ViewpointSet

    node = PlannerNode(PlannerNodeConfig(release_heap_after_plan=release, fusion_wait_s=0.0))
    node.viewpoints["r1"] = ViewpointSet(robot_id="r1", camera_height_m=1.0, intrinsics=Intrinsics.from_fov(64, 48, 90),
                                         viewpoints=[Viewpoint(vp_id=0, x=1.0, y=0.0, yaw_rad=0.0)])
    node.states["r1"] = RobotState(robot_id="r1", stamp_ns=1, status="arrived", x=0.0, y=0.0, yaw_rad=0.0,
                                   T_world_cam=np.eye(4).tolist())
    return node


def test_the_planner_node_releases_the_heap_after_each_decision_even_a_failed_one(monkeypatch) -> None:  # noqa: ANN001
    import planner.node

    calls: list[int] = []
    monkeypatch.setattr(planner.node, "release_free_heap", lambda: calls.append(1) or True)
    node = _planner_node(release=True)
    node.plan_once(now_s=0.0)
    assert node.counters.get("decisions") == 1 and calls == [1] and node.counters.get("heap_releases") == 1

    def boom(*_a: object) -> list:
        raise RuntimeError("planning bug")

    failing = _planner_node(release=True)
    monkeypatch.setattr(failing.planner, "plan", boom)
    failing.plan_once(now_s=0.0)
    assert failing.counters.get("plan_errors") == 1 and failing.counters.get("heap_releases") == 1
    sizes = node._extra_counters()
    assert sizes["history_views"] == 1 and sizes["point_map_points"] == 0 and sizes["blacklisted_viewpoints"] == 0
    node.planner.mark_failed("r1", 0)
    assert node._extra_counters()["blacklisted_viewpoints"] == 1
    off = _planner_node(release=False)
    off.plan_once(now_s=0.0)
    assert off.counters.get("decisions") == 1 and off.counters.get("heap_releases") == 0 and len(calls) == 2
