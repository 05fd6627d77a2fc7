"""Depth must agree with other keyframes before it is fused (mapper.consistency)."""

from __future__ import annotations

import numpy as np

from mapper.consistency import DepthMap, coverage_count, downsample, verify_depth
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(160, 120, 70.0)
K = INTR.K()


def wall_depth(T_world_cam: np.ndarray, wall_y: float = 3.0) -> np.ndarray:
    """Exact z-depth of the plane y = wall_y seen by a camera (0 where it is not in front)."""
    vv, uu = np.mgrid[0:INTR.height, 0:INTR.width].astype(np.float64)
    rays_cam = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], -1)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    rays_w = rays_cam @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (wall_y - t[1]) / rays_w[..., 1]
    return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)


def cams() -> list[np.ndarray]:
    return [look_at([x, 0.0, 1.0], [x * 0.5, 3.0, 1.0]) for x in (0.0, 0.3, -0.3, 0.6)]


def test_a_planted_inconsistent_layer_is_removed_and_the_wall_kept() -> None:
    T_ref, *T_others = cams()
    others = [DepthMap(wall_depth(T), K, T) for T in T_others]
    depth = wall_depth(T_ref)
    conf = np.ones_like(depth)
    planted = np.zeros(depth.shape, bool)
    planted[40:80, 60:100] = True
    depth[planted] *= 0.8  # a layer 20 % in front of the wall that no other view sees
    out, st = verify_depth(depth, conf, K, T_ref, others, min_views=2)
    assert np.all(out[planted] == 0.0)
    kept = out[~planted] > 0
    assert kept.mean() > 0.9  # the true wall survives (a few pixels at the image border no other view covers)
    assert st.rejected >= planted.sum() and st.checked > 0.9 * depth.size


def test_unchecked_pixels_keep_their_confidence_and_no_others_is_a_no_op() -> None:
    T_ref = cams()[0]
    depth = wall_depth(T_ref)
    conf = np.full_like(depth, 0.8)
    out, st = verify_depth(depth, conf, K, T_ref, [])
    np.testing.assert_array_equal(out, conf)
    assert st.unchecked == int((depth > 0).sum()) and st.rejected == 0
    # Another view that looks elsewhere covers nothing: nothing can be checked, nothing is removed.
    away = look_at([0.0, 0.0, 1.0], [0.0, -3.0, 1.0])
    out2, st2 = verify_depth(depth, conf, K, T_ref, [DepthMap(wall_depth(away, -3.0), K, away)])
    np.testing.assert_array_equal(out2, conf)
    assert st2.checked == 0


def test_downsample_keeps_geometry_and_drops_unconfident() -> None:
    T = cams()[0]
    depth = wall_depth(T)
    conf = np.ones_like(depth)
    conf[:, :80] = 0.1
    small = downsample(depth, conf, K, T, 80, 0.5)
    assert small.depth_m.shape == (60, 80)
    assert np.all(small.depth_m[:, :39] == 0) and np.all(small.depth_m[:, 41:] > 0)
    # The small map agrees with the full one it came from.
    assert coverage_count(np.where(conf >= 0.5, depth, 0), K, T, [small])[:, 82:158].min() == 1
