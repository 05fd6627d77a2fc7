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
from typing import TYPE_CHECKING

import numpy as np

from mapper.config import MapperConfig
from mapper.core import MapperCore
from mapper.geometry.contract import View
from mapper.geometry.features import LruCache
from mapper.geometry.registry import ORACLE_RECONSTRUCTORS
from mapper.inbox import FrameIntake
from mapper.keeper import StateKeeper
from mapper.outbox import GraphOutbox
from mapper.queries import GraphQueries
from mapper.work.compute import compute_keyframe, runs_perception
from mapper.work.local import LocalWorkers, local_worker_config
from mapper.work.offload import Finished, Offloader
from protocol.keys import Keys
from protocol.messages import GraphDelta, OracleFrame
from protocol.node import Node, Process
from protocol.ratelog import RateLimitedLog
from protocol.runtime import HeapReleaser
from protocol.transport import Counters, Frame, StatusReporter

if TYPE_CHECKING:
    pass

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
        self.outbox = GraphOutbox(self.core, config, self.keys, self.counters)
        self._reporter: StatusReporter | None = None
        self._state_shown: tuple[bool, str | None] = (False, None)  # the keeper's health last put in the status
        self.keeper = StateKeeper(config.state_dir, config.save_period_s, self.counters)
        log.info("mapper %s: %s", config.id, self.keeper.start(self.core))
        self.core.reserve = lambda version, next_id: self.keeper.reserve(version, next_id, self.core)
        self.offloader: Offloader | None = None
        self._robots = LruCache(config.max_sources)  # source ids of robot frames (their keyframes are marked)
        self._release_heap = HeapReleaser(config.release_heap_period_s)
        self.node = Node(config.zenoh, self.keys, ROLE, config.id, counters=self.counters,
                         status_period_s=config.status_period_s, logger=log)
        self.local_workers: LocalWorkers | None = None
        if config.workers.enabled and config.geometry.backend not in ORACLE_RECONSTRUCTORS:  # jobs carry no ORACLE:
            # ORACLE 2D perception (the simulator's semantic camera) then stays in the mapper, after the job.
            perception = runs_perception(config) and not self.intake.needs_oracle
            self.offloader = Offloader(config.workers, config, self.keys, self.counters, perception,
                                       bad_input=self.intake.bad_input)
            self.core.offload = self.offloader.offload
            self.offloader.on_news = self.intake.slots.wake  # a worker's ack or result ends the wait for frames

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

    # -- main loop -------------------------------------------------------------------------------------
    def _extra_counters(self) -> dict[str, float]:
        out = dict(self.core.counters)
        out.update(self.core.stages.counters())
        out.update(self.intake.extra_counters())
        out["graph_version"] = self.core.version
        out["nodes"] = len(self.core.store.nodes)
        out["edges"] = len(self.core.store.edges)
        out["keyframes_stored"] = len(self.core.keyframes)  # bounded: keyframes.max_keyframes
        out["pointmap_voxels"] = len(self.core.voxels)  # bounded: point_map.max_voxels
        if self.offloader is not None:
            out.update(self.offloader.extra_counters())
        if self.local_workers is not None:
            out["local_workers_alive"] = float(self.local_workers.alive())
        times = self.core.update_times_s
        if times:
            out["update_s_mean"] = float(np.mean(times))
            out["update_s_max"] = float(np.max(times))
        return out

    def serve(self, node: Node) -> None:
        cfg, k = self.config, self.keys
        node.on_exit(self._stopped)
        node.alive()
        self.outbox.open(node)
        node.subscribe(k.all_frames, self.intake.on_frame)
        if self.intake.needs_oracle:
            node.subscribe(k.all_oracle, self.intake.on_oracle)
        node.queryable(k.graph_all, self.queries.on_query)
        node.queryable(k.graph_json_all, self.queries.on_json_query)
        if self.offloader is not None:
            self.offloader.open(node.session)
            node.on_exit(self.offloader.close)
            self.local_workers = self._start_local_workers()
        node.on_exit(lambda: self.keeper.close(self.core))
        self._reporter = node.status(extra=self._extra_counters)
        log.info(
            "mapper %s: geometry=%s segmenter=%s embedder=%s%s, graph epoch %s version %d",
            cfg.id, cfg.geometry.backend, cfg.perception.segmenter, cfg.perception.embedder,
            " (ORACLE inputs)" if self.intake.needs_oracle else "", self.core.epoch, self.core.version,
        )
        self.outbox.periodic(force=True)
        while node.running:
            # Waits for frames, or for a worker's news (Offloader.on_news wakes it), or 0.2 s for the periodic work.
            self._step(timeout_s=0.2)

    def _start_local_workers(self) -> LocalWorkers | None:
        """The worker processes of ``[workers] local`` (stopped with the mapper); None when there are none. They
        join with the mapper's Zenoh settings, credentials included (``argus up --secure`` gives the mapper's
        login their keys: deploy/acl.py)."""
        cfg = self.config
        n = cfg.workers.local
        if not n:
            return None
        threads = cfg.workers.local_torch_threads or cfg.torch_threads
        configs = [local_worker_config(cfg.id, cfg.site, cfg.key_prefix, cfg.zenoh, i, threads, cfg.log_level)
                   for i in range(n)]
        if any(c is None for c in configs):
            self.counters.add("local_workers_unreachable")
            log.warning("no local worker: the mapper has no fixed Zenoh endpoint for it to join (a peer listening "
                        "on a random port); keyframes are computed in the mapper's thread")
            return None
        pool = LocalWorkers([c for c in configs if c is not None], self.counters)
        pool.start()
        self.node.on_exit(pool.close)
        return pool

    def _stopped(self) -> None:
        self.outbox.close()
        log.info("mapper stopped at graph version %d", self.core.version)

    def _step(self, timeout_s: float) -> None:
        for frame, oracle in self.intake.ready(timeout_s):
            if self.offloader is not None and self.offloader.has_news():
                # A worker's result goes into the graph (and the worker gets its next job) before the next
                # frame, not after the whole batch: with 8 cameras a batch held results ~0.4 s, the workers idle.
                self._finish_jobs(self.offloader)
            # Decoded one at a time, just before processing: decoded pixels in flight stay in the budget.
            rgb = self.intake.decode(frame)
            if rgb is None:
                continue
            try:
                delta = self._process(frame, rgb, oracle)
            finally:
                self.intake.release(frame)
            if delta is not None:
                self.outbox.delta(delta)
        if self.offloader is not None:
            self._finish_jobs(self.offloader)
        if self.local_workers is not None:
            self.local_workers.check()
        self.outbox.periodic()
        self.intake.bad_input.flush()
        self.save()
        if self._release_heap():
            self.counters.add("heap_releases")

    def _finish_jobs(self, offloader: Offloader) -> None:
        """Jobs out to free workers, keyframes back from workers (or left to the mapper) into the graph, then
        jobs out again (those the finished keyframes made)."""
        todo = offloader.step()
        # Free workers take their next job before this thread fuses the results they sent: a worker would
        # otherwise idle through the fusion (~0.1-0.2 s a keyframe), and the job is the same (made at ingest).
        todo.extend(offloader.send())
        while True:
            for done in todo:
                delta = self._finish(done)
                if delta is not None:
                    self.outbox.delta(delta)
            todo = offloader.send()  # given-up jobs come back here: done now
            if not todo:
                break
        # Only now: a keyframe finished above may be a source of another still to finish (its JPEG is kept).
        offloader.prune(self.core.views_to_keep())

    def _process(self, frame: Frame, rgb: np.ndarray, oracle: OracleFrame | None) -> GraphDelta | None:
        view = self.intake.view(frame, rgb, oracle)
        if view is None:
            return None
        self.counters.add("frames_processed")
        if frame.header.source_kind == "robot":
            self._robots.put(view.source_id, True)
        if self.offloader is not None:
            # Answers workers' fetches; a worker decodes it at the mapper's working size.
            self.offloader.remember(view.key, frame.jpeg, frame.received_ns, self.intake.reduction(frame))
        delta = self.core.ingest(view)
        if self.offloader is not None:
            self.offloader.prune(self.core.views_to_keep())
        return self._after(view, delta)

    def _after(self, view: View, delta: GraphDelta | None) -> GraphDelta | None:
        if self.core.last is not None and self.core.last.view is view:
            self.outbox.rerun()
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


def run(config: MapperConfig, stop: threading.Event | None = None) -> int:
    """Run the mapper until SIGINT/SIGTERM (or ``stop``)."""
    import torch

    from protocol.runtime import install_stop_handlers

    torch.set_num_threads(config.torch_threads)
    # Before the (slow) construction: a stop while models load is a clean exit too.
    return MapperNode(config).run(stop or install_stop_handlers())
