"""Configuration of keyframe workers: the mapper's side (``[workers]`` of ``argus mapper``) and the
``argus worker`` process."""

from __future__ import annotations

import os
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from mapper.work.dispatch import DispatchConfig
from protocol.jpeg import MAX_DECODE_BYTES
from protocol.keys import SiteName
from protocol.session import ZenohSettings, default_site

ENV_LOCAL_WORKERS = "ARGUS_LOCAL_WORKERS"
"""When set to a count, the default of ``[workers] local`` (the test suite sets 0: its mappers start no child)."""


def default_local_workers() -> int:
    """``$ARGUS_LOCAL_WORKERS`` when set to a count, else 1."""
    text = os.environ.get(ENV_LOCAL_WORKERS, "").strip()
    return int(text) if text.isdigit() else 1


class OffloadConfig(BaseModel):
    """How the mapper hands keyframes to ``argus worker`` processes (only while one is alive; with none the
    mapper does every keyframe itself, as without this section)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(
        default=True, description="send heavy per-keyframe work (geometry, 2D perception) to live workers"
    )
    ack_timeout_s: float = Field(default=2.0, gt=0.0, description="a job not acknowledged by then is re-issued")
    result_timeout_s: float = Field(
        default=30.0, gt=0.0, description="an acknowledged job with no result by then is re-issued"
    )
    max_attempts: int = Field(default=3, ge=1, description="issues of one job before the mapper does it itself")
    quarantine_after: int = Field(
        default=3, ge=1, description="rejected results after which a worker gets no more jobs (until it restarts)"
    )
    max_in_flight: int = Field(
        default=1, ge=1, le=16,
        description="jobs per worker at once. 1: a job never waits behind another on a worker, so the freshest "
        "keyframe is the one computed (2 hides the transfer of the next job; on loopback that is ~20 ms of ~1 s)",
    )
    max_jobs: int = Field(
        default=16, ge=1, le=256,
        description="keyframe jobs held (pending or in flight); each holds a decoded image. Beyond it new "
        "keyframes are dropped (jobs_dropped_full); per source only the freshest pending job is kept",
    )
    max_frame_age_s: float = Field(
        default=1.5, ge=0.0,
        description="deadline of a keyframe job: one whose frame reached the mapper longer ago than this, when it "
        "is made a job or while it waits for a free worker, is dropped (keyframes_dropped.stale.<source>) and the "
        "source's next, fresher keyframe is mapped instead. Past capacity, capture-to-graph latency stays near "
        "this plus one job (~0.5 s on one core) plus the frame's wait before it reached the mapper. A job "
        "re-issued after its worker failed is kept (no gap); a keyframe deferred until it had a stereo partner "
        "counts from its retry. 0: no deadline",
    )
    fair_order: bool = Field(
        default=True,
        description="a free worker takes the job of the source served least recently (each with its freshest "
        "keyframe): past capacity every camera is mapped in turn. False: the job submitted first, which may serve "
        "a few sources again and again (their windows then reuse the worker's cached depth: cheaper jobs)",
    )
    max_result_bytes: int = Field(default=32 * 1024 * 1024, ge=1024, description="larger results are refused")
    local: int = Field(
        default_factory=default_local_workers, ge=0, le=16,
        description="worker processes the mapper starts on its own machine (mapper.work.local): ordinary workers "
        "joined to the mapper's own Zenoh endpoints, so its thread only ingests, fuses and publishes while they "
        "compute keyframes (2 cameras at 2 fps on 2 cores: capture-to-graph p50 1.5 -> 0.9 s). Stopped with the "
        "mapper, restarted if they exit. 0: the mapper computes keyframes itself while no other worker is alive "
        "(set 0 where GPU workers on other machines do the work). Default: $ARGUS_LOCAL_WORKERS, else 1",
    )
    local_torch_threads: int | None = Field(
        default=None, ge=1, le=64, description="torch CPU threads of each local worker (default: the mapper's)"
    )

    def dispatch(self) -> DispatchConfig:
        return DispatchConfig(self.ack_timeout_s, self.result_timeout_s, self.max_attempts, self.quarantine_after,
                              self.max_in_flight, self.max_jobs, max_frame_age_s=self.max_frame_age_s,
                              fair=self.fair_order)


class WorkerConfig(BaseModel):
    """``argus worker``: takes keyframe jobs from the mapper of its site. The geometry and perception settings
    come with each job (the mapper's own), so a worker needs only to know where the site is."""

    model_config = ConfigDict(extra="forbid")
    id: str = Field(default="worker", description="worker id (unique per site: job, ack, result, status keys)")
    site: SiteName = Field(
        default_factory=default_site, validate_default=True,
        description="Argus site name (key prefix argus/<site>/...; default $ARGUS_SITE or default)",
    )
    key_prefix: str = Field(default="argus", description="key expression prefix")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how to join Zenoh")
    torch_threads: int = Field(default=2, ge=1, le=64, description="torch CPU threads")
    queue_depth: int = Field(
        default=2, ge=1, le=16, description="jobs held at once (taking one more answers busy: the mapper re-issues it)"
    )
    max_job_bytes: int = Field(default=16 * 1024 * 1024, ge=1024, description="larger job samples are refused")
    fetch_timeout_s: float = Field(default=5.0, gt=0.0, description="wait for a source keyframe's JPEG")
    image_cache: int = Field(default=64, ge=0, description="decoded source keyframes kept (they recur across jobs)")
    max_image_pixels: int = Field(
        default=4096 * 4096, ge=1,
        description="largest image decoded (at the size the job names: the mapper's working size, its JPEG "
        "decoded at 1/1, 1/2, 1/4 or 1/8)",
    )
    max_decode_bytes: int = Field(
        default=MAX_DECODE_BYTES, ge=1024 * 1024,
        description="memory libjpeg may take to decode one JPEG of a job (protocol.jpeg.JpegInfo.decode_bytes, "
        "from its headers: the decoded image, and a progressive JPEG's DCT coefficients); over it the job fails",
    )
    status_period_s: float = Field(default=1.0, gt=0.0, description="status publishing period")
    release_heap_after_job: bool = Field(
        default=True,
        description="after each job, give the C heap's freed memory back to the system (glibc malloc_trim, a few "
        "ms; counter heap_releases): a job's large temporary arrays otherwise leave the resting RSS creeping up "
        "(a 30-minute soak: 523 -> 865 MiB, 635 MiB right after one release)",
    )
    warm_up: bool = Field(
        default=True,
        description="before declaring itself alive, run one small synthetic keyframe (mapper.work.compute.warm_up) "
        "with the default mapper settings, so the first real job does not also pay the process's one-time costs "
        "(JIT kernels, lazy imports, first calls: ~1-4 s on 2 cores); meanwhile the mapper maps keyframes itself",
    )
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(default="INFO", description="log level")
