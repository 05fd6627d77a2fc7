"""Which worker does which keyframe job: the dispatcher's state machine (pure: time is passed in, no Zenoh).

A job goes ``pending`` -> ``assigned`` (sent to a worker) -> ``acked`` (the worker took it) -> ``done`` (a valid
result). It goes back to ``pending`` (re-issued, to any live worker) when its worker's liveliness disappears,
when no ack comes within ``ack_timeout_s`` or no result within ``result_timeout_s``, when the worker answers that
it could not do it, or when its result is rejected. After ``max_attempts`` issues it is given up (the mapper does
it itself). Results are idempotent by job id: a second result of a done job is a duplicate and ignored.

Workers: a job goes to the live worker with the fewest jobs in flight (at most ``max_in_flight`` each); among
equally loaded ones, to the worker that did its source's previous job (source affinity: a keyframe's window is
mostly its own camera's recent keyframes, whose features and depth that worker has cached; another worker would
compute them again, ~1.5x the CPU per job measured with 2 workers and 4 cameras). A worker whose results were
rejected ``quarantine_after`` times is quarantined (no more jobs) until its liveliness token goes and comes back
(a restarted process).

Backpressure: at most one pending job per source, the freshest (a newer keyframe of the source replaces it:
dropped as ``superseded``); a job whose frame is older than ``max_frame_age_s`` when it is submitted or while it
waits for a worker is dropped (``stale``: its frame's age is given at :meth:`Dispatcher.submit`, so an older
keyframe retried once it had stereo partners ages from its capture, not from its retry; with more sources than
the workers keep up with, latency stays bounded and the sources' fresher frames are mapped instead); and at most
``max_jobs`` jobs in all (a new one beyond that: dropped as ``full``). A job already started once (re-issued
after its worker went away or failed) is never dropped for staleness: the graph must have no gap.

Kept jobs: a frame whose sender needs it mapped (``FrameHeader.map_always``: a robot's arrival view, which its
next goal is planned on) is never stale nor superseded, and when the table is full, the least informative job that
may be shed (never started, of the source served most recently) makes room for it (``shed``). Under overload the
arrival views are mapped and video-rate frames give way; the status says how many (``jobs_dropped_shed``,
``keyframes_dropped.shed.<source>``).

Order: when a worker has room, re-issued jobs go first (oldest first), then kept ones, then the source served
least recently (its last job sent longest ago; never served: first) with its freshest pending job, ties by older
frame first.
Fair: a source whose keyframes come often cannot keep the others waiting, and each source is served with the
newest keyframe it has. Every outcome is counted in :attr:`Dispatcher.counters`.
"""

from __future__ import annotations

import collections
import enum
from dataclasses import dataclass, field


class State(enum.Enum):
    PENDING = "pending"
    ASSIGNED = "assigned"
    ACKED = "acked"


class Outcome(enum.Enum):
    """What became of a result handed to :meth:`Dispatcher.result`."""

    ACCEPTED = "accepted"  # the first valid result: use it
    DUPLICATE = "duplicate"  # the job is already done: ignore it
    REJECTED = "rejected"  # invalid: counted against the worker, the job is re-issued
    UNKNOWN = "unknown"  # no such job (given up, dropped, or never issued): ignore it


@dataclass
class Job:
    job_id: str
    source_id: str
    state: State = State.PENDING
    worker: str | None = None
    attempts: int = 0
    since: float = 0.0  # when it entered its state
    submitted: float = 0.0  # re-issued jobs go before newer ones
    fresh: bool = True  # a source's newest keyframe (False: an older keyframe retried, never superseded)
    captured: float = 0.0  # when its frame was taken in, on the caller's clock (``now`` less its age at submit)
    keep: bool = False  # its sender needs it mapped (FrameHeader.map_always): never stale, superseded or shed


@dataclass
class Worker:
    in_flight: set[str] = field(default_factory=set)
    bad_results: int = 0
    quarantined: bool = False
    done: int = 0


@dataclass(frozen=True)
class DispatchConfig:
    ack_timeout_s: float = 2.0
    result_timeout_s: float = 30.0
    max_attempts: int = 3
    quarantine_after: int = 3
    max_in_flight: int = 2
    max_jobs: int = 16
    max_workers: int = 256
    max_frame_age_s: float = 1.5  # a never-started job whose frame is older is dropped as stale (0: never)
    max_sources: int = 4096  # sources whose last worker is remembered (affinity), the least recent forgotten
    affinity_hold_s: float = 0.5  # a job waits up to this long for its source's last worker when that one is full
    fair: bool = True  # least recently served source first (False: the job submitted first)


class Dispatcher:
    """Jobs (by id) and workers (by id); the caller keeps the payloads and does the I/O."""

    def __init__(self, config: DispatchConfig | None = None) -> None:
        self.config = config or DispatchConfig()
        self.jobs: dict[str, Job] = {}
        self.workers: dict[str, Worker] = {}
        self._done: collections.OrderedDict[str, None] = collections.OrderedDict()  # recent done ids
        self.counters: collections.Counter[str] = collections.Counter()
        self._affinity: collections.OrderedDict[str, str] = collections.OrderedDict()  # source -> last worker
        self._served: collections.OrderedDict[str, float] = collections.OrderedDict()  # source -> last job sent
        self.dropped: list[tuple[str, str]] = []
        """``(job_id, reason)`` of jobs dropped or given up since the caller last took them (:meth:`take_dropped`)."""

    # -- workers ------------------------------------------------------------------------------------
    def worker_up(self, worker_id: str) -> None:
        """A worker's liveliness token appeared (a new or restarted process: not quarantined)."""
        if worker_id in self.workers:
            return
        if len(self.workers) >= self.config.max_workers:  # made-up tokens must not grow the table without bound
            self.counters["workers_refused"] += 1
            return
        self.workers[worker_id] = Worker()
        self.counters["workers_joined"] += 1

    def worker_down(self, worker_id: str, now: float) -> list[str]:
        """A worker's liveliness token disappeared: its jobs go back to pending (returned)."""
        w = self.workers.pop(worker_id, None)
        if w is None:
            return []
        self.counters["workers_lost"] += 1
        return self._reissue(sorted(w.in_flight), now, "jobs_reissued_worker_lost")

    def live_workers(self) -> list[str]:
        """Workers that may take jobs."""
        return sorted(k for k, w in self.workers.items() if not w.quarantined)

    # -- jobs ---------------------------------------------------------------------------------------
    def submit(self, job_id: str, source_id: str, now: float, fresh: bool = True, age_s: float = 0.0,
               keep: bool = False) -> bool:
        """Add a job (False: a duplicate of a known or recently done job, ignored; or dropped). ``age_s``: how
        old its frame is now (a job already older than ``max_frame_age_s`` is dropped as ``stale``). A ``fresh``
        job (the source's newest keyframe) drops the source's older fresh job still pending (``superseded``); an
        older keyframe retried (``fresh`` False: deferred until it had stereo partners) is not superseded. With
        ``max_jobs`` jobs already, the new one is dropped (``full``).

        A ``keep`` job (its sender needs it mapped: a robot's arrival view) is never stale nor superseded, goes
        before other new jobs, and a full table makes room for it by shedding the least informative pending job
        (``shed``): one never started of the source served most recently (what it adds is the least new), its
        newest frame; only a table full of kept or started jobs refuses it (``full``)."""
        if job_id in self.jobs or job_id in self._done:
            self.counters["jobs_duplicate_submit"] += 1
            return False
        if not keep and self._too_old(max(age_s, 0.0)):
            self.dropped.append((job_id, "stale"))
            self.counters["jobs_dropped_stale"] += 1
            return False
        for j in list(self.jobs.values()):
            if fresh and j.fresh and not j.keep and j.source_id == source_id and j.state is State.PENDING:
                self._drop(j.job_id, "superseded")
        if len(self.jobs) >= self.config.max_jobs and keep:
            sheddable = [j for j in self.jobs.values() if j.state is State.PENDING and not j.keep and j.attempts == 0]
            if sheddable:
                least = max(sheddable, key=lambda j: (self._served.get(j.source_id, float("-inf")), j.captured))
                self._drop(least.job_id, "shed")
        if len(self.jobs) >= self.config.max_jobs:
            self.dropped.append((job_id, "full"))
            self.counters["jobs_dropped_full"] += 1
            return False
        self.jobs[job_id] = Job(job_id, source_id, since=now, submitted=now, fresh=fresh,
                                captured=now - max(age_s, 0.0), keep=keep)
        if keep:
            self.counters["jobs_kept"] += 1
        self.counters["jobs_submitted"] += 1
        return True

    def _too_old(self, age_s: float) -> bool:
        return self.config.max_frame_age_s > 0 and age_s > self.config.max_frame_age_s

    def drop_stale(self, now: float) -> list[str]:
        """Drop the pending jobs never started whose frame is older than ``max_frame_age_s`` (returned)."""
        out = [j.job_id for j in self.jobs.values()
               if j.state is State.PENDING and j.attempts == 0 and not j.keep and self._too_old(now - j.captured)]
        for job_id in out:
            self._drop(job_id, "stale")
        return out

    def _order(self, j: Job) -> tuple[float, float, float, float]:
        """Sort key of a pending job: re-issued ones first (oldest first), then kept ones (``keep``), then the
        least recently served source, its fresh keyframe before a retried older one, then the older frame (not
        ``fair``: the job submitted first)."""
        if j.attempts > 0 or not self.config.fair:
            return (0.0 if j.attempts > 0 else 1.0, j.submitted, 0.0, 0.0)
        if j.keep:  # a view its sender waits for (a robot's arrival): before the others, oldest first
            return (0.5, j.submitted, 0.0, 0.0)
        return (1.0, self._served.get(j.source_id, float("-inf")), 0.0 if j.fresh else 1.0, j.captured)

    def assign(self, now: float) -> list[tuple[str, str, int]]:
        """Send pending jobs to the least loaded live workers, in :meth:`_order` (stale ones dropped first):
        ``(job_id, worker_id, attempt)``. Source affinity (:meth:`_pick`) may hold a job back a little while its
        worker is full."""
        self.drop_stale(now)
        out = []
        for j in sorted((j for j in self.jobs.values() if j.state is State.PENDING), key=self._order):
            free = [(len(self.workers[k].in_flight), k) for k in self.live_workers()
                    if len(self.workers[k].in_flight) < self.config.max_in_flight]
            if not free:
                break
            wid = self._pick(j, free, now)
            if wid is None:
                continue
            j.state, j.worker, j.since = State.ASSIGNED, wid, now
            j.attempts += 1
            self.workers[wid].in_flight.add(j.job_id)
            self._served.pop(j.source_id, None)
            self._served[j.source_id] = now
            while len(self._served) > self.config.max_sources:
                self._served.popitem(last=False)
            self.counters["jobs_assigned"] += 1
            out.append((j.job_id, wid, j.attempts))
        return out

    def _pick(self, j: Job, free: list[tuple[int, str]], now: float) -> str | None:
        """Where job ``j`` goes among ``free`` ((jobs in flight, worker id)): the source's last worker when it is among
        the least loaded; None (held) while that worker is live but full and the job has waited less than
        ``affinity_hold_s`` (under full load each worker keeps its sources instead of swapping them at every
        turn); else the least loaded, first by id. Remembers the choice for the source."""
        least = min(n for n, _ in free)
        ties = sorted(k for n, k in free if n == least)
        last = self._affinity.get(j.source_id)
        if last is not None and last not in {k for _, k in free} and last in self.live_workers() \
                and now - j.since < self.config.affinity_hold_s:
            self.counters["jobs_held_for_affinity"] += 1
            return None
        wid = last if last in ties else ties[0]
        if wid == last:
            self.counters["jobs_assigned_same_worker"] += 1
        self._affinity.pop(j.source_id, None)
        self._affinity[j.source_id] = wid
        while len(self._affinity) > self.config.max_sources:
            self._affinity.popitem(last=False)
        return wid

    def ack(self, job_id: str, worker_id: str, attempt: int, now: float) -> bool:
        """The worker took the job (False: a stale or unknown ack, ignored)."""
        j = self.jobs.get(job_id)
        if j is None or j.worker != worker_id or j.attempts != attempt or j.state is not State.ASSIGNED:
            self.counters["acks_ignored"] += 1
            return False
        j.state, j.since = State.ACKED, now
        return True

    def result(self, job_id: str, worker_id: str, now: float, problem: str | None = None) -> Outcome:
        """A result of ``job_id`` from ``worker_id``; ``problem``: why it was found invalid (None: valid).

        The first valid result wins, whichever worker and attempt it comes from (the job's answer does not
        depend on who computed it)."""
        if job_id in self._done:
            self.counters["results_duplicate"] += 1
            return Outcome.DUPLICATE
        j = self.jobs.get(job_id)
        w = self.workers.get(worker_id)
        if problem is not None:
            self.counters["results_rejected"] += 1
            if w is not None:
                w.bad_results += 1
                if w.bad_results >= self.config.quarantine_after and not w.quarantined:
                    w.quarantined = True
                    self.counters["workers_quarantined"] += 1
                    self._reissue(sorted(w.in_flight - {job_id}), now, "jobs_reissued_quarantine")
            if j is not None and j.worker == worker_id:
                self._reissue([job_id], now, "jobs_reissued_rejected")
            return Outcome.REJECTED if j is not None else Outcome.UNKNOWN
        if j is None:
            self.counters["results_unknown"] += 1
            return Outcome.UNKNOWN
        self._finish(j)
        if w is not None:
            w.done += 1
        self.counters["results_accepted"] += 1
        return Outcome.ACCEPTED

    def failed(self, job_id: str, worker_id: str, now: float) -> bool:
        """The worker says it could not do the job (busy, a fetch timed out, its backend raised): re-issued."""
        j = self.jobs.get(job_id)
        if j is None or j.worker != worker_id:
            return False
        self._reissue([job_id], now, "jobs_reissued_worker_failed")
        return True

    def expire(self, now: float) -> list[str]:
        """Drop stale pending jobs (:meth:`drop_stale`); re-issue jobs whose ack or result is overdue (returned)."""
        c = self.config
        self.drop_stale(now)
        jobs = list(self.jobs.values())
        late_ack = [j.job_id for j in jobs if j.state is State.ASSIGNED and now - j.since > c.ack_timeout_s]
        late = [j.job_id for j in jobs if j.state is State.ACKED and now - j.since > c.result_timeout_s]
        return self._reissue(late_ack, now, "jobs_reissued_no_ack") + self._reissue(late, now, "jobs_reissued_late")

    def orphans(self) -> list[str]:
        """Pending jobs while no live worker may take them: removed here, for the caller to do itself."""
        if self.live_workers():
            return []
        out = [j.job_id for j in self.jobs.values() if j.state is State.PENDING]
        for job_id in out:
            del self.jobs[job_id]
            self.counters["jobs_done_locally"] += 1
        return out

    def take_dropped(self) -> list[tuple[str, str]]:
        out, self.dropped = self.dropped, []
        return out

    def in_flight(self) -> int:
        return sum(j.state is not State.PENDING for j in self.jobs.values())

    def pending(self) -> int:
        return sum(j.state is State.PENDING for j in self.jobs.values())

    # -- internals ----------------------------------------------------------------------------------
    def _release(self, j: Job) -> None:
        if j.worker is not None and j.worker in self.workers:
            self.workers[j.worker].in_flight.discard(j.job_id)
        j.worker = None

    def _finish(self, j: Job) -> None:
        self._release(j)
        del self.jobs[j.job_id]
        self._done[j.job_id] = None
        while len(self._done) > 4 * self.config.max_jobs + 64:
            self._done.popitem(last=False)

    def _drop(self, job_id: str, reason: str) -> None:
        j = self.jobs.pop(job_id)
        self._release(j)
        self.dropped.append((job_id, reason))
        self.counters[f"jobs_dropped_{reason}"] += 1

    def _reissue(self, job_ids: list[str], now: float, counter: str) -> list[str]:
        out = []
        for job_id in job_ids:
            j = self.jobs.get(job_id)
            if j is None:
                continue
            self._release(j)
            if j.attempts >= self.config.max_attempts:
                self._drop(job_id, "given_up")
                continue
            j.state, j.since = State.PENDING, now
            self.counters[counter] += 1
            out.append(job_id)
        return out
