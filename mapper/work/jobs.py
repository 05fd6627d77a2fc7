"""Keyframe jobs and results on the wire (pure: no Zenoh).

A job (:class:`protocol.messages.WorkJob`) names its keyframe ``<source_id>#<seq>``, carries the keyframe's
JPEG, the window of views to reconstruct with (the keyframe and its source keyframes: ids, intrinsics and the
poses the mapper holds; their JPEGs are fetched from the mapper's keyframe store) and the mapper's core
settings. A result (:class:`protocol.messages.WorkResult`) carries the keyframe's z-depth as a 16-bit PNG
(``depth_unit_m`` metres per unit: 1 mm up to 65 m), its confidence as a 16-bit PNG, its refined pose and its
2D detections (masks as 8-bit PNGs).

Nothing a worker sends reaches the graph unchecked: :func:`decode_result` refuses a result whose arrays have
the wrong shapes, whose depth or confidence is not finite or out of range, whose pose is not rigid, or whose
detections disagree with the image, with a reason (:class:`ResultRejected`); the dispatcher counts it against
the worker (:mod:`mapper.work.dispatch`).
"""

from __future__ import annotations

import hashlib
import json
from typing import Any, cast

import cv2
import numpy as np

from mapper.config import MapperCoreConfig
from mapper.geometry.contract import View
from mapper.geometry.singleview import depth_to_world
from mapper.perception.base import Detection, ViewGeometry
from mapper.work.compute import KeyframeProducts
from protocol.jpeg import JpegError
from protocol.messages import Intrinsics, Reduction, WorkDetection, WorkFrame, WorkJob, WorkResult
from protocol.oracle import decode_u16_png, encode_u16_png, png_size
from protocol.poses import PoseError, check_pose

Problem = tuple[str, str]
"""``(reason, detail)``: the counter a rejected result is counted under and a sentence for the log."""
DEPTH_UNIT_M = 0.001
"""Metres per depth PNG unit unless the depth is deeper than 65.535 m (then coarser, see :func:`encode_products`)."""
MAX_DEPTH_M = 1000.0
"""Deeper depth from a worker is garbage."""
MAX_DEPTH_PIXELS_PER_IMAGE_PIXEL = 16
"""A depth map may be finer than its image (some backends upsample), up to this many times its pixels."""


class ResultRejected(ValueError):
    """A worker's result that must not reach the graph."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail


def job_id_of(key: tuple[str, int]) -> str:
    """The id of the job of keyframe ``(source_id, seq)``: results are idempotent by it."""
    return f"{key[0]}#{key[1]}"


def core_settings(config: MapperCoreConfig) -> tuple[dict[str, Any], str]:
    """The core settings a worker must run with (JSON-able) and their digest."""
    settings = MapperCoreConfig.model_validate(
        config.model_dump(include=set(MapperCoreConfig.model_fields))).model_dump(mode="json")
    text = json.dumps(settings, sort_keys=True)
    return settings, hashlib.sha256(text.encode()).hexdigest()[:32]


def frame_of(view: View, reduction: int = 1) -> WorkFrame:
    """``view`` for a job; its image is its JPEG decoded at 1/``reduction`` (the mapper's working size)."""
    h, w = view.image.shape[:2]
    return WorkFrame(source_id=view.source_id, seq=view.seq, stamp_ns=view.stamp_ns, width=w, height=h,
                     reduction=cast(Reduction, reduction), intrinsics=view.intrinsics,  # pydantic checks it
                     T_world_cam=None if view.T_world_cam is None else view.T_world_cam.tolist(),
                     pose_trusted=view.pose_trusted,
                     pose_covariance=None if view.pose_covariance is None else view.pose_covariance.tolist(),
                     prior_rel_trans_m=view.prior_rel_trans_m, prior_rel_rot_deg=view.prior_rel_rot_deg)


def view_of(frame: WorkFrame, image: np.ndarray) -> View:
    """The :class:`View` a worker reconstructs: ``frame`` with its decoded ``image`` (ValueError if they disagree)."""
    if image.shape[:2] != (frame.height, frame.width):
        raise ValueError(f"image of {frame.source_id}#{frame.seq} is {image.shape[1]}x{image.shape[0]}, "
                         f"the job says {frame.width}x{frame.height}")
    return View(image=image, source_id=frame.source_id, intrinsics=frame.intrinsics,
                T_world_cam=None if frame.T_world_cam is None else np.asarray(frame.T_world_cam),
                pose_trusted=frame.pose_trusted, stamp_ns=frame.stamp_ns, seq=frame.seq,
                pose_covariance=None if frame.pose_covariance is None else np.asarray(frame.pose_covariance),
                prior_rel_trans_m=frame.prior_rel_trans_m, prior_rel_rot_deg=frame.prior_rel_rot_deg)


def make_job(views: list[View], target: int, jpeg: bytes, attempt: int, perception: bool,
             config: MapperCoreConfig, reductions: list[int] | None = None) -> WorkJob:
    """The job of keyframe ``views[target]`` (its JPEG: ``jpeg``); ``reductions``: each view's JPEG was decoded at
    1/that (default 1: at full size)."""
    settings, digest = core_settings(config)
    scale = reductions or [1] * len(views)
    return WorkJob(job_id=job_id_of(views[target].key), attempt=attempt,
                   window=[frame_of(v, r) for v, r in zip(views, scale, strict=True)],
                   target_index=target, jpeg=jpeg, perception=perception, core_config=settings,
                   config_digest=digest)


# --- worker side: products -> result -------------------------------------------------------------------
def _mask_png(mask: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.asarray(mask, dtype=bool).astype(np.uint8))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def _float_vector(a: np.ndarray) -> np.ndarray:
    """A descriptor as it is (float32 or float64: exactly the mapper's own), anything else as float32."""
    a = np.asarray(a)
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float32)


def encode_products(products: KeyframeProducts | None, job: WorkJob, worker_id: str,
                    timings_s: dict[str, float] | None = None) -> WorkResult:
    """A worker's answer to ``job``: ``products`` compressed (None: the keyframe could not be anchored)."""
    if products is None:
        return WorkResult(job_id=job.job_id, attempt=job.attempt, worker_id=worker_id, ok=True, anchored=False,
                          timings_s=timings_s or {})
    g = products.geometry
    d = np.where(np.isfinite(g.depth_m) & (g.depth_m > 0), g.depth_m, 0.0).astype(np.float64)
    unit = max(DEPTH_UNIT_M, float(d.max(initial=0.0)) / 65535.0)
    conf = np.clip(np.nan_to_num(g.confidence.astype(np.float64), nan=0.0), 0.0, 1.0)
    h, w = d.shape
    K = products.K
    dets = None if products.detections is None else [
        WorkDetection(mask_png=_mask_png(x.mask), label=x.label, confidence=float(x.confidence),
                      descriptor=_float_vector(x.descriptor),
                      alternatives=[(str(a), float(b)) for a, b in x.alternatives], instance_key=int(x.instance_key))
        for x in products.detections
    ]
    return WorkResult(
        job_id=job.job_id, attempt=job.attempt, worker_id=worker_id, ok=True,
        T_world_cam=np.asarray(products.T_world_cam).tolist(),
        intrinsics=Intrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                              width=w, height=h),
        depth_png=encode_u16_png(np.round(d / unit).astype(np.uint16)), depth_unit_m=unit,
        confidence_png=encode_u16_png(np.round(conf * 65535.0).astype(np.uint16)),
        detections=dets, timings_s={**products.timings_s, **(timings_s or {})},
    )


# --- mapper side: result -> products, checked ----------------------------------------------------------
def _u16(data: bytes | None, what: str, max_pixels: int) -> np.ndarray:
    if data is None:
        raise ResultRejected("result_incomplete", f"no {what}")
    try:
        return decode_u16_png(data, max_pixels=max_pixels)
    except (JpegError, ValueError) as e:
        raise ResultRejected("result_bad_image", f"{what}: {e}") from None


def _mask(data: bytes, shapes: set[tuple[int, int]]) -> np.ndarray:
    try:
        w, h = png_size(data)
    except JpegError as e:
        raise ResultRejected("result_bad_detection", f"mask: {e}") from None
    if (h, w) not in shapes:
        raise ResultRejected("result_bad_shape", f"mask is {w}x{h}, neither the image's nor the depth's size")
    m = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if m is None or m.shape != (h, w):
        raise ResultRejected("result_bad_detection", "mask PNG does not decode to one channel")
    return m != 0


def decode_result(result: WorkResult, job: WorkJob) -> KeyframeProducts | None:
    """The products of an ``ok`` result of ``job`` (None: not anchored), checked; raises :class:`ResultRejected`.
    Masks may come at the image's size or at the depth's (some segmenters work on the geometry)."""
    if not result.anchored:
        return None
    if result.T_world_cam is None or result.intrinsics is None:
        raise ResultRejected("result_incomplete", "no pose or no intrinsics")
    target = job.window[job.target_index]
    pixels = MAX_DEPTH_PIXELS_PER_IMAGE_PIXEL * target.width * target.height
    depth = _u16(result.depth_png, "depth", pixels).astype(np.float32) * np.float32(result.depth_unit_m)
    conf = _u16(result.confidence_png, "confidence", pixels).astype(np.float32) / np.float32(65535.0)
    intr = result.intrinsics
    if (intr.height, intr.width) != depth.shape:
        raise ResultRejected("result_bad_shape", f"intrinsics are for {intr.width}x{intr.height}, depth is "
                             f"{depth.shape[1]}x{depth.shape[0]}")
    try:
        T = check_pose(result.T_world_cam, source=f"result of {job.job_id}").T
    except PoseError as e:
        raise ResultRejected("result_bad_pose", str(e)) from None
    K = intr.K()
    dets = None
    if result.detections is not None:
        shapes = {(target.height, target.width), depth.shape}
        dets = [Detection(mask=_mask(d.mask_png, shapes), label=d.label,
                          confidence=d.confidence, descriptor=d.descriptor, alternatives=tuple(d.alternatives),
                          instance_key=d.instance_key) for d in result.detections]
    vg = ViewGeometry(points_world=depth_to_world(depth, K, T), depth_m=depth, confidence=conf)
    products = KeyframeProducts(vg, T, K, dets, dict(result.timings_s))
    problem = products_problem(products, (target.height, target.width))
    if problem is not None:
        raise ResultRejected(*problem)
    return products


def products_problem(p: KeyframeProducts, image_hw: tuple[int, int]) -> Problem | None:
    """Why ``p`` cannot be fused into the graph of a keyframe whose image is ``image_hw`` (rows, cols), or None."""
    g = p.geometry
    d, c, pts = np.asarray(g.depth_m), np.asarray(g.confidence), np.asarray(g.points_world)
    if d.ndim != 2 or d.size == 0 or c.shape != d.shape or pts.shape != (*d.shape, 3):
        return "result_bad_shape", f"depth {d.shape}, confidence {c.shape}, points {pts.shape} disagree"
    if d.size > MAX_DEPTH_PIXELS_PER_IMAGE_PIXEL * image_hw[0] * image_hw[1]:
        return "result_bad_shape", f"depth of {d.shape} is far larger than the image {image_hw}"
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(c)) and np.all(np.isfinite(pts))):
        return "result_not_finite", "depth, confidence or points hold NaN or inf"
    if d.min() < 0.0 or d.max() > MAX_DEPTH_M:
        return "result_bad_depth", f"depth outside [0, {MAX_DEPTH_M:g}] m: {d.min():.3g}..{d.max():.3g}"
    if c.min() < 0.0 or c.max() > 1.0:
        return "result_bad_depth", f"confidence outside [0, 1]: {c.min():.3g}..{c.max():.3g}"
    K = np.asarray(p.K)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return "result_bad_shape", "intrinsics are not a camera matrix"
    try:
        check_pose(p.T_world_cam)
    except PoseError as e:
        return "result_bad_pose", str(e)
    return _detections_problem(p.detections, {image_hw, d.shape})


def _detections_problem(dets: list[Detection] | None, shapes: set[tuple[int, ...]]) -> Problem | None:
    """Masks at the image's or the depth's size (fusion resizes them to the depth), finite descriptors."""
    dims = set()
    for x in dets or []:
        if np.asarray(x.mask).shape not in shapes:
            return "result_bad_shape", f"a mask is {np.asarray(x.mask).shape}, not one of {sorted(shapes)}"
        desc = np.asarray(x.descriptor)
        if desc.ndim != 1 or desc.size == 0 or desc.dtype.kind != "f" or not np.all(np.isfinite(desc)):
            return "result_bad_detection", f"descriptor of shape {desc.shape} ({desc.dtype}) is not a finite vector"
        dims.add(desc.size)
        if not (np.isfinite(x.confidence) and 0.0 <= x.confidence <= 1.0):
            return "result_bad_detection", f"label confidence {x.confidence!r} is not in [0, 1]"
    if len(dims) > 1:
        return "result_bad_detection", f"descriptors of different sizes {sorted(dims)}"
    return None
