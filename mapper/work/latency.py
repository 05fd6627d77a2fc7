"""Where a keyframe's capture-to-graph time goes: recent seconds per stage of its life (pure: no I/O).

The mapper records, for each keyframe, the age of its frame (now minus its capture stamp) when it enters the
core (``age_at_ingest``), when it becomes a worker job (``age_at_submit``; a deferred keyframe retried:
``age_at_submit_retry``), when the job is sent (``age_at_send``, after ``wait_pending`` in the dispatcher's
queue), when its result comes back (``age_at_result``, after ``job_roundtrip`` from send to result), how
long a deferred keyframe waited for a stereo partner (``deferred_wait``) and its age when a graph delta is
committed (``age_at_commit``: the benchmark's capture-to-graph latency, less the publish). The status shows the
p50 / p99 / max of the last ``keep`` values of each stage as ``kf_s.<stage>.{p50,p99,max}`` and how many were
recorded (``kf_s.<stage>.n``), so a latency tail can be traced to its stage without prints.
"""

from __future__ import annotations

import collections
import threading

import numpy as np


class StageTimes:
    """The last ``keep`` durations (seconds) of each stage; bounded in stages (``max_stages``) and values.
    Thread-safe: the mapper's thread records, the status thread reads."""

    def __init__(self, keep: int = 512, max_stages: int = 32) -> None:
        self.keep, self.max_stages = keep, max_stages
        self._values: dict[str, collections.deque[float]] = {}
        self._counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        """Record one duration; non-finite values are ignored, a stage beyond ``max_stages`` too."""
        if not np.isfinite(seconds):
            return
        with self._lock:
            d = self._values.get(stage)
            if d is None:
                if len(self._values) >= self.max_stages:
                    return
                d = self._values[stage] = collections.deque(maxlen=self.keep)
            d.append(float(seconds))
            self._counts[stage] += 1

    def age(self, stage: str, stamp_ns: int, now_ns: int) -> None:
        """Record the age of a frame captured at ``stamp_ns`` (0: unstamped, not recorded)."""
        if stamp_ns > 0:
            self.add(stage, (now_ns - stamp_ns) / 1e9)

    def counters(self, prefix: str = "kf_s") -> dict[str, float]:
        """``<prefix>.<stage>.{p50,p99,max,n}`` (seconds over the recent values; n: all recorded)."""
        out: dict[str, float] = {}
        with self._lock:
            recent = {stage: np.array(d, dtype=np.float64) for stage, d in self._values.items()}
            counts = dict(self._counts)
        for stage, v in recent.items():
            p50, p99 = np.percentile(v, [50, 99])
            out[f"{prefix}.{stage}.p50"] = round(float(p50), 4)
            out[f"{prefix}.{stage}.p99"] = round(float(p99), 4)
            out[f"{prefix}.{stage}.max"] = round(float(v.max()), 4)
            out[f"{prefix}.{stage}.n"] = float(counts[stage])
        return out
