"""Offloading keyframes changes nothing but where the work runs (MapperCore hooks, the worker's job code and the
mapper's Offloader, in-process: no Zenoh). RGB-only geometry (mvs) and classical perception on a fixed seed."""

from __future__ import annotations

import functools
import time
from typing import Any

import numpy as np
import pytest

import mapper.work.offload as offload_module
from mapper.config import MapperCoreConfig
from mapper.core import MapperCore
from mapper.geometry.contract import View
from mapper.work.compute import compute_keyframe
from mapper.work.config import OffloadConfig, WorkerConfig
from mapper.work.jobs import decode_result, encode_products, make_job
from mapper.work.offload import Offloader
from mapper.work.worker import WorkerNode
from protocol.codec import decode, encode
from protocol.jpeg import decode_jpeg
from protocol.keys import Keys
from protocol.messages import WorkJob, WorkResult
from protocol.transport import Counters

N_FRAMES = 8


@functools.cache
def frames() -> tuple[list[bytes], list[np.ndarray], Any]:
    from bench.system import render_cameras

    cam = render_cameras(1, N_FRAMES, 160, 120, "apartment", 0)[0]
    return cam.jpegs, cam.poses, cam.intrinsics


def views() -> list[View]:
    jpegs, poses, intr = frames()
    return [View(image=decode_jpeg(j), source_id="r1", intrinsics=intr, T_world_cam=T, seq=i, stamp_ns=1000 + i)
            for i, (j, T) in enumerate(zip(jpegs, poses, strict=True))]


def graph(core: MapperCore) -> list[tuple[str, str, tuple[float, float, float], int]]:
    return [(n.node_id, n.label, n.centroid, n.point_count) for n in core.nodes()]


def in_process() -> MapperCore:
    core = MapperCore(MapperCoreConfig())
    for v in views():
        core.ingest(v)
    return core


@functools.cache
def reference() -> tuple[list[tuple[str, str, tuple[float, float, float], int]], dict[str, float], int]:
    core = in_process()
    return graph(core), dict(core.counters), len(core.voxels)


def offloaded(through_the_wire: bool) -> MapperCore:
    """Every keyframe offloaded, then finished right after its ingest, as a worker would; optionally through
    the wire format (compressed depth, PNG masks)."""
    core = MapperCore(MapperCoreConfig())
    jobs: list[tuple[View, list[View], int]] = []
    core.offload = lambda view, window, target: jobs.append((view, window, target)) is None
    for v in views():
        core.ingest(v)
        while jobs:
            view, window, target = jobs.pop(0)
            p = compute_keyframe(core.reconstructor, core.segmenter, core.embedder, core.config, window, target)
            if through_the_wire:
                job = make_job(window, target, b"", 1, True, core.config)
                p = decode_result(decode(encode(encode_products(p, job, "w")), WorkResult), job)
            core.complete(view, p)
    return core


def test_with_no_worker_the_result_is_the_in_process_one() -> None:
    nodes, counters, voxels = reference()
    assert len(nodes) >= 2 and counters["keyframes"] >= 5
    core = MapperCore(MapperCoreConfig())
    asked = []
    core.offload = lambda view, window, target: asked.append(view.key) is None and False  # no worker alive
    for v in views():
        core.ingest(v)
    assert len(asked) >= 5 and "keyframes_offloaded" not in core.counters
    assert graph(core) == nodes and len(core.voxels) == voxels
    assert {k: v for k, v in core.counters.items() if k != "last_update_s"} == \
        {k: v for k, v in counters.items() if k != "last_update_s"}


def test_offloaded_keyframes_finished_later_give_the_same_graph() -> None:
    nodes, counters, voxels = reference()
    core = offloaded(through_the_wire=False)
    assert core.counters["keyframes_offloaded"] >= 5
    assert graph(core) == nodes and len(core.voxels) == voxels


def test_through_the_wire_the_graph_is_the_same_within_centimetres() -> None:
    """Depth in 1 mm units moves a few points across fusion's thresholds: node centroids move ~1 cm at most."""
    nodes, _, _ = reference()
    core = offloaded(through_the_wire=True)
    got = graph(core)
    assert [(i, lab) for i, lab, _, _ in got] == [(i, lab) for i, lab, _, _ in nodes]
    for (_, _, c, n), (_, _, c0, n0) in zip(got, nodes, strict=True):
        assert np.allclose(c, c0, atol=0.03) and abs(n - n0) <= max(2, 0.1 * n0), (c, c0, n, n0)


def test_mark_processed_waits_for_an_offloaded_keyframe() -> None:
    core = MapperCore(MapperCoreConfig())
    pending: list[tuple[View, list[View], int]] = []
    core.offload = lambda view, window, target: pending.append((view, window, target)) is None
    vs = views()
    for v in vs[:2]:
        core.ingest(v)
    view, window, target = pending[-1]
    assert core.mark_processed(view) is None  # not processed yet: a waiting planner must not be told it was
    p = compute_keyframe(core.reconstructor, core.segmenter, core.embedder, core.config, window, target)
    delta = core.complete(view, p)
    assert delta is not None and delta.frames == {"r1": view.seq}


# --- the worker's job code, without Zenoh ----------------------------------------------------------------
def test_worker_answers_a_job_like_the_mapper_would() -> None:
    vs = views()
    jpegs = frames()[0]
    core = MapperCore(MapperCoreConfig())
    window: list[View] = []
    core.offload = lambda view, w, target: window.extend(w) is None and target == 0
    for v in vs:
        core.ingest(v)
        if window:
            break
    target = window[0]
    job = make_job(window, 0, jpegs[target.seq], 1, True, core.config)
    node = WorkerNode(WorkerConfig(id="w"))
    for v in window[1:]:
        node._images.put(v.key, v.image)  # as if fetched from the mapper's keyframe store
    result = decode(encode(node.do(decode(encode(job), WorkJob))), WorkResult)
    assert result.ok and result.worker_id == "w" and result.job_id == f"r1#{target.seq}"
    got = decode_result(result, job)
    want = compute_keyframe(core.reconstructor, core.segmenter, core.embedder, core.config, window, 0)
    assert got is not None and want is not None and got.detections is not None and want.detections is not None
    assert np.allclose(got.T_world_cam, want.T_world_cam, atol=1e-9)
    assert np.abs(got.geometry.depth_m - want.geometry.depth_m).max() <= 0.0006
    assert [d.label for d in got.detections] == [d.label for d in want.detections]
    # where the job's CPU went, by stage, for ``argus bench system``'s profile (mvs reports its own stages)
    spent = {k: node.counters.get(k) for k in ("cpu_s.decode", "cpu_s.geometry.features", "cpu_s.geometry.sweep",
                                                 "cpu_s.geometry.place", "cpu_s.perception", "cpu_s.encode")}
    assert all(v >= 0.0 for v in spent.values()) and spent["cpu_s.geometry.sweep"] > 0.0, spent
    assert node.counters.get("cpu_s.geometry.total") == 0.0  # the reconstructor's total is not a stage
    # a source it cannot get is a failed job with the reason, never an exception
    node2 = WorkerNode(WorkerConfig(id="w"))
    bad = job.model_copy(update={"jpeg": b"\xff\xd8 not a jpeg"})
    r = node2.do(bad)
    assert not r.ok and "JPEG" in (r.error or "") and node2.counters.get("jobs_failed") == 1


# --- the mapper's Offloader, with a recording session -----------------------------------------------------
class Sent:
    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []

    def put(self, key: str, payload: bytes, **_: Any) -> None:
        self.puts.append((key, payload))


def offloader(**cfg: Any) -> tuple[Offloader, Sent, Counters]:
    counters = Counters()
    o = Offloader(OffloadConfig(**cfg), MapperCoreConfig(), Keys("t"), counters, perception=True)
    sent = Sent()
    o._session = sent  # type: ignore[assignment]
    return o, sent, counters


def window_of(i: int) -> list[View]:
    vs = views()
    return [vs[i], vs[i - 1]]


def submit(o: Offloader, i: int) -> WorkJob:
    jpegs = frames()[0]
    w = window_of(i)
    for v in w:
        o.remember(v.key, jpegs[v.seq])
    assert o.offload(w[0], w, 0)
    return o._pending[f"r1#{i}"].job


def answer(o: Offloader, job: WorkJob, worker: str, result: WorkResult | None = None) -> list[Any]:
    if result is None:
        w = window_of(int(job.job_id.split("#")[1]))
        core = MapperCore(MapperCoreConfig())
        p = compute_keyframe(core.reconstructor, core.segmenter, core.embedder, core.config, w, 0)
        result = encode_products(p, job, worker)
    o._inbox.append(("result", encode(result)))
    return o.step()


def test_offloader_declines_without_a_live_worker_and_sends_to_the_least_loaded() -> None:
    o, sent, _ = offloader()
    w = window_of(3)
    o.remember(w[0].key, b"x")
    o.remember(w[1].key, b"y")
    assert not o.offload(w[0], w, 0)  # nobody alive: the core does it itself
    o.dispatcher.worker_up("a")
    o.dispatcher.worker_up("b")
    submit(o, 3)
    submit(o, 5)  # another keyframe of the same source, while #3 is pending: #3 is superseded (freshest kept)
    assert o.step() == [] and o.send() == []
    assert [k for k, _ in sent.puts] == ["argus/t/work/job/a"]
    assert decode(sent.puts[0][1], WorkJob).job_id == "r1#5"
    assert o.extra_counters()["work_jobs_dropped_superseded"] == 1


def test_a_keyframe_whose_frame_came_in_too_long_ago_is_dropped_as_stale_per_source() -> None:
    """The job deadline counts from when the frame reached the mapper (its own clock), so a keyframe whose frame
    came in 2 s before it could be made a job (the mapper busy) is dropped (keyframes_dropped.stale.<source>), not
    mapped late; the source's next, fresh one is sent."""
    o, sent, counters = offloader(max_frame_age_s=1.5)
    o.dispatcher.worker_up("a")
    jpegs = frames()[0]
    old, new = window_of(3), window_of(6)
    now = time.time_ns()
    for v in old:
        o.remember(v.key, jpegs[v.seq], received_ns=now - 2_000_000_000)  # 2 s ago
    assert o.offload(old[0], old, 0)  # handled (not done by the mapper), but too old to be a job
    for v in new:
        o.remember(v.key, jpegs[v.seq], received_ns=now)
    assert o.offload(new[0], new, 0)
    assert o.step() == [] and o.send() == []
    assert [decode(p, WorkJob).job_id for _, p in sent.puts] == ["r1#6"]
    assert counters.get("jobs_sent.r1") == 1  # served once
    assert counters.get("keyframes_dropped.stale.r1") == 1 and counters.get("keyframes_dropped") == 1
    assert o.extra_counters()["work_jobs_dropped_stale"] == 1


def test_a_deferred_keyframe_ages_from_its_retry(monkeypatch: pytest.MonkeyPatch) -> None:
    """A keyframe deferred until it had a partner (tum-fr1-xyz replayed at 0.5 Hz: 16 s later) is retried once
    the partner's own job came back (here 1.8 s after the partner came in) and is mapped, not dropped as stale: it
    could not be a job before."""
    o, sent, counters = offloader(max_frame_age_s=1.5)
    o.dispatcher.worker_up("a")
    jpegs = frames()[0]
    first, partner = window_of(3)[0], window_of(5)[0]
    now = time.time_ns()
    o.remember(first.key, jpegs[first.seq], received_ns=now - 16_000_000_000)
    o.remember(partner.key, jpegs[partner.seq], received_ns=now)
    assert o.offload(partner, [partner, first], 0)  # the partner's own keyframe, as it came in
    monkeypatch.setattr(offload_module.time, "time_ns", lambda: now + 1_800_000_000)  # its job came back
    assert o.offload(first, [first, partner], 0)  # the first, retried now that it has a partner
    assert o.step() == []
    o.send()
    assert counters.get("keyframes_dropped") == 0 and o.dispatcher.counters["jobs_dropped_stale"] == 0
    assert set(o.dispatcher.jobs) == {"r1#3", "r1#5"}  # both are jobs: sent, or waiting for the worker's room


def test_duplicate_results_are_ignored_and_a_lost_job_reissued() -> None:
    o, sent, counters = offloader()
    o.dispatcher.worker_up("a")
    o.dispatcher.worker_up("b")
    job = submit(o, 4)
    o.send()
    assert sent.puts[-1][0] == "argus/t/work/job/a"
    lost = o.dispatcher.worker_down("a", 0.0)
    assert lost == ["r1#4"]
    o.send()
    assert sent.puts[-1][0] == "argus/t/work/job/b" and decode(sent.puts[-1][1], WorkJob).attempt == 2
    done = answer(o, job, "b")
    assert len(done) == 1 and done[0].view.key == ("r1", 4) and done[0].products is not None
    assert answer(o, job, "b") == []  # the same result again: ignored
    assert o.extra_counters()["work_results_duplicate"] == 1


def test_garbage_results_are_rejected_and_the_worker_quarantined() -> None:
    o, sent, counters = offloader(quarantine_after=2, max_attempts=5)
    o.dispatcher.worker_up("bad")
    job = submit(o, 4)
    empty = encode_products(None, job, "bad").model_copy(update={"anchored": True})  # no depth at all
    o.send()
    assert answer(o, job, "bad", empty) == []  # rejected, re-issued
    assert o.dispatcher.live_workers() == ["bad"]
    o.send()
    assert decode(sent.puts[-1][1], WorkJob).attempt == 2
    done = answer(o, job, "bad", empty)
    assert counters.get("result_incomplete") == 2
    assert o.extra_counters()["workers_quarantined"] == 1
    # the only worker quarantined: the keyframe is done by the mapper itself, no gap in the graph
    assert o.dispatcher.live_workers() == []
    assert len(done) == 1 and done[0].local is not None and done[0].view.key == ("r1", 4)


@pytest.mark.parametrize("garbage", [b"", b"\x00" * 10, b"\x95\xa4ARG1\xa9work_job\x01\x00\x80"])
def test_undecodable_work_samples_are_counted(garbage: bytes) -> None:
    o, _, counters = offloader()
    o._inbox.append(("result", garbage))
    o._inbox.append(("ack", garbage))
    assert o.step() == []
    assert counters.get("work_undecodable") == 2


# --- the mapper process's loop, without Zenoh ----------------------------------------------------------------
class FakeSession(Sent):
    def delete(self, key: str) -> None:
        self.puts.append((key, b""))


class FakePublisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)


def test_keyframes_finished_together_keep_their_jpegs_for_later_windows() -> None:
    """Regression: two results taken in one step; finishing the first forgot the second's JPEG (it was neither
    a stored keyframe yet nor a job), so every later window with it as a source was done by the mapper."""
    from mapper.config import MapperConfig
    from mapper.node import MapperNode
    from protocol.messages import FrameHeader
    from protocol.transport import Frame

    node = MapperNode(MapperConfig(site="t"))
    o = node.offloader
    assert o is not None
    session = FakeSession()
    o._session = session  # type: ignore[assignment]
    o.dispatcher.worker_up("w")
    jpegs, poses, intr = frames()
    vs = views()
    for i in range(4):
        h = FrameHeader(source_id="r1", source_kind="robot", seq=i, stamp_ns=1000 + i, width=160, height=120,
                        intrinsics=intr, T_world_cam=poses[i])
        node._process(Frame(h, jpegs[i], "argus/t/robot/r1/frame", time.time_ns()), vs[i].image, None)
        o.send()  # as the mapper's loop does after each frame: the worker takes up to two at once
    out = [k for k in o._pending]
    assert len(out) >= 2, out
    for job_id in out:  # all answered before the mapper looks: one step takes them all
        p = o._pending[job_id]
        products = compute_keyframe(node.core.reconstructor, node.core.segmenter, node.core.embedder,
                                    node.core.config, p.views, p.target)
        o._inbox.append(("result", encode(encode_products(products, p.job, "w"))))
    deltas = FakePublisher()
    node.outbox.session, node.outbox.pubs = session, {"delta": deltas}
    node._finish_jobs(o)
    assert deltas.payloads
    stored = {v.key for v in node.core.keyframes.views()}
    assert {("r1", int(j.split("#")[1])) for j in out} <= stored
    assert stored <= set(o._jpegs), "every stored keyframe's JPEG answers workers' fetches"


def test_a_result_in_is_finished_before_the_next_frame_of_a_batch() -> None:
    """The mapper's loop takes a worker's result (and sends the worker its next job) between two frames of a
    batch, not after the whole batch (regression: with 8 cameras, a batch held results while workers idled)."""
    from mapper.config import MapperConfig
    from mapper.node import MapperNode
    from protocol.messages import FrameHeader
    from protocol.transport import Frame

    node = MapperNode(MapperConfig(site="t"))
    o = node.offloader
    assert o is not None
    jpegs, poses, intr = frames()
    for i in range(3):
        h = FrameHeader(source_id=f"r{i}", source_kind="robot", seq=0, stamp_ns=1000, width=160, height=120,
                        intrinsics=intr, T_world_cam=poses[i])
        node.intake.slots.put(f"argus/t/robot/r{i}/frame", Frame(h, jpegs[i], f"argus/t/robot/r{i}/frame", 0))
    events: list[str] = []

    def process(frame: Frame, *_: Any) -> None:
        events.append(f"frame {frame.header.source_id}")
        if frame.header.source_id == "r1":
            o._inbox.append(("ack", b"a worker's answer came in"))

    node._process = process  # type: ignore[method-assign,assignment]
    node._finish_jobs = lambda _o: events.append("jobs")  # type: ignore[method-assign,assignment]
    node.outbox.periodic = lambda force=False: None  # type: ignore[method-assign]  # no session here
    node._step(timeout_s=0.0)
    assert events == ["frame r0", "frame r1", "jobs", "frame r2", "jobs"]


def test_junk_work_messages_reach_the_log_rate_limited_and_cleaned(caplog: pytest.LogCaptureFixture) -> None:
    """985 junk acks and results (NUL bytes and all) are counted one by one, logged once a period, never raw."""
    import logging

    o, _, counters = offloader()
    junk = b"ARG1\x00\x00junk\x00" + bytes(range(32))
    with caplog.at_level(logging.WARNING):
        for i in range(985):
            if i % 2:
                o._on_ack(junk, time.monotonic())
            else:
                o._on_result(junk, time.monotonic())
    assert counters.get("work_undecodable") == 985
    lines = [r.getMessage() for r in caplog.records]
    assert 1 <= len(lines) <= 3, lines
    assert all("\x00" not in ln and ln.isprintable() for ln in lines)


def test_an_ack_or_result_from_a_worker_wakes_the_mapper() -> None:
    o, _, _ = offloader()
    news: list[int] = []
    o.on_news = lambda: news.append(1)

    class Payload(bytes):
        def to_bytes(self) -> bytes:
            return bytes(self)

    class Sample:
        payload = Payload(b"junk")

    o._receive("result", Sample())  # type: ignore[arg-type]
    o._receive("ack", Sample())  # type: ignore[arg-type]
    assert news == [1, 1] and o.has_news()
