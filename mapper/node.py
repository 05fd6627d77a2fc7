"""The ``argus mapper`` process: Zenoh I/O around :class:`mapper.core.MapperCore`.

Subscribes to every frame key of the site (:class:`mapper.inbox.FrameIntake`: checked on arrival, a bounded
newest-frames ring per source, so a slow mapper always works on fresh frames, decoded one at a time under a
pixel budget) and, when an ORACLE backend is configured, to the oracle keys; feeds the core; publishes each
GraphDelta, each changed node under ``graph/node/<id>`` (deleting removed ones), a GraphSnapshot and the
PointMap at bounded rates; answers queries on ``graph/**`` and, as JSON, on ``graph/json/**``
(:class:`mapper.queries.GraphQueries`); reports status; persists the graph atomically so a restart resumes it,
with versions and node ids leased ahead of use so a restart never reuses one (:mod:`mapper.keeper`).
Bad input of every kind is counted and logged as a WARNING, rate-limited
(:class:`protocol.ratelog.RateLimitedLog`: the first of each reason, then one summary line per
``BAD_INPUT_LOG_PERIOD_S`` with counts). Memory bound: README, "Memory bound".
"""

from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.config import MapperConfig
from mapper.core import MapperCore
from mapper.geometry.contract import View
from mapper.geometry.features import LruCache
from mapper.inbox import FrameIntake
from mapper.keeper import StateKeeper
from mapper.queries import GraphQueries
from mapper.work.compute import compute_keyframe, runs_perception
from mapper.work.offload import Finished, Offloader
from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, OracleFrame, PointMap
from protocol.node import Node, Process
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, Frame, StatusReporter, message_encoding

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)
ROLE = "mapper"
BAD_INPUT_LOG_PERIOD_S = 10.0
"""Bad-input warnings: each reason at most once per this many seconds, then one summary line with counts."""


class MapperNode(Process):
    """One mapper process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: MapperConfig, core: MapperCore | None = None) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
        self.core = core or MapperCore(config)
        self.counters = Counters()
        self.intake = FrameIntake(config, self.keys, self.counters, RateLimitedLog(log, BAD_INPUT_LOG_PERIOD_S))
        self.queries = GraphQueries(self.core, self.keys, self.counters, self.intake.refuse)
        self._rerun: Any = None
        self._last_snapshot: tuple[tuple[str, int], float] = (("", -1), 0.0)
        self._last_map = (-1, 0.0)
        self._reporter: StatusReporter | None = None
        self._state_shown: tuple[bool, str | None] = (False, None)  # the keeper's health last put in the status
        self.keeper = StateKeeper(config.state_dir, config.save_period_s, self.counters)
        log.info("mapper %s: %s", config.id, self.keeper.start(self.core))
        self.core.reserve = lambda version, next_id: self.keeper.reserve(version, next_id, self.core)
        self.offloader: Offloader | None = None
        self._robots = LruCache(config.max_sources)  # source ids of robot frames (their keyframes are marked)
        self.node = Node(config.zenoh, self.keys, ROLE, config.id, counters=self.counters,
                         status_period_s=config.status_period_s, logger=log)
        if config.workers.enabled and not self.intake.needs_oracle:  # jobs carry no ORACLE samples
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
        out.update(self.intake.extra_counters())
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

    def serve(self, node: Node) -> None:
        cfg, k = self.config, self.keys
        node.on_exit(self._stopped)
        node.alive()
        pubs = {
            "delta": node.publisher(k.graph_delta, message=GraphDelta),
            "snapshot": node.publisher(k.graph_snapshot, message=GraphSnapshot),
            # the point map answers queries with its newest value (late joiners)
            "map": node.latest(node.publisher(k.map_points, important=False, message=PointMap)),
        }
        node.subscribe(k.all_frames, self.intake.on_frame)
        if self.intake.needs_oracle:
            node.subscribe(k.all_oracle, self.intake.on_oracle)
        node.queryable(k.graph_all, self.queries.on_query)
        node.queryable(k.graph_json_all, self.queries.on_json_query)
        if self.offloader is not None:
            self.offloader.open(node.session)
            node.on_exit(self.offloader.close)
        node.on_exit(lambda: self.keeper.close(self.core))
        self._reporter = node.status(extra=self._extra_counters)
        self._open_rerun()
        log.info(
            "mapper %s: geometry=%s segmenter=%s embedder=%s%s, graph epoch %s version %d",
            cfg.id, cfg.geometry.backend, cfg.perception.segmenter, cfg.perception.embedder,
            " (ORACLE inputs)" if self.intake.needs_oracle else "", self.core.epoch, self.core.version,
        )
        self._publish_periodic(pubs, force=True)
        while node.running:
            # Results of workers arrive in between frames: poll them often while jobs are out.
            busy = self.offloader is not None and self.offloader.busy()
            self._step(node.session, pubs, timeout_s=0.02 if busy else 0.2)

    def _stopped(self) -> None:
        self._close_rerun()
        log.info("mapper stopped at graph version %d", self.core.version)

    def _step(self, session: zenoh.Session, pubs: dict[str, Any], timeout_s: float) -> None:
        for frame, oracle in self.intake.ready(timeout_s):
            # Decoded one at a time, just before processing: decoded pixels in flight stay in the budget.
            rgb = self.intake.decode(frame)
            if rgb is None:
                continue
            try:
                delta = self._process(frame, rgb, oracle)
            finally:
                self.intake.release(frame)
            if delta is not None:
                self._publish_delta(session, pubs, delta)
        if self.offloader is not None:
            self._finish_jobs(session, pubs, self.offloader)
        self._publish_periodic(pubs)
        self.intake.bad_input.flush()
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
        view = self.intake.view(frame, rgb, oracle)
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

    torch.set_num_threads(config.torch_threads)
    return MapperNode(config).run(stop)
