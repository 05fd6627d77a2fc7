"""The geometry contract: MapAnything-style factored reconstruction and its composition into metric points.

A ``Reconstructor`` takes N views and returns, per view, unit ray directions in the camera frame, depth
along those rays up to one global scale, each view's pose in the FIRST view's frame (translation at the
same scale) and one metric scale factor. ``compose`` multiplies the scale back in and anchors everything
at the first view's known world pose, which is all that is needed to put every view in the world frame
(the paper's "Depths and Poses Estimation").

Conventions are those of ``protocol.poses``: OpenCV camera axes, ``T_a_b`` maps frame-b points into
frame a, metres once composed. Pure numpy, no I/O.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from protocol.messages import Intrinsics
from protocol.poses import as_pose

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

CONFIDENT = 0.5
"""A pixel whose confidence is at least this is "confident": consumers fuse it, benchmarks score it."""


@dataclass(frozen=True)
class OracleData:
    """Simulator ground truth for one view: an ORACLE, used only by the ``oracle`` backend and benchmarks.

    depth_m: (H, W) float32 z-depth in metres (0 = no hit); T_world_cam_true: (4, 4) true pose;
    instance_id: (H, W) int32 (0 structure, -1 nothing, k >= 1 object id); labels: object id -> label.
    """

    depth_m: F32
    T_world_cam_true: F64
    instance_id: NDArray[np.int32] | None = None
    labels: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class View:
    """One RGB image handed to a reconstructor.

    image: (H, W, 3) uint8 RGB. intrinsics: None for an uncalibrated camera. T_world_cam: a pose prior
    (odometry) or a calibration, None when unknown; ``pose_trusted`` says it is a surveyed calibration
    that reconstruction must not move. prior_rel_rot_deg: how accurate the prior's rotation is *relative to
    the same source's other priors* (std-dev, degrees), when the source knows it: ~0.05 for visual-inertial
    tracking, motion capture or a gyro, ~1 for priors with independent per-frame errors; None lets the
    reconstructor judge it from the images; ``math.inf`` says the prior's errors are independent per frame
    (no relative information beyond the absolute prior). prior_rel_trans_m: the same for the relative
    translation (std-dev, metres; None: the reconstructor's default). pose_covariance: the 6x6 covariance the
    frame's header declared for its pose (x y z roll pitch yaw; m^2, rad^2), None when it declared none; between
    two views of one source its growth is the drift accrued in between (odometry, visual-inertial tracking),
    on top of the per-frame accuracy in ``prior_rel_*`` (``mapper.inbox.PriorAccuracy`` derives both from the
    wire). oracle: ORACLE truth (simulated sources only).
    """

    image: NDArray[np.uint8]
    source_id: str
    intrinsics: Intrinsics | None = None
    T_world_cam: F64 | None = None
    pose_trusted: bool = False
    stamp_ns: int = 0
    seq: int = 0
    oracle: OracleData | None = None
    prior_rel_rot_deg: float | None = None
    prior_rel_trans_m: float | None = None
    pose_covariance: F64 | None = None
    map_always: bool = False  # the sender needs it mapped: never shed under load (FrameHeader.map_always)

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"View.image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        if self.intrinsics is not None and (
            self.intrinsics.width != img.shape[1] or self.intrinsics.height != img.shape[0]
        ):
            raise ValueError(
                f"intrinsics are for {self.intrinsics.width}x{self.intrinsics.height}, "
                f"image is {img.shape[1]}x{img.shape[0]}"
            )
        if self.T_world_cam is not None:
            object.__setattr__(self, "T_world_cam", as_pose(self.T_world_cam))

    @property
    def key(self) -> tuple[str, int]:
        """Identity of the frame (source, sequence number), used for caches."""
        return (self.source_id, self.seq)


@dataclass
class FactoredReconstruction:
    """What every backend returns (MapAnything's factored form).

    ray_dirs: (N, h, w, 3) float32 unit vectors in each camera frame; depth_along_ray: (N, h, w) float32
    up to ``metric_scale``; T_first_cam: (N, 4, 4) pose of each view in the first view's frame, its
    translation at the same scale as the depth; confidence: (N, h, w) float32 in [0, 1] (0 = no depth);
    intrinsics: per view, at the output resolution; info: timings, inlier counts, ... Keys with a
    meaning for callers: ``T_world_first`` (the backend's own world pose of view 0, see ``anchor_pose``) and
    ``pose_ok`` (per view; False where no pose could be estimated: that view's T_first_cam is a placeholder
    and its confidence is 0, so do not store its pose).
    """

    ray_dirs: F32
    depth_along_ray: F32
    T_first_cam: F64
    metric_scale: float
    confidence: F32
    intrinsics: list[Intrinsics]
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.intrinsics)
        if self.ray_dirs.ndim != 4 or self.ray_dirs.shape[0] != n or self.ray_dirs.shape[3] != 3:
            raise ValueError(f"ray_dirs must be (N, h, w, 3) with N={n}, got {self.ray_dirs.shape}")
        hw = self.ray_dirs.shape[:3]
        if self.depth_along_ray.shape != hw or self.confidence.shape != hw:
            raise ValueError("depth_along_ray and confidence must be (N, h, w) like ray_dirs")
        if self.T_first_cam.shape != (n, 4, 4):
            raise ValueError(f"T_first_cam must be (N, 4, 4), got {self.T_first_cam.shape}")
        if not np.isfinite(self.metric_scale) or self.metric_scale <= 0:
            raise ValueError(f"metric_scale must be finite and > 0, got {self.metric_scale}")

    @property
    def n_views(self) -> int:
        return int(self.ray_dirs.shape[0])


@dataclass
class ComposedGeometry:
    """Metric world geometry: points_world (N, h, w, 3), depth_m (N, h, w) z-depth, T_world_cam (N, 4, 4),
    confidence (N, h, w), intrinsics per view at the output resolution."""

    points_world: F32
    depth_m: F32
    T_world_cam: F64
    confidence: F32
    intrinsics: list[Intrinsics]


def compose(recon: FactoredReconstruction, T_world_first: F64, views: Sequence[int] | None = None) -> ComposedGeometry:
    """Metric world points, z-depths and poses from a factored reconstruction.

    Scale multiplies both the depths and the relative translations; the first view's world pose fixes
    the frame: ``T_world_cam_i = T_world_first @ scaled(T_first_cam_i)``. ``views``: only these views, in this
    order (a keyframe job needs its target's points, not its sources'); default: all.
    """
    T_wf = as_pose(T_world_first)
    m = float(recon.metric_scale)
    sel = list(range(len(recon.intrinsics))) if views is None else list(views)
    T_first_cam = np.array(recon.T_first_cam, dtype=np.float64, copy=True)[sel]
    T_first_cam[:, :3, 3] *= m
    T_world_cam = T_wf @ T_first_cam
    depth_ray = recon.depth_along_ray[sel].astype(np.float64) * m
    points_cam = recon.ray_dirs[sel].astype(np.float64) * depth_ray[..., None]
    R = T_world_cam[:, :3, :3]
    t = T_world_cam[:, :3, 3]
    n, h, w = depth_ray.shape
    # One BLAS product per view (numpy's einsum here was ~60 ms per 320x240 view, a tenth of a keyframe).
    points_world = np.matmul(points_cam.reshape(n, h * w, 3), R.transpose(0, 2, 1)).reshape(n, h, w, 3)
    points_world += t[:, None, None, :]
    return ComposedGeometry(
        points_world=points_world.astype(np.float32),
        depth_m=points_cam[..., 2].astype(np.float32),
        T_world_cam=T_world_cam,
        confidence=recon.confidence[sel].astype(np.float32),
        intrinsics=[recon.intrinsics[i] for i in sel],
    )


def pixel_rays(intrinsics: Intrinsics) -> F32:
    """Unit ray directions (h, w, 3) in the camera frame through every pixel centre."""
    u = np.arange(intrinsics.width, dtype=np.float64)
    v = np.arange(intrinsics.height, dtype=np.float64)
    uu, vv = np.meshgrid(u, v)
    d = np.stack(
        [(uu - intrinsics.cx) / intrinsics.fx, (vv - intrinsics.cy) / intrinsics.fy, np.ones_like(uu)], axis=-1
    )
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _shared_pixel_rays(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> F32:
    """:func:`pixel_rays` of a camera, computed once per process and read-only: every keyframe of a camera has the
    same rays (~4 ms each time at 320 x 240)."""
    rays = pixel_rays(Intrinsics(width=width, height=height, fx=fx, fy=fy, cx=cx, cy=cy))
    rays.setflags(write=False)
    return rays


def z_to_ray_depth(depth_m: NDArray[np.floating], rays: F32) -> F32:
    """Convert z-depth (h, w) to depth along the unit rays (h, w, 3) of the same pixels."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(rays[..., 2] > 0, depth_m / rays[..., 2], 0.0)
    return out.astype(np.float32)


def factored_from_metric(
    depth_m: Sequence[NDArray[np.floating]],
    T_world_cam: Sequence[F64],
    confidence: Sequence[NDArray[np.floating]],
    intrinsics: Sequence[Intrinsics],
    info: dict[str, Any] | None = None,
) -> FactoredReconstruction:
    """Build the factored form (metric_scale 1, poses relative to view 0) from metric z-depths and poses.

    Backends that work in metres (``mvs``, ``oracle``) use this so every backend returns the same type.
    """
    if not depth_m:
        raise ValueError("need at least one view")
    T_first_world = np.linalg.inv(as_pose(T_world_cam[0]))
    # Views with the same intrinsics share their rays, computed once per process.
    rays = [_shared_pixel_rays(k.width, k.height, k.fx, k.fy, k.cx, k.cy) for k in intrinsics]
    return FactoredReconstruction(
        ray_dirs=np.stack(rays).astype(np.float32),
        depth_along_ray=np.stack([z_to_ray_depth(d, r) for d, r in zip(depth_m, rays, strict=True)]),
        T_first_cam=np.stack([T_first_world @ as_pose(T) for T in T_world_cam]),
        metric_scale=1.0,
        confidence=np.stack([np.clip(c, 0.0, 1.0) for c in confidence]).astype(np.float32),
        intrinsics=list(intrinsics),
        info=dict(info or {}),
    )


def anchor_pose(recon: FactoredReconstruction, views: Sequence[View]) -> F64:
    """The world pose to pass to ``compose``: the backend's own estimate of the first view's pose
    (``info["T_world_first"]``, e.g. refined by bundle adjustment or the ORACLE truth) when it has one,
    else the first view's prior. Raises ``ValueError`` when neither exists."""
    T = recon.info.get("T_world_first")
    if T is None:
        T = views[0].T_world_cam if views else None
    if T is None:
        raise ValueError("the first view has no world pose: give it a prior or a calibration")
    return as_pose(T)


@runtime_checkable
class Reconstructor(Protocol):
    """A geometry backend. ``targets``: indices of views that need dense depth (default all); other views
    still get a pose but confidence 0 everywhere."""

    name: str

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        ...
