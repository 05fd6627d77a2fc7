"""The ``argus mapper`` process: Zenoh I/O around :class:`mapper.core.MapperCore`.

Subscribes to every frame key of the site (a bounded newest-frames ring per source, so a slow mapper
always works on fresh frames) and, when an ORACLE backend is configured, to the oracle keys; decodes
the JPEGs; feeds the core; publishes each GraphDelta, each changed node under ``graph/node/<id>``
(deleting removed ones), a GraphSnapshot and the PointMap at bounded rates; answers queries on
``graph/**`` (``graph/snapshot``, ``graph/nodes?label=..;near=..;radius=..;id=..;since_version=..``,
``graph/node/<id>``) and, as JSON, on ``graph/json/**`` (the same keys below ``graph/json/``);
reports status; persists the graph atomically so a restart resumes it, with versions and node ids
leased ahead of use so a restart never reuses one (:mod:`mapper.keeper`).

Each frame is checked on arrival, before it takes a ring slot (``config.limits``,
:mod:`mapper.intake`): compressed size, pixel count, the JPEG's own size against its header, compressed
bytes per pixel, intrinsics and the camera position against the site's box; a refused frame is counted
under its reason and never decoded. Its pose is checked too (:func:`protocol.poses.check_pose`): a
nearly rigid one is projected onto SO(3) (counter ``poses_projected``); any other is dropped with its
frame (``frames_bad_pose``). A header that does not decode (a non-finite pose or intrinsics, a wrong
shape) counts as ``header_errors``. Every kind of bad input is logged as a WARNING, rate-limited
(:class:`protocol.ratelog.RateLimitedLog`: the first of each reason, then one summary line per
``BAD_INPUT_LOG_PERIOD_S`` with counts).

Memory of the frame path is bounded (README, "Memory bound"): compressed frames buffered stay under
``limits.max_buffered_frame_bytes`` (rings) plus the same for frames waiting for an ORACLE sample, and
frames are decoded one at a time, just before processing, under ``limits.decode_budget_pixels``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.config import MapperConfig
from mapper.core import MapperCore
from mapper.geometry.contract import OracleData, View
from mapper.geometry.features import LruCache
from mapper.intake import IMAGE_REASONS, frame_problem
from mapper.keeper import StateKeeper
from mapper.work.compute import compute_keyframe, runs_perception
from mapper.work.offload import Finished, Offloader
from protocol.codec import DecodeError, encode
from protocol.jpeg import JpegError, decode_jpeg
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, Message, OracleFrame, PointMap
from protocol.oracle import decode_u16_png, png_to_depth
from protocol.poses import PoseError, check_pose
from protocol.query import GraphQuery
from protocol.ratelog import RateLimitedLog
from protocol.session import open_session_retrying
from protocol.transport import (
    Counters,
    Frame,
    LatestSlots,
    LatestValue,
    StatusReporter,
    declare_message_publisher,
    decode_frame_sample,
    decode_message_sample,
    message_encoding,
)

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)
ROLE = "mapper"
BAD_INPUT_LOG_PERIOD_S = 10.0
"""Bad-input warnings: each reason at most once per this many seconds, then one summary line with counts."""


def needs_oracle(config: MapperConfig) -> bool:
    """Whether the configured backends read simulator ground truth (ORACLE keys)."""
    from mapper.perception.registry import ORACLE_BACKENDS

    p = config.perception
    return config.geometry.backend == "oracle" or p.segmenter in ORACLE_BACKENDS or p.embedder in ORACLE_BACKENDS


def oracle_data(msg: OracleFrame) -> OracleData:
    """Decode an OracleFrame's PNGs (raises JpegError on corrupt images)."""
    depth = png_to_depth(msg.depth_png) if msg.depth_png is not None else None
    ids = decode_u16_png(msg.ids_png).astype(np.int32) if msg.ids_png is not None else None
    if depth is None:
        depth = np.zeros(ids.shape if ids is not None else (1, 1), dtype=np.float32)
    labels: dict[int, str] = {}
    for k, v in msg.labels.items():
        try:
            labels[int(k)] = v
        except ValueError:
            continue
    return OracleData(
        depth_m=depth, T_world_cam_true=np.asarray(msg.T_world_cam_true), instance_id=ids, labels=labels
    )


class DecodeBudget:
    """Decoded pixels in flight across all sources: a frame is decoded only when its pixels fit."""

    def __init__(self, max_pixels: int) -> None:
        self.max_pixels = max_pixels
        self.in_flight = 0
        self.peak = 0
        self._lock = threading.Lock()

    def acquire(self, pixels: int) -> bool:
        """Reserve ``pixels``; False (nothing reserved) when they do not fit in the budget."""
        with self._lock:
            if self.in_flight + pixels > self.max_pixels:
                return False
            self.in_flight += pixels
            self.peak = max(self.peak, self.in_flight)
            return True

    def release(self, pixels: int) -> None:
        with self._lock:
            self.in_flight = max(0, self.in_flight - pixels)


class MapperNode:
    """One mapper process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: MapperConfig, core: MapperCore | None = None) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
        self.core = core or MapperCore(config)
        self.counters = Counters()
        lim = config.limits
        self.slots: LatestSlots[Frame] = LatestSlots(
            depth=config.ring_depth, max_keys=config.max_sources, max_bytes=lim.max_buffered_frame_bytes,
            size=lambda f: len(f.jpeg),
        )
        self.needs_oracle = needs_oracle(config)
        self._oracle: collections.OrderedDict[tuple[str, int], OracleFrame] = collections.OrderedDict()
        self._oracle_lock = threading.Lock()
        # Frames (still compressed) waiting for their ORACLE sample, with their deadline; bounded in count and bytes.
        self._pending: collections.deque[tuple[Frame, float]] = collections.deque(maxlen=2 * config.max_sources)
        self.decode_budget = DecodeBudget(lim.decode_budget_pixels)
        self._session: zenoh.Session | None = None
        self._rerun: Any = None
        self.bad_input = RateLimitedLog(log, BAD_INPUT_LOG_PERIOD_S)
        self._last_snapshot: tuple[tuple[str, int], float] = (("", -1), 0.0)
        self._last_map = (-1, 0.0)
        self._reporter: StatusReporter | None = None
        self._state_shown: tuple[bool, str | None] = (False, None)  # the keeper's health last put in the status
        self.keeper = StateKeeper(config.state_dir, config.save_period_s, self.counters)
        log.info("mapper %s: %s", config.id, self.keeper.start(self.core))
        self.core.reserve = lambda version, next_id: self.keeper.reserve(version, next_id, self.core)
        self.offloader: Offloader | None = None
        self._robots = LruCache(config.max_sources)  # source ids of robot frames (their keyframes are marked)
        if config.workers.enabled and not self.needs_oracle:  # jobs carry no ORACLE samples
            self.offloader = Offloader(config.workers, config, self.keys, self.counters, runs_perception(config))
            self.core.offload = self.offloader.offload

    # -- persistence -----------------------------------------------------------------------------
    def save(self, force: bool = False) -> None:
        """Save the state when due (:class:`StateKeeper`); a failure shows in the status, the mapper goes on."""
        self.keeper.save(self.core, force)
        rep, failing = self._reporter, self.keeper.failing
        if rep is not None and (failing, self.keeper.last_error) != self._state_shown:
            # Only on a change, so a status another part of the mapper set is not overwritten every step.
            rep.state = "degraded" if failing else "ok"
            rep.last_error = self.keeper.last_error or rep.last_error
            self._state_shown = (failing, self.keeper.last_error)

    # -- subscriptions (Zenoh threads) -------------------------------------------------------------
    def _refuse(self, reason: str, msg: str, *args: object) -> None:
        """Count a refused input under ``reason`` (and ``decode_errors`` when its image was refused unread) and
        log it (rate-limited)."""
        self.counters.add(reason)
        if reason in IMAGE_REASONS:
            self.counters.add("decode_errors")
        self.bad_input.warning(reason, msg, *args)

    def _on_frame(self, sample: zenoh.Sample) -> None:
        self.counters.add("frames_in")
        try:
            self._admit(sample)
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self._refuse("frame_errors", "frame on %s failed: %s: %s", sample.key_expr, type(e).__name__, e)

    def _admit(self, sample: zenoh.Sample) -> None:
        """Check a frame sample as it arrives; only an acceptable frame takes a ring slot."""
        lim = self.config.limits
        size = len(sample.payload)
        if size > lim.max_frame_bytes:  # refused before the payload is copied out of Zenoh
            self._refuse("frames_too_large", "refused a %d-byte frame on %s (limits.max_frame_bytes = %d)",
                         size, sample.key_expr, lim.max_frame_bytes)
            return
        try:
            frame = decode_frame_sample(sample)
            kind, source_id = self.keys.parse_frame(frame.key)
            if source_id != frame.header.source_id or kind != frame.header.source_kind:
                raise DecodeError(f"header names {frame.header.source_id!r}, key {frame.key!r}")
        except (DecodeError, ValueError) as e:
            self._refuse("header_errors", "bad frame sample on %s: %s", sample.key_expr, e)
            return
        h = frame.header
        problem = frame_problem(h, frame.jpeg, lim)
        if problem is not None:
            self._refuse(problem[0], "refused a frame from %s#%d: %s", h.source_id, h.seq, problem[1])
            return
        # Checked on arrival: a bad-pose frame never takes a ring slot from its source's good frames.
        checked = self._checked_pose(frame)
        if checked is not None:
            self.slots.put(checked.key, checked)

    def _checked_pose(self, frame: Frame) -> Frame | None:
        """``frame`` with its pose projected onto SO(3) when slightly off (``poses_projected``), or None
        when the pose is unusable (``frames_bad_pose``, a rate-limited warning); the frame is dropped.

        Shape and finiteness were already checked by the codec (a header failing them is a header error).
        """
        h = frame.header
        if h.T_world_cam is None:
            return frame
        try:
            checked = check_pose(h.T_world_cam, source=f"{h.source_id} frame {h.seq} pose")
        except PoseError as e:
            self._refuse("frames_bad_pose", "dropped a frame: %s", e)
            return None
        if not checked.projected:
            return frame
        self.counters.add("poses_projected")
        return dataclasses.replace(frame, header=h.model_copy(update={"T_world_cam": checked.T.tolist()}))

    def _on_oracle(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode_message_sample(sample, OracleFrame)
        except DecodeError as e:
            self._refuse("oracle_errors", "bad oracle sample on %s: %s", sample.key_expr, e)
            return
        with self._oracle_lock:
            self._oracle[(msg.source_id, msg.seq)] = msg
            while len(self._oracle) > self.config.max_oracle_cache:
                self._oracle.popitem(last=False)

    def _on_query(self, query: zenoh.Query) -> None:
        self._guarded_answer(query, json_view=False)

    def _on_json_query(self, query: zenoh.Query) -> None:
        self._guarded_answer(query, json_view=True)

    def _guarded_answer(self, query: zenoh.Query, json_view: bool) -> None:
        try:
            self._answer(query, json_view)
        except Exception as e:  # noqa: BLE001 - a bad query gets an error reply, never a crash
            self._refuse("query_errors", "bad query %s?%s: %s: %s", query.key_expr, query.parameters,
                         type(e).__name__, e)
            try:
                query.reply_err(f"{type(e).__name__}: {e}")
            except Exception:  # noqa: BLE001 - the querier may be gone
                pass

    def _answer(self, query: zenoh.Query, json_view: bool = False) -> None:
        """Reply with msgpack envelopes, or (``json_view``, keys under ``graph/json/``) with JSON objects."""
        import zenoh

        t0 = time.perf_counter()
        key = str(query.key_expr)
        if json_view:
            if not zenoh.KeyExpr(self.keys.graph_json_all).includes(zenoh.KeyExpr(key)):
                return  # e.g. graph/**: the msgpack queryable answers that; formats never mix in one reply set
            self.counters.add("json_queries")
            for reply_key, msg in self._select(self.keys.from_graph_json(key), str(query.parameters)):
                query.reply(self.keys.graph_json(reply_key), msg.model_dump_json(),
                            encoding=message_encoding(type(msg), "application/json"))
        else:
            self.counters.add("queries")
            for reply_key, msg in self._select(key, str(query.parameters)):
                query.reply(reply_key, encode(msg), encoding=message_encoding(type(msg)))
        self.counters.set("last_query_ms", (time.perf_counter() - t0) * 1e3)

    def _select(self, key: str, params: str) -> list[tuple[str, Message]]:
        """What a query on ``key`` (under ``graph/``) answers: ``(reply key, message)`` pairs."""
        import zenoh

        if key == self.keys.graph_snapshot:
            return [(key, self.core.snapshot())]
        if key == self.keys.graph_nodes:
            q = GraphQuery.from_parameters(params)
            nodes = self.core.query(q)
            ids = {n.node_id for n in nodes}
            snap = self.core.snapshot()
            edges = [e for e in snap.edges if e.subject_id in ids and e.object_id in ids]
            return [(key, GraphSnapshot(epoch=snap.epoch, version=snap.version, stamp_ns=snap.stamp_ns,
                                        nodes=nodes, edges=edges))]
        try:
            node_id = self.keys.parse_node(key)
        except ValueError:
            node_id = None
        if node_id is not None:
            return [(key, n) for n in self.core.query(GraphQuery(id=node_id))]
        # A wildcard such as graph/**: answer with everything it covers, each under its own key.
        asked = zenoh.KeyExpr(key)
        out: list[tuple[str, Message]] = []
        if asked.intersects(zenoh.KeyExpr(self.keys.graph_snapshot)):
            out.append((self.keys.graph_snapshot, self.core.snapshot()))
        for n in self.core.nodes():
            nk = self.keys.graph_node(n.node_id)
            if asked.intersects(zenoh.KeyExpr(nk)):
                out.append((nk, n))
        return out

    # -- frames -> views -----------------------------------------------------------------------------
    def _take_oracle(self, frame: Frame) -> OracleFrame | None:
        with self._oracle_lock:
            return self._oracle.pop((frame.header.source_id, frame.header.seq), None)

    def _decode(self, frame: Frame) -> np.ndarray | None:
        """The frame's RGB image (its pixels are held in ``decode_budget`` until :meth:`_release`), or None."""
        h = frame.header
        lim = self.config.limits
        if not self.decode_budget.acquire(h.width * h.height):
            self._refuse("frames_over_decode_budget", "no decode budget for %s#%d (%dx%d)",
                         h.source_id, h.seq, h.width, h.height)
            return None
        try:
            # The size is checked against the header before any pixel is decoded (no memory bombs).
            rgb = decode_jpeg(frame.jpeg, expected_size=(h.width, h.height), max_pixels=lim.max_frame_pixels,
                              min_bytes_per_mpixel=lim.min_jpeg_bytes_per_mpixel)
            if rgb.shape[:2] != (h.height, h.width):
                raise JpegError(f"JPEG is {rgb.shape}, header says {h.width}x{h.height}")
        except JpegError as e:
            self._release(frame)
            self._refuse("decode_errors", "bad JPEG from %s#%d: %s", h.source_id, h.seq, e)
            return None
        return rgb

    def _release(self, frame: Frame) -> None:
        self.decode_budget.release(frame.header.width * frame.header.height)

    def _to_view(self, frame: Frame, rgb: np.ndarray, oracle: OracleFrame | None) -> View | None:
        h = frame.header
        try:
            od = oracle_data(oracle) if oracle is not None else None
            return View(
                image=rgb,
                source_id=h.source_id,
                intrinsics=h.intrinsics,
                T_world_cam=None if h.T_world_cam is None else np.asarray(h.T_world_cam),
                pose_trusted=h.pose_trusted,
                stamp_ns=h.stamp_ns,
                seq=h.seq,
                oracle=od,
            )
        except (ValueError, JpegError) as e:
            self._refuse("decode_errors", "unusable frame from %s#%d: %s", h.source_id, h.seq, e)
            return None

    def _ready_frames(self, timeout_s: float) -> list[tuple[Frame, OracleFrame | None]]:
        """Frames ready to process, still compressed (with their ORACLE sample when one is needed)."""
        fresh = [f for _, f in self.slots.take_all(timeout=timeout_s)]
        if not self.needs_oracle:
            return [(f, None) for f in fresh]
        now = time.monotonic()
        for f in fresh:
            if len(self._pending) == self._pending.maxlen:
                self.counters.add("frames_dropped")
            self._pending.append((f, now + self.config.oracle_wait_s))
        # The frames waiting have the same byte bound as the receive rings: the oldest go first.
        held = sum(len(f.jpeg) for f, _ in self._pending)
        while held > self.config.limits.max_buffered_frame_bytes:
            f, _ = self._pending.popleft()
            held -= len(f.jpeg)
            self.counters.add("frames_dropped")
        ready: list[tuple[Frame, OracleFrame | None]] = []
        waiting: collections.deque[tuple[Frame, float]] = collections.deque(maxlen=self._pending.maxlen)
        while self._pending:
            f, deadline = self._pending.popleft()
            o = self._take_oracle(f)
            if o is not None:
                ready.append((f, o))
            elif now >= deadline:
                self.counters.add("frames_without_oracle")
            else:
                waiting.append((f, deadline))
        self._pending = waiting
        return ready

    # -- publishing ----------------------------------------------------------------------------------
    def _publish_delta(self, session: zenoh.Session, pubs: dict[str, Any], delta: GraphDelta) -> None:
        pubs["delta"].put(encode(delta))
        for n in delta.upserted:
            session.put(self.keys.graph_node(n.node_id), encode(n), encoding=message_encoding(GraphNode))
        for node_id in delta.removed:
            session.delete(self.keys.graph_node(node_id))
        self.counters.add("deltas")

    def _publish_periodic(self, pubs: dict[str, Any], force: bool = False) -> None:
        now = time.monotonic()
        version = self.core.version
        pc = self.config.publish
        seen, when = self._last_snapshot
        if (self.core.epoch, version) != seen and (force or now - when >= pc.snapshot_period_s):
            snap = self.core.snapshot()
            pubs["snapshot"].put(encode(snap))
            self._last_snapshot = ((snap.epoch, snap.version), now)
            self.counters.add("snapshots")
        v, when = self._last_map
        if version != v and (force or now - when >= pc.point_map_period_s) and len(self.core.voxels):
            pubs["map"].put(encode(self.core.point_map(pc.point_map_max_points)))
            self._last_map = (version, now)
            self.counters.add("point_maps")

    # -- main loop -------------------------------------------------------------------------------------
    def _extra_counters(self) -> dict[str, float]:
        out = dict(self.core.counters)
        out["frames_dropped"] = self.counters.get("frames_dropped") + self.slots.dropped
        out["sources_refused"] = self.slots.refused_keys
        out["sources_evicted"] = self.slots.evicted_keys
        out["frame_bytes_buffered"] = self.slots.bytes
        out["decoded_pixels_in_flight"] = self.decode_budget.in_flight
        out["decoded_pixels_peak"] = self.decode_budget.peak
        out["graph_version"] = self.core.version
        out["nodes"] = len(self.core.store.nodes)
        out["edges"] = len(self.core.store.edges)
        if self.offloader is not None:
            out.update(self.offloader.extra_counters())
        times = self.core.update_times_s
        if times:
            out["update_s_mean"] = float(np.mean(times))
            out["update_s_max"] = float(np.max(times))
        return out

    def run(self, stop: threading.Event) -> int:
        cfg = self.config
        session = open_session_retrying(cfg.zenoh, stop, log)  # the router may start after the mapper
        if session is None:
            return 0
        with session:
            self._session = session
            token = session.liveliness().declare_token(self.keys.alive(ROLE, cfg.id))
            pubs = {
                "delta": declare_message_publisher(session, self.keys.graph_delta, important=True, message=GraphDelta),
                "snapshot": declare_message_publisher(
                    session, self.keys.graph_snapshot, important=True, message=GraphSnapshot),
                # the point map answers queries with its newest value (late joiners)
                "map": LatestValue(session, declare_message_publisher(
                    session, self.keys.map_points, important=False, message=PointMap)),
            }
            subs = [session.declare_subscriber(self.keys.all_frames, self._on_frame)]
            if self.needs_oracle:
                subs.append(session.declare_subscriber(self.keys.all_oracle, self._on_oracle))
            queryable = session.declare_queryable(self.keys.graph_all, self._on_query)
            json_queryable = session.declare_queryable(self.keys.graph_json_all, self._on_json_query)
            if self.offloader is not None:
                self.offloader.open(session)
            reporter = self._reporter = StatusReporter(
                session, self.keys.status(ROLE, cfg.id), ROLE, cfg.id, self.counters, cfg.status_period_s,
                extra=self._extra_counters,
            )
            self._open_rerun()
            log.info(
                "mapper %s: geometry=%s segmenter=%s embedder=%s%s, graph epoch %s version %d",
                cfg.id, cfg.geometry.backend, cfg.perception.segmenter, cfg.perception.embedder,
                " (ORACLE inputs)" if self.needs_oracle else "", self.core.epoch, self.core.version,
            )
            try:
                with reporter:
                    self._publish_periodic(pubs, force=True)
                    while not stop.is_set():
                        # Results of workers arrive in between frames: poll them often while jobs are out.
                        busy = self.offloader is not None and self.offloader.busy()
                        self._step(session, pubs, timeout_s=0.02 if busy else 0.2)
            finally:
                self.keeper.close(self.core)
                if self.offloader is not None:
                    self.offloader.close()
                queryable.undeclare()
                json_queryable.undeclare()
                for s in subs:
                    s.undeclare()
                token.undeclare()
                self._close_rerun()
        log.info("mapper stopped at graph version %d", self.core.version)
        return 0

    def _step(self, session: zenoh.Session, pubs: dict[str, Any], timeout_s: float) -> None:
        for frame, oracle in self._ready_frames(timeout_s):
            # Decoded one at a time, just before processing: decoded pixels in flight stay in the budget.
            rgb = self._decode(frame)
            if rgb is None:
                continue
            try:
                delta = self._process(frame, rgb, oracle)
            finally:
                self._release(frame)
            if delta is not None:
                self._publish_delta(session, pubs, delta)
        if self.offloader is not None:
            self._finish_jobs(session, pubs, self.offloader)
        self._publish_periodic(pubs)
        self.bad_input.flush()
        self.save()

    def _finish_jobs(self, session: zenoh.Session, pubs: dict[str, Any], offloader: Offloader) -> None:
        """Keyframes back from workers (or left to the mapper) into the graph, then jobs out."""
        todo = offloader.step()
        while True:
            for done in todo:
                delta = self._finish(done)
                if delta is not None:
                    self._publish_delta(session, pubs, delta)
            todo = offloader.send()  # given-up jobs come back here: done now
            if not todo:
                break
        # Only now: a keyframe finished above may be a source of another still to finish (its JPEG is kept).
        offloader.prune(self.core.keyframes.views())

    def _process(self, frame: Frame, rgb: np.ndarray, oracle: OracleFrame | None) -> GraphDelta | None:
        view = self._to_view(frame, rgb, oracle)
        if view is None:
            return None
        self.counters.add("frames_processed")
        if frame.header.source_kind == "robot":
            self._robots.put(view.source_id, True)
        if self.offloader is not None:
            self.offloader.remember(view.key, frame.jpeg)  # a keyframe's JPEG answers workers' fetches
        delta = self.core.ingest(view)
        if self.offloader is not None:
            self.offloader.prune(self.core.keyframes.views())
        return self._after(view, delta)

    def _after(self, view: View, delta: GraphDelta | None) -> GraphDelta | None:
        if self.core.last is not None and self.core.last.view is view:
            self._log_rerun()
        if delta is None and self._robots.get(view.source_id) is not None:
            delta = self.core.mark_processed(view)  # a planner may be waiting for this frame
        return delta

    def _finish(self, done: Finished) -> GraphDelta | None:
        """Finish a keyframe whose work a worker did, or that the mapper must now do itself."""
        products = done.products
        if done.local is not None:
            p, core = done.local, self.core
            try:
                products = compute_keyframe(core.reconstructor, core.segmenter, core.embedder, core.config, p.views,
                                            p.target)
            except Exception as e:  # noqa: BLE001 - one bad keyframe must never stop the mapper
                self.counters.add("keyframe_errors")
                log.warning("keyframe %s#%d failed: %s: %s", p.view.source_id, p.view.seq, type(e).__name__, e)
                return None
        return self._after(done.view, self.core.complete(done.view, products))

    # -- Rerun -----------------------------------------------------------------------------------------
    def _open_rerun(self) -> None:
        rc = self.config.rerun
        if rc.file is None and not rc.serve:
            return
        from mapper.rerun_log import RerunLogger

        try:
            self._rerun = RerunLogger(rc)
        except Exception as e:  # noqa: BLE001 - visualisation must never stop mapping
            log.error("Rerun output disabled: %s", e)
            self._rerun = None

    def _log_rerun(self) -> None:
        if self._rerun is None:
            return
        try:
            self._rerun.log(self.core)
        except Exception as e:  # noqa: BLE001
            self.counters.add("rerun_errors")
            log.debug("Rerun logging failed: %s", e)

    def _close_rerun(self) -> None:
        if self._rerun is not None:
            self._rerun.close()


def run(config: MapperConfig, stop: threading.Event | None = None) -> int:
    """Run the mapper until SIGINT/SIGTERM (or ``stop``)."""
    import torch

    from protocol.runtime import install_stop_handlers

    torch.set_num_threads(config.torch_threads)
    stop = stop or install_stop_handlers()
    return MapperNode(config).run(stop)
