"""Sparse image features for pose refinement and registration: SIFT, ratio-test matching, epipolar check.

Pure functions over arrays plus a small bounded cache object (owned by whoever uses it, never global).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Features:
    """Keypoints ``uv`` (K, 2) float64 in full-image pixels and their SIFT descriptors (K, 128) float32."""

    uv: F64
    desc: NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.uv.shape[0])


def to_gray(image_rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """RGB uint8 to 8-bit grey."""
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2GRAY), dtype=np.uint8)


def extract_features(image_rgb: NDArray[np.uint8], max_features: int = 2000, contrast: float = 0.01) -> Features:
    """SIFT keypoints and descriptors of an RGB image (RootSIFT-normalised for better matching).

    The contrast threshold is half OpenCV's default: indoor surfaces are often low-contrast and the
    ratio test plus geometric checks remove the weaker matches this lets through."""
    sift = cv2.SIFT.create(nfeatures=max_features, contrastThreshold=contrast)
    kps, desc = sift.detectAndCompute(to_gray(image_rgb), None)
    if desc is None or not kps:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-9)
    d = np.sqrt(d)
    return Features(np.array([k.pt for k in kps], dtype=np.float64), d)


def match_features(a: Features, b: Features, ratio: float = 0.8) -> NDArray[np.int64]:
    """Mutual nearest neighbours passing Lowe's ratio test: (M, 2) indices into ``a`` and ``b``.

    One dense distance matrix serves both directions (descriptors are unit length after RootSIFT, so
    squared distance = 2 - 2 a.b): a single BLAS product instead of two brute-force searches."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    import torch

    from mapper.geometry import kernels

    # NumPy's product (OpenBLAS): torch's CPU build multiplies with MKL, which takes ~2x as long on AMD processors.
    sim = torch.from_numpy(np.ascontiguousarray(a.desc, dtype=np.float32) @ np.ascontiguousarray(b.desc, np.float32).T)
    if kernels.AVAILABLE:
        # A row whose maximum repeats fails the ratio test below whichever of its columns is named.
        nn_ab_np, top2, nn_ba_np = kernels.nearest_both_ways(sim.numpy())
        nn_ab, values, nn_ba = torch.from_numpy(nn_ab_np), torch.from_numpy(top2), torch.from_numpy(nn_ba_np)
    else:
        two = torch.topk(sim, 2, dim=1)
        nn_ab, values = two.indices[:, 0], two.values
        nn_ba = sim.T.contiguous().argmax(dim=1)  # a row-wise reduction on the transposed copy is the fast one
    d2 = (2.0 - 2.0 * values).clamp_(min=0.0)
    # Lowe's test on distances (not squared): d1 < ratio * d2  <=>  d1^2 < ratio^2 * d2^2.
    ok = d2[:, 0] < (ratio * ratio) * d2[:, 1]
    # Mutual check: repetitive indoor textures make one-way matches much dirtier (measured on sim scenes).
    ok &= nn_ba[nn_ab] == torch.arange(len(a))
    ia = torch.nonzero(ok).flatten()
    return np.stack([ia.numpy(), nn_ab[ia].numpy()], axis=1).astype(np.int64).reshape(-1, 2)


def normalise(uv: F64, K: F64) -> F64:
    """Pixels to normalised image coordinates (z = 1)."""
    return (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def epipolar_inliers(uv_a: F64, uv_b: F64, K_a: F64, K_b: F64, thresh_px: float = 2.0) -> NDArray[np.bool_]:
    """Inliers of an essential-matrix RANSAC between two calibrated views (all False if it fails)."""
    return essential_geometry(uv_a, uv_b, K_a, K_b, thresh_px)[0]


def essential_geometry(
    uv_a: F64, uv_b: F64, K_a: F64, K_b: F64, thresh_px: float = 2.0
) -> tuple[NDArray[np.bool_], F64 | None]:
    """Essential-matrix RANSAC between two calibrated views: inlier mask and the relative rotation
    ``R_b_a`` (camera-a directions into camera b) the images alone give, None when it fails.

    The rotation is well determined by the images even where the translation direction is not (small
    baselines), which makes it a check on a pose prior's relative rotation."""
    inl, R, _ = essential_pose(uv_a, uv_b, K_a, K_b, thresh_px)
    return inl, R


def essential_pose(
    uv_a: F64, uv_b: F64, K_a: F64, K_b: F64, thresh_px: float = 2.0, method: int = cv2.RANSAC,
    min_inliers: int = 15,
) -> tuple[NDArray[np.bool_], F64 | None, F64 | None]:
    """Essential-matrix estimation (``method``: ``cv2.RANSAC``, ``cv2.USAC_ACCURATE``, ...) between two
    calibrated views: inlier mask, relative rotation ``R_b_a`` and unit translation direction ``t_b_a``
    (x_b = R x_a + t); both None when it fails or keeps fewer than ``min_inliers`` inliers."""
    n = uv_a.shape[0]
    if n < 8:
        return np.zeros(n, bool), None, None
    f = 0.5 * (K_a[0, 0] + K_b[0, 0])
    na, nb = normalise(uv_a, K_a), normalise(uv_b, K_b)
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=method, prob=0.999, threshold=thresh_px / f)
    if E is None or mask is None or E.shape != (3, 3):
        return np.zeros(n, bool), None, None
    inl = mask.reshape(-1).astype(bool)
    if inl.sum() < min_inliers:
        return inl, None, None
    _, R, t, _ = cv2.recoverPose(E, na[inl], nb[inl], np.eye(3))
    return inl, np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)


class LruCache:
    """A small bounded least-recently-used cache."""

    def __init__(self, capacity: int) -> None:
        self.capacity = max(1, capacity)
        self._d: OrderedDict[Hashable, object] = OrderedDict()

    def get(self, key: Hashable) -> object | None:
        if key in self._d:
            self._d.move_to_end(key)
            return self._d[key]
        return None

    def put(self, key: Hashable, value: object) -> None:
        self._d[key] = value
        self._d.move_to_end(key)
        while len(self._d) > self.capacity:
            self._d.popitem(last=False)

    def values(self) -> list[object]:
        """The cached values, least recently used first."""
        return list(self._d.values())

    def __len__(self) -> int:
        return len(self._d)


def prior_consistent(
    uv_a: F64, uv_b: F64, K_a: F64, K_b: F64, T_b_a: F64, depth_range_m: tuple[float, float], tol_px: float
) -> NDArray[np.bool_]:
    """Matches that the prior relative pose can explain: the point in view b lies within ``tol_px`` of the
    segment that view a's ray traces in view b between the depths of ``depth_range_m``.

    This removes matches on things fixed to the camera (a robot's gripper or body in view), which have
    no image motion whatever the camera does and would otherwise pull a bundle adjustment to a
    degenerate rotation-only solution, while the tolerance leaves room for the prior's error.
    """
    n = uv_a.shape[0]
    if n == 0:
        return np.zeros(0, bool)
    rays = np.concatenate([normalise(uv_a, K_a), np.ones((n, 1))], axis=1)
    ends = []
    for d in depth_range_m:
        p = (rays * d) @ T_b_a[:3, :3].T + T_b_a[:3, 3]
        z = np.maximum(p[:, 2], 1e-6)
        ends.append(p[:, :2] / z[:, None] * np.array([K_b[0, 0], K_b[1, 1]]) + K_b[:2, 2])
    # Both ends behind camera b: no depth in range is visible there.
    a, b = ends
    ab = b - a
    t = np.clip(np.sum((uv_b - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-9), 0.0, 1.0)
    dist = np.linalg.norm(uv_b - (a + t[:, None] * ab), axis=1)
    return dist < tol_px
