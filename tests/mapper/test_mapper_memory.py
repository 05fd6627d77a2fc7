"""The mapper's and the worker's freed heap goes back to the system: at most once per period in the mapper's loop
(:class:`protocol.runtime.HeapReleaser`), after each job in a worker."""

from __future__ import annotations

from typing import Any

import pytest

import protocol.runtime
from mapper.config import GeometryConfig, MapperConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.node import MapperNode
from mapper.work.config import WorkerConfig
from mapper.work.worker import WorkerNode
from protocol.runtime import HeapReleaser


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def releases(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls: list[int] = []
    monkeypatch.setattr(protocol.runtime, "release_free_heap", lambda: calls.append(1) or True)
    return calls


def test_heap_releaser_releases_at_most_once_per_period(releases: list[int]) -> None:
    clock = Clock()
    r = HeapReleaser(5.0, clock=clock)
    assert r() is True and r() is False  # the first call releases; the next one within the period does not
    clock.t += 4.9
    assert r() is False
    clock.t += 0.1
    assert r() is True and r.releases == 2 and len(releases) == 2
    never = HeapReleaser(0.0, clock=clock)
    assert never() is False and never.releases == 0 and len(releases) == 2


def test_heap_releaser_reports_nothing_without_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(protocol.runtime, "release_free_heap", lambda: None)
    r = HeapReleaser(1.0)
    assert r() is False and r.releases == 0


class Sink:
    def put(self, *_: Any, **__: Any) -> None:
        pass


def test_the_mapper_loop_releases_the_heap_once_per_period(releases: list[int]) -> None:
    cfg = MapperConfig(geometry=GeometryConfig(backend="oracle"), perception=PerceptionConfig(segmenter="sim",
                                                                                           embedder="sim"),
                       release_heap_period_s=5.0)
    node = MapperNode(cfg, core=MapperCore(cfg))
    clock = Clock()
    node._release_heap = HeapReleaser(cfg.release_heap_period_s, clock=clock)
    node.outbox.session, node.outbox.pubs = Sink(), {"delta": Sink(), "snapshot": Sink(), "map": Sink()}
    for _ in range(3):
        node._step(timeout_s=0.0)
    assert node.counters.get("heap_releases") == 1
    clock.t += 5.0
    node._step(timeout_s=0.0)
    assert node.counters.get("heap_releases") == 2 and len(releases) == 2
    assert MapperConfig().release_heap_period_s == 5.0
    sizes = node._extra_counters()  # the bounded sizes a soak samples from the status
    assert sizes["keyframes_stored"] == 0 and sizes["pointmap_voxels"] == 0 and sizes["nodes"] == 0


def test_a_worker_releases_the_heap_after_each_job_unless_told_not_to(monkeypatch: pytest.MonkeyPatch) -> None:
    import mapper.work.worker as worker

    calls: list[int] = []
    monkeypatch.setattr(worker, "release_free_heap", lambda: calls.append(1) or True)
    node = WorkerNode(WorkerConfig(id="w"))
    node.release_heap()
    node.release_heap()
    assert node.counters.get("heap_releases") == 2 and calls == [1, 1]
    off = WorkerNode(WorkerConfig(id="w", release_heap_after_job=False))
    off.release_heap()
    assert off.counters.get("heap_releases") == 0 and calls == [1, 1]


# --- what the soak samples must stay bounded: point map, keyframe store, graph nodes -------------------------
def test_the_point_map_keeps_its_voxel_budget_and_the_most_observed_voxels() -> None:
    import numpy as np

    from mapper.pointmap import VoxelMap

    vm = VoxelMap(voxel_m=1.0, max_voxels=3)
    seen_often = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]])
    for _ in range(3):
        vm.add(seen_often)
    for i in range(10):  # ten new voxels, each seen once
        vm.add(np.array([[10.5 + i, 0.5, 0.5]]))
        assert len(vm) <= 3
    assert len(vm) == 3
    kept = {tuple(p) for p in vm.points().round(1).tolist()}
    assert {(0.5, 0.5, 0.5), (1.5, 0.5, 0.5)} <= kept  # the least observed went first


def test_the_point_map_never_holds_more_than_its_budget_even_in_the_middle_of_an_add() -> None:
    """Regression (soak: the mapper's status showed 302,306 voxels for a budget of 300,000): the merged voxels
    were stored before the trim, so the status thread could read one view's voxels over the budget."""
    import numpy as np

    from mapper.pointmap import VoxelMap

    sizes: list[int] = []

    class Watched(VoxelMap):
        def __setattr__(self, name: str, value: object) -> None:
            if name == "keys":
                sizes.append(len(value))  # type: ignore[arg-type]
            super().__setattr__(name, value)

    vm = Watched(voxel_m=1.0, max_voxels=5)
    for i in range(4):
        vm.add(np.array([[10.5 + i + j, 0.5, 0.5] for j in range(4)]))
    assert len(vm) == 5 and max(sizes) == 5


def test_the_keyframe_store_and_recent_frames_keep_their_budget() -> None:
    from mapper.config import KeyframeConfig
    from mapper.keyframes import KeyframeStore
    from tests.support.boxes import EYES, view

    store = KeyframeStore(KeyframeConfig(max_keyframes=4))
    for seq in range(12):
        store.add(view(EYES[seq % len(EYES)], seq, source=f"cam{seq % 3}"))
        assert len(store) <= 4
    assert len(store) == 4 and [v.seq for v in store.views()] == [8, 9, 10, 11]  # the oldest dropped
    for seq in range(12, 40):  # recent non-keyframes of many moving sources: at most max_keyframes sources
        store.note_frame(view([float(seq), 0.0, 1.0], seq, source=f"robot{seq}"))
    assert len(store.views()) - len(store) <= 4 * KeyframeConfig().recent_sources


def test_the_object_map_keeps_its_node_cap_dropping_the_least_observed() -> None:
    from types import SimpleNamespace

    from mapper.fusion import FusionConfig, ObjectMap, UpdateResult

    om = ObjectMap(FusionConfig(max_nodes=3))
    for i, obs in enumerate([5, 1, 7, 2, 9]):
        om.nodes[f"n{i}"] = SimpleNamespace(node_id=f"n{i}", observations=obs, last_seen_ns=i)  # type: ignore[assignment]
    res = UpdateResult()
    om._enforce_cap(res)
    assert sorted(om.nodes) == ["n0", "n2", "n4"] and res.removed == {"n1", "n3"} and res.pruned == 2
