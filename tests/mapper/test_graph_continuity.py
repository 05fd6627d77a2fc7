"""Graph continuity (issue 19): epochs, the version lease, restarts, failing state directories, and the
consumer rule that follows a restarted mapper and shrugs off a forged snapshot. In-process, no Zenoh."""

from __future__ import annotations

import errno
import os
import types
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

import mapper.persistence as persistence
from mapper.config import GeometryConfig, MapperConfig, PerceptionConfig
from mapper.geometry.contract import View
from mapper.node import MapperNode
from mapper.persistence import Lease, read_lease, remove_stale_temps, resume, state_path, write_lease
from planner.config import PlannerNodeConfig
from planner.node import PlannerNode
from protocol.codec import MAGIC, decode, encode
from protocol.graph import RESYNC_AFTER, GraphFollower, GraphVersionError, apply_delta
from protocol.messages import GraphDelta, GraphSnapshot
from tests.support.boxes import BASKET, EYES, SHIFTED, TABLE, scene_view, view
from tests.support.messages import node_msg
from tests.support.procs import wait_for


def snap(epoch: str, version: int, *ids: str) -> GraphSnapshot:
    return GraphSnapshot(epoch=epoch, version=version, stamp_ns=version, nodes=[node_msg(i) for i in ids])


# --- the consumer rule (protocol.graph.GraphFollower) ---------------------------------------------------
def test_a_forged_huge_version_is_overridden_by_the_live_mappers_snapshots() -> None:
    f = GraphFollower()
    assert f.offer_snapshot(snap("E", 40, "n1", "n2")) == "adopted"
    assert f.offer_snapshot(snap("E", 10**15)) == "adopted"  # forged: same epoch, empty, absurd version
    for i in range(1, RESYNC_AFTER):
        assert f.offer_snapshot(snap("E", 40 + i, "n1", "n2")) == "stale"
    assert f.offer_snapshot(snap("E", 40 + RESYNC_AFTER, "n1", "n2")) == "resynced"
    assert f.graph == snap("E", 40 + RESYNC_AFTER, "n1", "n2")
    # and it follows the live deltas again
    assert f.offer_delta(GraphDelta(epoch="E", version=44, stamp_ns=1, upserted=[node_msg("n3")])) == "applied"
    assert [n.node_id for n in f.graph.nodes] == ["n1", "n2", "n3"]
    assert f.counters["resyncs"] == 1


def test_a_forged_snapshot_of_another_epoch_is_dropped_at_the_next_real_one() -> None:
    f = GraphFollower()
    f.offer_snapshot(snap("E", 40, "n1"))
    f.offer_snapshot(snap("forged", 10**15))
    assert f.offer_delta(GraphDelta(epoch="E", version=41, stamp_ns=1)) == "other_epoch"
    assert f.need_snapshot  # the caller re-queries: the mapper answers in its own epoch
    assert f.offer_snapshot(snap("E", 41, "n1")) == "adopted"
    assert f.graph.epoch == "E" and not f.need_snapshot


def test_one_stale_snapshot_in_between_newer_ones_changes_nothing() -> None:
    f = GraphFollower()
    f.offer_snapshot(snap("E", 10, "n1"))
    for v in (11, 9, 12, 8, 13, 7, 14):  # stale ones never come RESYNC_AFTER in a row
        f.offer_snapshot(snap("E", v, "n1"))
    assert f.graph.version == 14 and "resyncs" not in f.counters


def test_a_mapper_restarted_without_state_is_followed_at_once() -> None:
    f = GraphFollower()
    f.offer_snapshot(snap("old", 275, *[f"n{i}" for i in range(112)]))
    assert f.offer_delta(GraphDelta(epoch="new", version=1, stamp_ns=1)) == "other_epoch"
    assert f.offer_snapshot(snap("new", 38, "n1")) == "adopted"
    assert (f.graph.epoch, f.graph.version, len(f.graph.nodes)) == ("new", 38, 1)
    assert f.offer_delta(GraphDelta(epoch="new", version=39, stamp_ns=1, removed=["n1"])) == "applied"
    assert f.graph.nodes == [] and f.counters["epoch_changes"] == 2


def test_gaps_and_runs_of_old_deltas_ask_for_the_snapshot() -> None:
    f = GraphFollower()
    f.offer_snapshot(snap("E", 10))
    assert f.offer_delta(GraphDelta(epoch="E", version=12, stamp_ns=1)) == "gap" and f.need_snapshot
    f.offer_snapshot(snap("E", 12))
    for _ in range(RESYNC_AFTER - 1):
        assert f.offer_delta(GraphDelta(epoch="E", version=5, stamp_ns=1)) == "old"
    assert not f.need_snapshot
    f.offer_delta(GraphDelta(epoch="E", version=6, stamp_ns=1))
    assert f.need_snapshot  # a live mapper behind us: re-query, its replies count toward a resync


def test_apply_delta_refuses_another_epoch() -> None:
    with pytest.raises(GraphVersionError, match="epoch"):
        apply_delta(snap("A", 1), GraphDelta(epoch="B", version=2, stamp_ns=0))
    assert apply_delta(snap("A", 1), GraphDelta(epoch="A", version=2, stamp_ns=0)).epoch == "A"


def test_messages_without_an_epoch_still_decode() -> None:
    """A schema 1.1 snapshot (no epoch field) decodes with epoch ''; ours say minor 4."""
    s = snap("E", 3, "n1")
    _, kind, major, minor, body = msgpack.unpackb(encode(s), raw=False)
    assert (major, minor) == (1, 4) and body["epoch"] == "E"
    del body["epoch"]
    old = msgpack.packb([MAGIC, kind, 1, 1, body], use_bin_type=True)
    assert decode(old, GraphSnapshot).epoch == ""


# --- the planner follows (regressions of issue 19 item 2) ---------------------------------------------------
def _follow(planner: PlannerNode, *snaps: GraphSnapshot) -> None:
    for s in snaps:
        planner.offer_snapshot(s)
        planner._follow_graph()


def test_planner_follows_the_real_graph_after_a_forged_huge_version() -> None:
    planner = PlannerNode(PlannerNodeConfig())
    _follow(planner, snap("E", 20, "n1", "n2"), snap("E", 10**15))
    assert planner.graph.nodes == []
    _follow(planner, *[snap("E", 21 + i, "n1", "n2", "n3") for i in range(RESYNC_AFTER)])
    assert planner.graph == snap("E", 20 + RESYNC_AFTER, "n1", "n2", "n3")
    assert planner.counters.get("resyncs") == 1


def test_planner_follows_a_mapper_restarted_with_no_state() -> None:
    planner = PlannerNode(PlannerNodeConfig())
    _follow(planner, snap("life1", 275, *[f"n{i}" for i in range(112)]))
    _follow(planner, snap("life2", 38, *[f"n{i}" for i in range(81)]))
    assert (planner.graph.epoch, planner.graph.version, len(planner.graph.nodes)) == ("life2", 38, 81)
    planner._deltas.append(GraphDelta(epoch="life2", version=39, stamp_ns=1, removed=["n0"]))
    planner._follow_graph()
    assert (planner.graph.version, len(planner.graph.nodes)) == (39, 80)


# --- the lease and the resume rule (mapper.persistence) ------------------------------------------------------
def at(r: persistence.Resume) -> tuple[int, int]:
    return r.version, r.next_id


def test_resume_rule() -> None:
    fresh = resume(None, None, None)
    assert (fresh.version, fresh.next_id) == (0, 1) and len(fresh.epoch) == 16
    assert resume(None, None, None).epoch != fresh.epoch  # each life without a lease is a new epoch
    assert at(resume(7, 12, None)) == (7, 12)
    # killed: the restored graph gets a version above anything the lease allowed, ids above its ceiling
    r = resume(7, 12, Lease("E", 1000, 1001))
    assert (r.epoch, r.version, r.next_id) == ("E", 1001, 1001)
    # state lost, lease kept: still above
    assert at(resume(None, None, Lease("E", 1000, 1001))) == (1001, 1001)
    # clean stop: exactly where it stopped
    assert at(resume(7, 12, Lease("E", 7, 12, clean=True))) == (7, 12)
    assert at(resume(6, 12, Lease("E", 7, 12, clean=True))) == (8, 12)


def test_lease_round_trip_and_unreadable_lease(tmp_path: Path) -> None:
    assert read_lease(tmp_path) is None
    write_lease(tmp_path, Lease("abc", 10, 20))
    assert read_lease(tmp_path) == Lease("abc", 10, 20)
    (tmp_path / persistence.LEASE_NAME).write_text('{"magic": "ARGUS-MAPPER-LEASE", "epoch": 5}')
    assert read_lease(tmp_path) is None
    (tmp_path / persistence.LEASE_NAME).write_bytes(b"\x00\xff")
    assert read_lease(tmp_path) is None


def test_stale_temp_files_are_removed(tmp_path: Path) -> None:
    for name in (".mapper_state.abc.tmp", ".mapper_lease.x1.tmp", "keep.tmp", "mapper_state.msgpack"):
        (tmp_path / name).write_bytes(b"\0" * 2048)
    assert remove_stale_temps(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.tmp", "mapper_state.msgpack"]


# --- the mapper node: restarts and failing disks ---------------------------------------------------------------
def mapper(state_dir: Path | None, **kw: object) -> MapperNode:
    cfg = MapperConfig(geometry=GeometryConfig(backend="oracle"),
                       perception=PerceptionConfig(segmenter="sim", embedder="sim"),
                       state_dir=state_dir, save_period_s=0.0, **kw)
    return MapperNode(cfg)


def feed(m: MapperNode, eyes: list[list[float]], seq0: int) -> list[GraphDelta]:
    out = []
    for i, eye in enumerate(eyes):
        d = m.core.ingest(view(eye, seq0 + i))
        if d is not None:
            out.append(d)
    return out


def test_kill_between_saves_never_reuses_a_version_or_an_id(tmp_path: Path) -> None:
    """Regression (issue 19 item 3): killed after unsaved versions, the mapper came back older, re-published
    versions it had already published, and gave a lost node's id to another object 0.6 m away."""
    (tmp_path / ".mapper_state.dead.tmp").write_bytes(b"\0" * 4096)  # a kill during an earlier save
    first = mapper(tmp_path)
    assert not list(tmp_path.glob(".mapper_state.*.tmp"))
    seen = [first.core.ingest(scene_view(EYES[0], 0, {"table": TABLE}))]
    first.save(force=True)  # the last save before the kill
    saved = first.core.snapshot()
    seen += feed_views(first, [scene_view(eye, 1 + i, {"table": TABLE, "basket": BASKET})
                               for i, eye in enumerate(EYES[:2])])  # published, never saved
    top = max(d.version for d in seen if d is not None)
    published = {n.node_id: n for d in seen if d is not None for n in d.upserted}
    basket_id = next(i for i, n in published.items() if n.label == "basket")
    assert top > saved.version and basket_id not in {n.node_id for n in saved.nodes}
    del first  # SIGKILL: no close(), no final save

    second = mapper(tmp_path)
    restored = second.core.snapshot()
    assert restored.epoch == saved.epoch and restored.version > top
    assert restored.nodes == saved.nodes  # the saved graph, published as a version nobody has seen
    later = feed_views(second, [scene_view(eye, 10 + i, {"table": TABLE, "shifted": SHIFTED})
                                for i, eye in enumerate(EYES[:2])])
    assert later and all(d.version > top for d in later)
    new = {n.node_id: n for d in later for n in d.upserted if n.node_id not in published}
    assert [n.label for n in new.values()] == ["shifted"]
    for d in later:  # an id published before names the same object (the table), never the new one
        for n in d.upserted:
            assert n.node_id not in published or published[n.node_id].label == n.label == "table"
    assert all(int(i[1:]) > persistence.ID_BLOCK for i in new)


def feed_views(m: MapperNode, views: list[View]) -> list[GraphDelta]:
    return [d for v in views if (d := m.core.ingest(v)) is not None]


def test_clean_stop_resumes_exactly_and_no_state_is_a_new_epoch(tmp_path: Path) -> None:
    first = mapper(tmp_path)
    feed(first, EYES[:2], 0)
    first.keeper.close(first.core)
    again = mapper(tmp_path)
    assert again.core.snapshot() == first.core.snapshot()  # same epoch, same version: deltas just go on
    assert feed(again, EYES[2:3], 5)[0].version == first.core.version + 1
    loose = mapper(None)
    other = mapper(None)
    assert loose.core.version == 0 and loose.core.epoch != other.core.epoch != first.core.epoch


def test_failed_saves_keep_the_last_good_state_and_are_retried(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    m = mapper(tmp_path)
    feed(m, EYES[:1], 0)
    m.save(force=True)
    good = state_path(tmp_path).read_bytes()

    real_fsync = os.fsync

    def disk_full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(persistence.os, "fsync", disk_full)
    feed(m, EYES[1:3], 1)
    m._reporter = reporter = types.SimpleNamespace(state="ok", last_error=None)  # type: ignore[assignment]
    m.save(force=True)
    assert reporter.state == "degraded" and "No space left" in reporter.last_error
    assert state_path(tmp_path).read_bytes() == good  # untouched
    assert not list(tmp_path.glob(".mapper_state.*.tmp"))  # no partial file left behind
    assert m.counters.get("save_errors") == 1 and m.keeper.failing
    assert "No space left" in (m.keeper.last_error or "")
    m.save()  # within the retry period: not retried in a tight loop
    assert m.counters.get("save_errors") == 1
    # still mapping and serving from memory
    assert m.core.snapshot().version == m.core.version and len(m.core.snapshot().nodes) >= 3

    monkeypatch.setattr(persistence.os, "fsync", real_fsync)
    m.save(force=True)
    assert not m.keeper.failing and m.counters.get("state_failing") == 0 and reporter.state == "ok"
    assert decode(persistence.load_state(tmp_path)["store"]["snapshot"], GraphSnapshot) == m.core.snapshot()


def test_unwritable_state_dir_keeps_mapping_in_a_memory_only_epoch(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A lease that cannot be extended: versions beyond it would be reused after a crash, so the mapper goes
    on in a new epoch no restart can come back to, and persists it once the disk works again."""
    monkeypatch.setattr(persistence, "VERSION_BLOCK", 2)
    m = mapper(tmp_path)
    epoch = m.core.epoch
    assert read_lease(tmp_path) == Lease(epoch, 1 + 2, 1 + persistence.ID_BLOCK)

    def broken(*_a: object, **_k: object) -> None:
        raise PermissionError(errno.EACCES, "Permission denied")

    real_write = persistence._write_atomic
    monkeypatch.setattr(persistence, "_write_atomic", broken)
    deltas = feed(m, EYES, 0)
    assert deltas[0].epoch == epoch and deltas[-1].epoch != epoch  # switched once the lease ran out
    assert m.counters.get("epoch_switches") == 1 and m.counters.get("lease_errors") >= 1
    assert m.keeper.failing and "Permission denied" in (m.keeper.last_error or "")
    assert read_lease(tmp_path) == Lease(epoch, 1 + 2, 1 + persistence.ID_BLOCK)  # the old lease, intact

    monkeypatch.setattr(persistence, "_write_atomic", real_write)
    m.keeper._last_lease_try = -np.inf  # the retry period is over
    m.keeper._last_save = -np.inf
    m.save()
    assert not m.keeper.failing
    assert read_lease(tmp_path).epoch == m.core.epoch  # the memory-only epoch is persisted now
    again = mapper(tmp_path)
    assert again.core.epoch == m.core.epoch and again.core.version > m.core.version


def test_a_state_dir_that_cannot_exist_still_serves(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    m = mapper(blocker / "state")
    deltas = feed(m, EYES[:2], 0)
    assert deltas and m.keeper.failing and m.counters.get("lease_errors") >= 1
    m.save(force=True)
    assert m.counters.get("save_errors") == 1 and len(m.core.snapshot().nodes) >= 2


# --- argus query watch --------------------------------------------------------------------------------------
class _Sample:
    def __init__(self, data: bytes) -> None:
        self.payload = self
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class _Session:
    """Just enough of a zenoh session for run_watch: the test pushes the samples."""

    def __init__(self) -> None:
        self.callback: Any = None

    def declare_subscriber(self, _key: str, callback: Any) -> _Session:
        self.callback = callback
        return self

    def undeclare(self) -> None:
        pass


def test_watch_says_new_epoch_not_gap(capsys: pytest.CaptureFixture[str]) -> None:
    import threading

    from deploy.query import run_watch
    from protocol.keys import Keys

    session = _Session()
    deltas = [GraphDelta(epoch="A", version=v, stamp_ns=0) for v in (5, 6, 8)] + [GraphDelta(epoch="B", version=1,
                                                                                             stamp_ns=0)]
    done = threading.Thread(target=run_watch, args=(session, Keys("s"), False, threading.Event(), len(deltas), 5.0))
    done.start()
    wait_for(lambda: session.callback is not None, timeout=10, what="watch subscribed")
    for d in deltas:
        session.callback(_Sample(encode(d)))
    done.join(timeout=10)
    lines = capsys.readouterr().out.splitlines()
    assert ["gap" in x for x in lines] == [False, False, True, False]
    assert "new mapper epoch 'B'" in lines[3]


def test_planner_does_not_requery_for_deltas_its_new_snapshot_covers() -> None:
    planner = PlannerNode(PlannerNodeConfig())
    _follow(planner, snap("E", 5))
    planner.offer_snapshot(snap("E", 10, "n1"))
    planner._deltas.extend(GraphDelta(epoch="E", version=v, stamp_ns=1) for v in (7, 8, 9, 10, 11))
    planner._follow_graph()
    assert planner.graph.version == 11 and not planner._need_snapshot
