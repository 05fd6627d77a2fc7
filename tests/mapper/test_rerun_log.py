"""The mapper's Rerun output: the point map as parts of new voxels, and box labels the viewer shows."""

from __future__ import annotations

import threading
import types
from pathlib import Path

import numpy as np
import pytest

from mapper.config import RerunConfig
from mapper.rerun_log import PointParts, RerunLogger
from protocol.messages import GraphNode, GraphSnapshot, OrientedBox
from protocol.rooms import RoomEdge, RoomLayer, RoomNode


class TestPointParts:
    def test_only_new_keys_are_taken(self) -> None:
        parts = PointParts(max_parts=8)
        new, refresh = parts.take(np.array([3, 1, 2]))
        assert new.tolist() == [True, True, True] and not refresh and parts.part_name == "part0"
        new, refresh = parts.take(np.array([1, 2, 3, 4]))
        assert new.tolist() == [False, False, False, True] and not refresh and parts.part_name == "part1"
        new, _ = parts.take(np.array([4, 1]))
        assert not new.any() and parts.parts == 2  # nothing new: no part

    def test_empty_input(self) -> None:
        new, refresh = PointParts(2).take(np.zeros(0, dtype=np.int64))
        assert new.shape == (0,) and not refresh

    def test_whole_map_afresh_after_max_parts(self) -> None:
        parts = PointParts(max_parts=2)
        parts.take(np.array([1]))
        parts.take(np.array([1, 2]))
        new, refresh = parts.take(np.array([2, 3]))  # 2 parts logged: the next one clears and logs everything
        assert refresh and new.tolist() == [True, True] and parts.part_name == "part0"
        assert parts.logged.tolist() == [2, 3]  # the evicted voxel 1 is gone from the recording's view


def test_boxes_show_their_labels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Rerun hides the labels of a batch with many boxes unless asked: the live viewer showed none."""
    box = OrientedBox(center=(1.0, 2.0, 0.5), extent=(0.5, 0.5, 1.0))
    nodes = [GraphNode(node_id=f"n{i}", label="chair", label_confidence=0.9, centroid=(1.0 + i, 2.0, 0.5), box=box,
                       point_count=10, observation_count=1, first_seen_ns=1, last_seen_ns=1) for i in range(40)]
    voxels = types.SimpleNamespace(keys=np.array([1, 2]), points=lambda: np.zeros((2, 3), np.float32),
                                   colors=lambda: np.zeros((2, 3), np.uint8), voxel_m=0.05)
    rooms = RoomLayer(version=1, stamp_ns=1, rooms=[RoomNode(
        room_id="room1", label="office", label_confidence=0.7, polygon=[(0.0, 0.0), (4.0, 0.0), (4.0, 3.0)],
        floor_z_m=0.0, area_m2=12.0, observed_fraction=1.0, centroid=(2.0, 1.0))], edges=[RoomEdge(
        subject_id="room1", predicate="connects", object_id="room2", position=(4.0, 1.0), width_m=0.9)])
    core = types.SimpleNamespace(lock=threading.Lock(), voxels=voxels, nodes=lambda: nodes, last=None,
                                 snapshot=lambda: GraphSnapshot(version=1, stamp_ns=1, nodes=nodes),
                                 room_layer=lambda: rooms)
    logger = RerunLogger(RerunConfig(file=tmp_path / "m.rrd"))
    logged: dict[str, object] = {}
    monkeypatch.setattr(logger.rec, "log", lambda path, arch, **kw: logged.__setitem__(path, arch))
    logger.log(core)  # type: ignore[arg-type]
    assert logged["world/objects"].show_labels is not None  # type: ignore[attr-defined]
    assert "world/points/part0" in logged
    assert "world/rooms/outlines" in logged and "world/rooms/doorways" in logged  # rooms under the objects
    logger.close()
