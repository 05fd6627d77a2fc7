"""The heavy per-keyframe work, the same wherever it runs (the mapper's own thread or an ``argus worker``).

``compute_keyframe`` reconstructs a window of views (the keyframe and its chosen source keyframes), places
the keyframe in the world and, unless told not to, runs 2D perception on it. It has no state: what it
returns depends only on its inputs and the backends, so a worker's answer is the mapper's own answer.
Everything after it (typical depth, the depth check, the keyframe store, fusion, edges) reads or writes
the mapper's state and stays in the mapper (:meth:`mapper.core.MapperCore.apply_products`).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mapper.config import MapperCoreConfig
from mapper.fusion import outside_fraction
from mapper.geometry.contract import Reconstructor, View, anchor_pose, compose
from mapper.perception.base import Detection, Embedder, Segmenter, ViewGeometry


@dataclass(frozen=True)
class KeyframeProducts:
    """What the heavy work gives for one keyframe.

    geometry: the keyframe's world points, z-depth and confidence at the geometry's resolution (h, w);
    T_world_cam: its refined pose (4, 4); K: its intrinsics (3, 3) at that resolution; detections: its 2D
    detections at the image's resolution, or None when perception was not run (the mapper runs it).
    """

    geometry: ViewGeometry
    T_world_cam: np.ndarray
    K: np.ndarray
    detections: list[Detection] | None
    timings_s: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds of this process per stage: ``geometry.<stage>`` (the reconstructor's own stages when it reports
    them in ``info["cpu_stage_s"]``, as ``mvs`` does; ``geometry.place`` for anchoring and composing), and
    ``perception``."""


def runs_perception(config: MapperCoreConfig) -> bool:
    """Whether 2D perception belongs to the heavy work: not when the depth check must first change the
    confidence perception reads (estimated depth with ``depth_check.enabled``)."""
    return not (config.depth_check.enabled and config.geometry.backend != "oracle")


def compute_keyframe(reconstructor: Reconstructor, segmenter: Segmenter, embedder: Embedder,
                     config: MapperCoreConfig, views: Sequence[View], target: int,
                     perception: bool | None = None) -> KeyframeProducts | None:
    """Reconstruct ``views`` for ``views[target]`` and, when ``perception`` (default: :func:`runs_perception`),
    segment and describe it; None when the reconstruction cannot be placed in the world (no posed view).

    Perception is skipped for depth that puts too much of the view outside the room's slab: the mapper
    rejects such a keyframe before perception anyway (``keyframes_rejected_depth``)."""
    t, c = time.perf_counter(), time.process_time()
    recon = reconstructor.reconstruct(views, targets=[target])
    c_recon = time.process_time()
    try:
        T_world_first = anchor_pose(recon, views)
    except ValueError:
        return None
    limit = getattr(reconstructor, "thread_limit", None)
    with limit() if callable(limit) else contextlib.nullcontext():
        # Under the reconstructor's thread limit like the reconstruction: with BLAS's default pool (a thread per
        # core) its idle thread spins on a busy machine (23 -> 7 ms of CPU per keyframe measured, same numbers).
        geo = compose(recon, T_world_first, views=[target])  # the sources' points are not this job's
    times = {"geometry": time.perf_counter() - t}
    cpu = stage_cpu(recon.info, c_recon - c)
    cpu["geometry.place"] = time.process_time() - c_recon
    vg = ViewGeometry(points_world=geo.points_world[0], depth_m=geo.depth_m[0], confidence=geo.confidence[0])
    dets = None
    if runs_perception(config) if perception is None else perception:
        fc = config.fusion
        if outside_fraction(vg.points_world, vg.confidence, vg.depth_m, fc) <= fc.max_outside_fraction:
            t, c = time.perf_counter(), time.process_time()
            view = views[target]
            dets = embedder.embed(view, segmenter.segment(view, vg))
            times["perception"] = time.perf_counter() - t
            cpu["perception"] = time.process_time() - c
    return KeyframeProducts(vg, geo.T_world_cam[0], geo.intrinsics[0].K(), dets, times, cpu)


def stage_cpu(info: dict[str, object], total_s: float) -> dict[str, float]:
    """A reconstruction's CPU seconds by stage as ``geometry.<stage>``, from ``info["cpu_stage_s"]`` (less its
    ``total``) when the reconstructor reports one, else all of ``total_s`` as ``geometry.reconstruct``."""
    stages = info.get("cpu_stage_s")
    if not isinstance(stages, dict):
        return {"geometry.reconstruct": total_s}
    return {f"geometry.{k}": float(v) for k, v in stages.items() if k != "total" and isinstance(v, (int, float))}


def warm_up_views(width: int = 320, height: int = 240, seed: int = 0) -> list[View]:
    """Two views of a textured plane 2 m in front, 10 cm apart (posed, calibrated): a keyframe job small enough
    to run at a worker's start (:func:`warm_up`) that still takes every path of a real one."""
    from protocol.messages import Intrinsics

    rng = np.random.default_rng(seed)
    f = 0.8 * width
    intr = Intrinsics(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2)
    # Blobs of every scale on the plane: SIFT finds corners, the census finds texture.
    tex = np.zeros((height, width + 40), np.float32)
    for s in (2, 4, 8, 16):
        small = rng.random((height // s + 2, (width + 40) // s + 2)).astype(np.float32)
        tex += np.kron(small, np.ones((s, s), np.float32))[:height, : width + 40] / 4
    img = (255 * tex).astype(np.uint8)
    shift = round(f * 0.10 / 2.0)  # 10 cm at 2 m: the plane moves this many pixels between the views
    views = []
    for i, (x0, cam_x) in enumerate(((0, 0.0), (shift, 0.10))):  # camera right: the plane moves left
        T = np.eye(4)
        T[0, 3] = cam_x
        rgb = np.repeat(img[:, x0 : x0 + width, None], 3, axis=2)
        views.append(View(image=np.ascontiguousarray(rgb), source_id="warm-up", intrinsics=intr, T_world_cam=T,
                          seq=i, stamp_ns=i))
    return views


def warm_up(reconstructor: Reconstructor, segmenter: Segmenter, embedder: Embedder, config: MapperCoreConfig,
            perception: bool | None = None) -> float:
    """Run one small synthetic keyframe (:func:`warm_up_views`) through :func:`compute_keyframe`, so the first real
    job does not also pay for what a process does once (JIT kernels loaded, lazy imports, first calls of the
    numeric libraries): about a second of the first keyframe's latency. Returns its seconds; never raises (a
    warm-up that fails only leaves the cost to the first job)."""
    t = time.perf_counter()
    try:
        compute_keyframe(reconstructor, segmenter, embedder, config, warm_up_views(), 0, perception=perception)
    except Exception:  # noqa: BLE001 - a failed warm-up only leaves that cost to the first job
        return math.nan
    return time.perf_counter() - t
