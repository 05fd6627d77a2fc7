"""The ``argus worker`` process: does keyframe jobs for the mapper of its site.

It declares a liveliness token ``alive/worker/<id>`` (the mapper sends jobs only to live workers and re-issues
the jobs of one whose token disappears), subscribes to its job key ``work/job/<id>``, acknowledges each job at
once on ``work/ack/<id>``, fetches the source keyframes' JPEGs it does not hold from the mapper's keyframe store
(a query on ``work/keyframe/<source_id>/<seq>``; decoded images are cached, sources recur across jobs), runs
:func:`mapper.work.compute.compute_keyframe` with the mapper's own settings (they come with the job; backends
are built once per settings digest) and puts the result on ``work/result/<id>``.

Bounded: at most ``queue_depth`` jobs are held; one more is answered ``busy`` (the mapper re-issues it).
A job that cannot be done (an undecodable JPEG, a source that cannot be fetched, a backend that raises) is
answered with ``ok = false`` and the reason; the worker carries on. Status (``status/worker/<id>``) counts
jobs in, done, failed, busy, fetches and cache hits, with mean job time.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from mapper.geometry.features import LruCache
from mapper.work.config import WorkerConfig
from mapper.work.jobs import encode_products, view_of
from protocol.codec import DecodeError, encode
from protocol.jpeg import JpegError, decode_jpeg, jpeg_info
from protocol.keys import Keys
from protocol.messages import WorkAck, WorkFrame, WorkJob, WorkResult
from protocol.node import Node, Process
from protocol.ratelog import RateLimitedLog
from protocol.runtime import release_free_heap
from protocol.transport import Counters, decode_message_sample

if TYPE_CHECKING:
    import zenoh

    from mapper.config import MapperCoreConfig

log = logging.getLogger(__name__)
ROLE = "worker"


class JobFailed(RuntimeError):
    """A job this worker cannot do (the reason goes back to the mapper)."""


class Backends:
    """The reconstructor, segmenter and embedder of one core-settings digest (built on first use)."""

    def __init__(self) -> None:
        self.digest: str | None = None
        self.config: MapperCoreConfig | None = None
        self.parts: tuple[Any, Any, Any] | None = None

    def get(self, job: WorkJob) -> tuple[MapperCoreConfig, tuple[Any, Any, Any]]:
        return self.of(job.config_digest, job.core_config)

    def of(self, digest: str, settings: dict[str, Any]) -> tuple[MapperCoreConfig, tuple[Any, Any, Any]]:
        """The backends of the core settings ``settings`` (digest ``digest``), built unless they are the last ones."""
        if self.digest != digest or self.config is None or self.parts is None:
            from mapper.config import MapperCoreConfig
            from mapper.geometry.registry import make_reconstructor
            from mapper.perception.registry import make_embedder, make_segmenter

            cfg = MapperCoreConfig.model_validate(settings)
            p = cfg.perception
            self.parts = (make_reconstructor(cfg.geometry.backend, cfg.geometry.options),
                          make_segmenter(p.segmenter, p.segmenter_options),
                          make_embedder(p.embedder, p.embedder_options))
            self.config, self.digest = cfg, digest
            log.info("backends for settings %s: geometry=%s segmenter=%s embedder=%s", digest[:8],
                     cfg.geometry.backend, p.segmenter, p.embedder)
        return self.config, self.parts

    def warm_up(self) -> float:
        """Build the backends of the default mapper settings (kept: a mapper with those settings finds them built)
        and run one synthetic keyframe through them (:func:`mapper.work.compute.warm_up`); seconds, NaN if it
        failed (the first job then pays what the warm-up would have)."""
        from mapper.config import MapperCoreConfig
        from mapper.work.compute import warm_up
        from mapper.work.jobs import core_settings

        try:
            settings, digest = core_settings(MapperCoreConfig())
            cfg, parts = self.of(digest, settings)
        except Exception:  # noqa: BLE001 - a failed warm-up only leaves its cost to the first job
            return float("nan")
        return warm_up(*parts, cfg)


class WorkerNode(Process):
    """One worker process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: WorkerConfig) -> None:
        self.config = config
        self.keys = Keys(config.site, config.key_prefix)
        self.counters = Counters()
        self.bad_input = RateLimitedLog(log)  # what mappers send reaches the log rate-limited and cleaned
        self._jobs: collections.deque[WorkJob] = collections.deque()
        self._cond = threading.Condition()
        self._images = LruCache(max(1, config.image_cache))
        self.backends = Backends()
        self._session: zenoh.Session | None = None
        self._pubs: dict[str, Any] = {}
        self.job_times_s: collections.deque[float] = collections.deque(maxlen=64)
        self.node = Node(config.zenoh, self.keys, ROLE, config.id, counters=self.counters,
                         status_period_s=config.status_period_s, logger=log)

    # -- Zenoh thread --------------------------------------------------------------------------------
    def _on_job(self, sample: zenoh.Sample) -> None:
        self.counters.add("jobs_in")
        try:
            if len(sample.payload) > self.config.max_job_bytes:
                raise DecodeError(f"job of {len(sample.payload)} bytes over max_job_bytes")
            job = decode_message_sample(sample, WorkJob)
        except DecodeError as e:
            self.counters.add("job_errors")
            self.bad_input.warning("job_errors", "bad job sample on %s: %s", sample.key_expr, e)
            return
        with self._cond:
            busy = len(self._jobs) >= self.config.queue_depth
            if not busy:
                self._jobs.append(job)
                self._cond.notify()
        if busy:
            self.counters.add("jobs_busy")
            self._put("result", self._failure(job, "busy"))
        else:
            self._put("ack", WorkAck(job_id=job.job_id, attempt=job.attempt, worker_id=self.config.id))

    def _put(self, which: str, msg: WorkAck | WorkResult) -> None:
        try:
            self._pubs[which].put(encode(msg))
        except Exception as e:  # noqa: BLE001 - a closing session must not raise into zenoh
            log.debug("put %s failed: %s", which, e)

    # -- jobs ------------------------------------------------------------------------------------------
    def _failure(self, job: WorkJob, reason: str) -> WorkResult:
        return WorkResult(job_id=job.job_id, attempt=job.attempt, worker_id=self.config.id, ok=False,
                          error=reason[:2000])

    def _decode(self, frame: WorkFrame, jpeg: bytes) -> np.ndarray:
        """``jpeg`` decoded as the mapper did (at 1/``frame.reduction``): checked against the frame's size and this
        worker's limits from its headers, before any pixel is decoded."""
        cfg = self.config
        try:
            info = jpeg_info(jpeg)
            if frame.reduction not in info.reductions() or info.output_size(frame.reduction) != (frame.width,
                                                                                                   frame.height):
                raise JpegError(f"the {info.width}x{info.height} JPEG at 1/{frame.reduction} is not the job's "
                                f"{frame.width}x{frame.height}")
            if frame.width * frame.height > cfg.max_image_pixels:
                raise JpegError(f"{frame.width}x{frame.height} is over max_image_pixels ({cfg.max_image_pixels})")
            # Its full size costs memory only as max_decode_bytes allows: no cap on it here.
            return decode_jpeg(jpeg, max_pixels=info.width * info.height, reduction=frame.reduction,
                               max_decode_bytes=cfg.max_decode_bytes)
        except JpegError as e:
            raise JobFailed(f"JPEG of {frame.source_id}#{frame.seq}: {e}") from None

    def _source_image(self, frame: WorkFrame) -> np.ndarray:
        """A source keyframe's image: cached, else fetched from the mapper's keyframe store."""
        key = (frame.source_id, frame.seq)  # one mapper decodes a frame at one size: view_of checks it
        img = self._images.get(key)
        if img is not None:
            self.counters.add("image_cache_hits")
            return img  # type: ignore[return-value]
        assert self._session is not None
        self.counters.add("keyframes_fetched")
        data = None
        for reply in self._session.get(self.keys.work_keyframe(*key), timeout=self.config.fetch_timeout_s):
            if reply.ok is not None:
                data = reply.ok.payload.to_bytes()
        if data is None:
            self.counters.add("fetch_failures")
            raise JobFailed(f"keyframe {frame.source_id}#{frame.seq} is not in the mapper's keyframe store")
        self.counters.add("fetched_bytes", len(data))
        img = self._decode(frame, data)
        self._images.put(key, img)
        return img

    def do(self, job: WorkJob) -> WorkResult:
        """The answer to ``job`` (never raises)."""
        from mapper.work.compute import compute_keyframe

        t0 = time.perf_counter()
        try:
            cfg, (rec, seg, emb) = self.backends.get(job)
            t, c = time.perf_counter(), time.process_time()
            views = []
            for i, f in enumerate(job.window):
                img = self._decode(f, job.jpeg) if i == job.target_index else self._source_image(f)
                views.append(view_of(f, img))
            fetch_s, fetch_cpu = time.perf_counter() - t, time.process_time() - c
            products = compute_keyframe(rec, seg, emb, cfg, views, job.target_index, perception=job.perception)
            c = time.process_time()
            result = encode_products(products, job, self.config.id, {"fetch": fetch_s})
            # Where a job's CPU goes (status ``cpu_s.<stage>``, cumulative; ``argus bench system`` reads them):
            # fetching and decoding the window's JPEGs, the reconstructor's stages, perception, the result's encoding.
            stages = products.cpu_s if products is not None else {}
            for stage, spent in {"decode": fetch_cpu, **stages, "encode": time.process_time() - c}.items():
                self.counters.add(f"cpu_s.{stage}", spent)
        except Exception as e:  # noqa: BLE001 - one bad job must never stop the worker
            self.counters.add("jobs_failed")
            self.bad_input.warning("jobs_failed", "job %s (attempt %d) failed: %s: %s", job.job_id, job.attempt,
                                   type(e).__name__, e)
            return self._failure(job, f"{type(e).__name__}: {e}")
        dt = time.perf_counter() - t0
        self.job_times_s.append(dt)
        self.counters.add("jobs_done")
        self.counters.set("last_job_s", dt)
        return result

    def _extra(self) -> dict[str, float]:
        with self._cond:
            queued = len(self._jobs)
        out = {"jobs_queued": float(queued), "images_cached": float(len(self._images))}
        if self.job_times_s:
            out["job_s_mean"] = float(np.mean(self.job_times_s))
        return out

    # -- main loop -------------------------------------------------------------------------------------
    def serve(self, node: Node) -> None:
        cfg = self.config
        self._session = node.session
        node.on_exit(lambda: log.info("worker %s stopped after %d jobs", cfg.id, int(self.counters.get("jobs_done"))))
        self._pubs = {
            "ack": node.publisher(self.keys.work_ack(cfg.id), message=WorkAck),
            "result": node.publisher(self.keys.work_result(cfg.id), message=WorkResult),
        }
        if cfg.warm_up:  # before the token: while it warms, the mapper maps keyframes itself
            log.info("worker %s: warming up (one synthetic keyframe)", cfg.id)
            log.info("worker %s: warm-up took %.1f s", cfg.id, self.backends.warm_up())
        node.subscribe(self.keys.work_job(cfg.id), self._on_job)
        node.alive()  # once it can take jobs: the mapper sends to live workers only
        node.status(extra=self._extra)
        log.info("worker %s: taking keyframe jobs on %s", cfg.id, self.keys.work_job(cfg.id))
        while node.running:
            job = self._next(0.2)
            if job is not None:
                self._put("result", self.do(job))
                with self._cond:
                    self._jobs.popleft()
                self.release_heap()

    def release_heap(self) -> None:
        """After a job, its freed memory back to the system (``protocol.runtime.release_free_heap``)."""
        if self.config.release_heap_after_job and release_free_heap() is not None:
            self.counters.add("heap_releases")

    def _next(self, timeout_s: float) -> WorkJob | None:
        """The oldest held job (it stays held, counting against queue_depth, until answered)."""
        with self._cond:
            if not self._jobs:
                self._cond.wait(timeout_s)
            return self._jobs[0] if self._jobs else None


def run(config: WorkerConfig, stop: threading.Event | None = None) -> int:
    """Run a worker until SIGINT/SIGTERM (or ``stop``)."""
    import torch

    from protocol.runtime import install_stop_handlers

    torch.set_num_threads(config.torch_threads)
    # Before the (slow) construction: a stop while models load is a clean exit too.
    return WorkerNode(config).run(stop or install_stop_handlers())
