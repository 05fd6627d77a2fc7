"""The mapper's side of keyframe workers: jobs out, results in, the keyframe store, worker liveliness.

:class:`Offloader` plugs into :class:`mapper.core.MapperCore` as its ``offload`` hook. While at least one
``argus worker`` is alive (its liveliness token ``alive/worker/<id>``), a keyframe's heavy work (geometry on its
window, 2D perception) becomes a :class:`~protocol.messages.WorkJob`; :meth:`Offloader.step`, called by the
mapper's own thread, sends pending jobs to the least loaded workers, takes their acks and results, checks each
result (:func:`mapper.work.jobs.decode_result`) and hands the accepted products back for the core to finish
(:meth:`MapperCore.complete`): the mapper stays the single writer of the graph. With no worker alive the hook
declines and the core does the work itself, exactly as without workers; jobs left pending when the last worker
goes, and jobs given up after ``max_attempts``, are done by the mapper too.

The keyframe store: the JPEG of every stored keyframe (and of every keyframe in a job) is kept and answers
queries on ``work/keyframe/<source_id>/<seq>``, so a worker fetches the source views it does not hold instead of
the mapper broadcasting them. Callbacks (Zenoh threads) only buffer, in bounded deques; all decoding and every
dispatcher change but liveliness happen on the mapper's thread.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mapper.geometry.contract import View
from mapper.geometry.mvs import one_blas_thread
from mapper.work.compute import KeyframeProducts
from mapper.work.config import OffloadConfig
from mapper.work.dispatch import Dispatcher, Outcome
from mapper.work.jobs import ResultRejected, decode_result, make_job
from mapper.work.latency import StageTimes
from protocol.codec import DecodeError, decode, encode
from protocol.keys import Keys
from protocol.messages import WorkAck, WorkJob, WorkResult
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters, message_encoding

if TYPE_CHECKING:
    import zenoh

    from mapper.config import MapperCoreConfig

log = logging.getLogger(__name__)
WORKER_ROLE = "worker"


@dataclass
class Pending:
    """A job the mapper holds: the keyframe, its window and the job message."""

    view: View
    views: list[View]
    target: int
    job: WorkJob
    submitted: float = 0.0  # time.monotonic() when made a job
    sent: float = 0.0  # time.monotonic() when last sent to a worker


@dataclass
class Finished:
    """A keyframe to finish: ``products`` from a worker, or ``local`` (the mapper computes them itself)."""

    view: View
    products: KeyframeProducts | None = None
    local: Pending | None = None


class Offloader:
    """Keyframe jobs for workers; see the module doc. Thread-safe where Zenoh calls in."""

    def __init__(self, config: OffloadConfig, core_config: MapperCoreConfig, keys: Keys, counters: Counters,
                 perception: bool, bad_input: RateLimitedLog | None = None) -> None:
        self.config, self.core_config, self.keys, self.counters = config, core_config, keys, counters
        # What workers send reaches the log rate-limited and cleaned (a flood of junk acks is one line a period).
        self.bad_input = bad_input or RateLimitedLog(log)
        self.perception = perception
        self.dispatcher = Dispatcher(config.dispatch())
        self._lock = threading.Lock()  # the dispatcher (liveliness callbacks) and the JPEG store (queries)
        self._pending: dict[str, Pending] = {}
        self._jpegs: collections.OrderedDict[tuple[str, int], bytes] = collections.OrderedDict()
        self._received: dict[tuple[str, int], int] = {}  # when each remembered frame reached the mapper (ns)
        self._reduction: dict[tuple[str, int], int] = {}  # each remembered JPEG was decoded at 1/this
        self._inbox: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=8 * config.max_jobs)
        self._newest: dict[str, int] = {}  # newest seq remembered per source (bounded by the mapper's sources)
        self._session: zenoh.Session | None = None
        self._decls: list[Any] = []
        self.stages = StageTimes()  # a job's stages (status: kf_s.*)
        self.on_news: Callable[[], None] | None = None  # called (Zenoh thread) when an ack or result arrives

    # -- Zenoh -----------------------------------------------------------------------------------------
    def open(self, session: zenoh.Session) -> None:
        k = self.keys
        self._session = session
        self._decls = [
            session.declare_subscriber(k.all_work_acks, lambda s: self._receive("ack", s)),
            session.declare_subscriber(k.all_work_results, lambda s: self._receive("result", s)),
            session.declare_queryable(k.all_work_keyframes, self._on_keyframe_query),
            session.liveliness().declare_subscriber(k.all_alive_of(WORKER_ROLE), self._on_alive, history=True),
        ]

    def close(self) -> None:
        for d in self._decls:
            try:
                d.undeclare()
            except Exception as e:  # noqa: BLE001 - the session may be closing
                log.debug("undeclare failed: %s", e)
        self._decls = []

    def _receive(self, what: str, sample: zenoh.Sample) -> None:
        if len(sample.payload) > self.config.max_result_bytes:
            self.counters.add("work_samples_too_large")
            return
        if len(self._inbox) == self._inbox.maxlen:
            self.counters.add("work_inbox_dropped")
        if what == "result":
            self.counters.add("work_result_bytes", len(sample.payload))
        self._inbox.append((what, sample.payload.to_bytes()))
        if self.on_news is not None:
            self.on_news()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            role, wid = self.keys.parse_alive(str(sample.key_expr))
        except ValueError:
            return
        if role != WORKER_ROLE:
            return
        with self._lock:
            if str(sample.kind).endswith("DELETE"):
                lost = self.dispatcher.worker_down(wid, time.monotonic())
                log.warning("worker %s went away; %d job(s) re-issued", wid, len(lost))
            else:
                self.dispatcher.worker_up(wid)
                log.info("worker %s is alive: keyframes go to %d worker(s)", wid, len(self.dispatcher.live_workers()))

    def _on_keyframe_query(self, query: zenoh.Query) -> None:
        import zenoh

        try:
            key = self.keys.parse_work_keyframe(str(query.key_expr))
            with self._lock:
                jpeg = self._jpegs.get(key)
            self.counters.add("keyframe_store_queries")
            if jpeg is None:
                self.counters.add("keyframe_store_misses")
                return
            query.reply(str(query.key_expr), jpeg, encoding=zenoh.Encoding.IMAGE_JPEG)
            self.counters.add("work_fetched_bytes", len(jpeg))
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counters.add("keyframe_store_errors")
            log.debug("keyframe query %s failed: %s", query.key_expr, e)

    # -- the keyframe store ------------------------------------------------------------------------------
    def remember(self, key: tuple[str, int], jpeg: bytes, received_ns: int | None = None, reduction: int = 1) -> None:
        """Keep a frame's JPEG while it may become a keyframe (see :meth:`prune`), and when it reached the mapper
        (``received_ns``, ``time.time_ns()`` of this machine; default now): a job's deadline counts from then.
        ``reduction``: the mapper decoded it at 1/that (its working size), and so will a worker."""
        with self._lock:
            self._jpegs[key] = jpeg
            self._received[key] = time.time_ns() if received_ns is None else received_ns
            self._reduction[key] = reduction
            if len(self._newest) > 4096:  # made-up source ids must not grow it without bound
                self._newest.clear()
            self._newest[key[0]] = max(key[1], self._newest.get(key[0], -1))

    def prune(self, keyframes: list[View]) -> None:
        """Forget the JPEGs of frames that are neither a stored keyframe nor in a job."""
        keep = {v.key for v in keyframes}
        for p in self._pending.values():
            keep.update(v.key for v in p.views)
        with self._lock:
            for key in [k for k in self._jpegs if k not in keep]:
                del self._jpegs[key]
                self._received.pop(key, None)
                self._reduction.pop(key, None)
        self.counters.set("keyframe_store_jpegs", len(self._jpegs))

    # -- the core's hook ----------------------------------------------------------------------------------
    def offload(self, view: View, views: list[View], target: int) -> bool:
        """MapperCore.offload: make ``view`` a job when a worker is alive (False: the core does it now)."""
        with self._lock:
            if not self.config.enabled or not self.dispatcher.live_workers():
                return False
            jpeg = self._jpegs.get(view.key)
            missing = [v.key for v in views if v.key not in self._jpegs]
            reductions = [self._reduction.get(v.key, 1) for v in views]
        if jpeg is None or missing:
            self.counters.add("offload_missing_jpeg")  # e.g. a view fed in-process: done here
            log.debug("keyframe %s done here: no JPEG of %s", view.key, missing or [view.key])
            return False
        job = make_job(views, target, jpeg, 1, self.perception, self.core_config, reductions)
        now_ns = time.time_ns()
        with self._lock:
            fresh = view.seq >= self._newest.get(view.source_id, -1)  # else a deferred keyframe retried
            # A deferred keyframe is retried once its partner's own keyframe was mapped: it could not be a job
            # before, so its deadline counts from now (a camera at 0.5 Hz would otherwise lose its first keyframe
            # to the seconds it waited for a partner, plus the partner's job). Under overload its wait for a
            # worker still makes it stale.
            received = self._received.get(view.key, now_ns) if fresh else now_ns
            age_s = (now_ns - received) / 1e9
            if self.dispatcher.submit(job.job_id, view.source_id, time.monotonic(), fresh, age_s,
                                      keep=view.map_always):
                self._pending[job.job_id] = Pending(view, views, target, job, time.monotonic())
        self.stages.age("age_at_submit" if fresh else "age_at_submit_retry", view.stamp_ns, time.time_ns())
        return True

    # -- the mapper's thread ---------------------------------------------------------------------------
    def has_news(self) -> bool:
        """Whether acks or results wait to be taken (:meth:`step`)."""
        return bool(self._inbox)

    def step(self) -> list[Finished]:
        """Take acks and results, re-issue overdue jobs; the keyframes to finish now, in arrival order (then
        :meth:`send`, so the jobs finishing them made go out at once)."""
        now = time.monotonic()
        out: list[Finished] = []
        while self._inbox:
            what, data = self._inbox.popleft()
            if what == "ack":
                self._on_ack(data, now)
            else:
                out.extend(self._on_result(data, now))
        with self._lock:
            self.dispatcher.expire(now)
            out.extend(self._dropped())
            orphans = self.dispatcher.orphans()
        for job_id in orphans:
            p = self._pending.pop(job_id)
            out.append(Finished(p.view, local=p))
        return out

    def send(self) -> list[Finished]:
        """Send pending jobs to workers; jobs dropped meanwhile that the mapper must do itself."""
        with self._lock:
            sends = self.dispatcher.assign(time.monotonic())
            out = self._dropped()
        for job_id, wid, attempt in sends:
            self._send(job_id, wid, attempt)
        return out

    def _send(self, job_id: str, worker_id: str, attempt: int) -> None:
        p = self._pending[job_id]
        p.job = p.job.model_copy(update={"attempt": attempt})
        p.sent = time.monotonic()
        self.stages.add("wait_pending", p.sent - p.submitted)
        self.stages.age("age_at_send", p.view.stamp_ns, time.time_ns())
        assert self._session is not None
        try:
            payload = encode(p.job)
            self._session.put(self.keys.work_job(worker_id), payload, encoding=message_encoding(WorkJob))
            self.counters.add("jobs_sent")
            if attempt == 1:  # how often each source is served (fair_order)
                self.counters.add(f"jobs_sent.{p.view.source_id}")
            self.counters.add("work_job_bytes", len(payload))
        except Exception as e:  # noqa: BLE001 - the job times out and is re-issued
            log.warning("sending job %s to %s failed: %s", job_id, worker_id, e)

    def _on_ack(self, data: bytes, now: float) -> None:
        try:
            ack = decode(data, WorkAck)
        except DecodeError as e:
            self.counters.add("work_undecodable")
            self.bad_input.warning("work_undecodable", "undecodable work ack: %s", e)
            return
        with self._lock:
            self.dispatcher.ack(ack.job_id, ack.worker_id, ack.attempt, now)

    def _on_result(self, data: bytes, now: float) -> list[Finished]:
        try:
            res = decode(data, WorkResult)
        except DecodeError as e:
            self.counters.add("work_undecodable")
            self.bad_input.warning("work_undecodable", "undecodable work result: %s", e)
            return []
        p = self._pending.get(res.job_id)
        if not res.ok:
            self.counters.add("work_failures")
            self.bad_input.warning("work_failures", "worker %s could not do %s: %s", res.worker_id, res.job_id,
                                   res.error)
            with self._lock:
                self.dispatcher.failed(res.job_id, res.worker_id, now)
            return []
        problem = None
        products = None
        if p is not None:
            t0 = time.perf_counter()
            try:
                with one_blas_thread():  # its points are one small product: see one_blas_thread
                    products = decode_result(res, p.job)
                self.counters.add("work_decode_s_sum", time.perf_counter() - t0)  # the mapper's cost of a result
                fetch = float(res.timings_s.get("fetch", 0.0))  # the worker getting the window's images
                self.counters.add("work_fetch_s_sum", fetch if 0.0 <= fetch <= 3600.0 else 0.0)  # NaN: not added
            except ResultRejected as e:
                problem = e.reason
                self.counters.add(e.reason)
                self.bad_input.warning("work_rejected", "rejected the result of %s from worker %s: %s", res.job_id,
                                       res.worker_id, e)
        with self._lock:
            outcome = self.dispatcher.result(res.job_id, res.worker_id, now, problem)
            if outcome is Outcome.REJECTED and self.dispatcher.workers.get(res.worker_id, None) is not None \
                    and self.dispatcher.workers[res.worker_id].quarantined:
                self.bad_input.warning("worker_quarantined", "worker %s quarantined after %d bad results",
                                       res.worker_id, self.dispatcher.workers[res.worker_id].bad_results)
        if outcome is not Outcome.ACCEPTED or p is None:
            return []
        del self._pending[res.job_id]
        self.counters.add("work_roundtrip_s_sum", now - p.submitted)  # submitted -> result in, waits included
        self.stages.add("job_roundtrip", now - p.sent)
        self.stages.age("age_at_result", p.view.stamp_ns, time.time_ns())
        return [Finished(p.view, products=products)]

    def _dropped(self) -> list[Finished]:
        out = []
        for job_id, reason in self.dispatcher.take_dropped():
            p = self._pending.pop(job_id, None)
            if p is None:
                source = job_id.rsplit("#", 1)[0]
            elif reason == "given_up":  # no worker managed it: the mapper does it
                out.append(Finished(p.view, local=p))
                continue
            else:
                source = p.view.source_id
            self.counters.add("keyframes_dropped")
            self.counters.add(f"keyframes_dropped.{reason}.{source}")
        return out

    def extra_counters(self) -> dict[str, float]:
        with self._lock:
            d = self.dispatcher
            out = {f"work_{k}": float(v) for k, v in d.counters.items()}
            out["workers_alive"] = float(len(d.live_workers()))
            out["workers_quarantined"] = float(sum(w.quarantined for w in d.workers.values()))
            out["jobs_pending"] = float(d.pending())
            out["jobs_in_flight"] = float(d.in_flight())
            for wid, w in d.workers.items():
                out[f"worker_jobs_done.{wid}"] = float(w.done)
        out.update(self.stages.counters())
        return out
