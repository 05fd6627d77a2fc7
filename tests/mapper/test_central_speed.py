"""The mapper's central per-keyframe path made faster without changing a single bit of its results: each fast
form is checked against the slow one it replaced (kept here as the reference) on random data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mapper.fusion import sum_by_index, voxel_downsample
from mapper.geometry.singleview import depth_to_world, pixel_rays
from mapper.pointmap import VoxelMap
from mapper.relations import EdgeCache, RelationConfig, compute_edges
from protocol.messages import OrientedBox


def _pose(seed: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = np.random.default_rng(seed).normal(size=3)
    return T


@pytest.mark.parametrize("seed", range(5))
def test_depth_to_world_is_the_strided_product_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = 60, 80
    depth = rng.uniform(0.2, 8.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.2] = 0.0
    K = np.array([[70.0, 0, 39.5], [0, 71.0, 29.5], [0, 0, 1]])
    T = _pose(seed)
    vs, us = np.mgrid[0:h, 0:w]
    rays = pixel_rays(K, us.reshape(-1).astype(float), vs.reshape(-1).astype(float))
    slow = ((rays * depth.reshape(-1, 1)) @ T[:3, :3].T + T[:3, 3]).reshape(h, w, 3).astype(np.float32)
    assert np.array_equal(depth_to_world(depth, K, T), slow)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sum_by_index_is_add_at_bit_for_bit(dtype: type) -> None:
    rng = np.random.default_rng(1)
    index = rng.integers(0, 50, 5000)
    values = (rng.normal(size=(5000, 3)) * 1e3).astype(dtype)
    slow = np.zeros((60, 3))
    np.add.at(slow, index, values)
    fast = sum_by_index(index, values, 60)
    assert fast.dtype == np.float64 and np.array_equal(fast, slow)
    assert sum_by_index(np.zeros(0, np.int64), np.zeros((0, 3)), 4).shape == (4, 3)


def test_voxel_map_and_downsample_keep_their_sums() -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(-2, 2, (4000, 3))
    cols = rng.integers(0, 255, (4000, 3)).astype(np.uint8)
    vm = VoxelMap(0.1, 10_000)
    vm.add(pts[:2000], cols[:2000])
    vm.add(pts[1000:], cols[1000:])
    # The reference: per voxel, the float64 sums of its points in order.
    keys = np.floor(pts / 0.1).astype(np.int64)
    first = {tuple(k) for k in keys[:2000]}
    assert len(vm) == len({tuple(k) for k in keys})
    assert int(vm.npoints.sum()) == 5000 and int(vm.counts.max()) == 2
    assert sum(1 for k in {tuple(k) for k in keys[1000:]} if k in first) == int((vm.counts == 2).sum())
    ds = voxel_downsample(pts.astype(np.float32), 0.5)
    assert ds.dtype == np.float32 and len(ds) == len({tuple(k) for k in np.floor(pts.astype(np.float32) / 0.5)})


def _boxes(rng: np.random.Generator, n: int) -> dict[str, OrientedBox]:
    out = {}
    for i in range(n):
        c = rng.uniform(-3, 3, 2)
        e = rng.uniform(0.1, 1.2, 3)
        z = rng.choice([0.0, 0.75, 1.5])
        out[f"n{i}"] = OrientedBox(center=(c[0], c[1], z + e[2] / 2), extent=tuple(e), yaw_rad=rng.uniform(-0.7, 0.7))
    return out


def test_edge_cache_gives_the_edges_of_a_fresh_computation() -> None:
    rng = np.random.default_rng(3)
    boxes = _boxes(rng, 40)
    cache = EdgeCache()
    cfg = RelationConfig()
    for step in range(6):
        assert compute_edges(boxes, cfg, cache) == compute_edges(boxes, cfg)
        # A keyframe changes a few boxes, adds one and removes one.
        for k in rng.choice(sorted(boxes), 3, replace=False):
            b = boxes[k]
            boxes[k] = b.model_copy(update={"center": (b.center[0] + 0.2, b.center[1], b.center[2])})
        boxes.pop(sorted(boxes)[step])
        boxes[f"new{step}"] = _boxes(rng, 1)["n0"]
    assert cache.hits > 0
    # Another config must not reuse what the old one decided.
    wide = RelationConfig(next_to_max_gap_m=2.0)
    assert compute_edges(boxes, wide, cache) == compute_edges(boxes, wide)


def test_merge_sorted_keys_is_np_unique_of_the_union() -> None:
    from mapper.pointmap import merge_sorted_keys

    rng = np.random.default_rng(4)
    keys = np.unique(rng.integers(-1000, 1000, 300)).astype(np.int64)
    for add in (np.unique(rng.integers(-1200, 1200, 200)), np.zeros(0, np.int64), keys[:5], np.array([5000])):
        add = add.astype(np.int64)
        merged, new, at = merge_sorted_keys(keys, add)
        ref, inv = np.unique(np.concatenate([keys, add]), return_inverse=True)
        assert np.array_equal(merged, ref) and np.array_equal(new, inv[len(keys) :])
        fresh = np.setdiff1d(add, keys)
        assert np.array_equal(np.insert(keys, at, fresh), ref)
    merged, new, at = merge_sorted_keys(np.zeros(0, np.int64), np.array([1, 3], np.int64))
    assert merged.tolist() == [1, 3] and new.tolist() == [0, 1] and at.tolist() == [0, 0]


def _reference_add(vm: VoxelMap, points: np.ndarray, colors: np.ndarray) -> None:
    """VoxelMap.add as it was (np.add.at, np.unique of the whole map, zeros then fancy adds)."""
    from mapper.fusion import voxel_keys

    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ok = np.all(np.isfinite(pts), axis=1)
    pts, cols = pts[ok], np.asarray(colors, dtype=np.float64).reshape(-1, 3)[ok]
    uk, inv = np.unique(voxel_keys(pts, vm.voxel_m), return_inverse=True)
    inv = inv.reshape(-1)
    s_new, c_new = np.zeros((len(uk), 3)), np.zeros((len(uk), 3))
    np.add.at(s_new, inv, pts)
    np.add.at(c_new, inv, cols)
    merged, minv = np.unique(np.concatenate([vm.keys, uk]), return_inverse=True)
    old, new = minv[: len(vm.keys)], minv[len(vm.keys) :]
    sums, csum = np.zeros((len(merged), 3)), np.zeros((len(merged), 3))
    npts, cnt = np.zeros(len(merged), dtype=np.int64), np.zeros(len(merged), dtype=np.int64)
    sums[old] += vm.sums
    csum[old] += vm.color_sums
    npts[old] += vm.npoints
    cnt[old] += vm.counts
    sums[new] += s_new
    csum[new] += c_new
    npts[new] += np.bincount(inv, minlength=len(uk))
    cnt[new] += 1
    vm.keys, vm.sums, vm.color_sums, vm.npoints, vm.counts = merged, sums, csum, npts, cnt
    if len(vm.keys) > vm.max_voxels:
        keep = np.sort(np.argsort(-vm.counts, kind="stable")[: vm.max_voxels])
        vm.keys, vm.sums = vm.keys[keep], vm.sums[keep]
        vm.color_sums, vm.npoints, vm.counts = vm.color_sums[keep], vm.npoints[keep], vm.counts[keep]


def test_voxel_map_add_is_the_old_add_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    fast, slow = VoxelMap(0.05, 3000), VoxelMap(0.05, 3000)
    for i in range(12):
        pts = rng.normal(size=(2000, 3)) * (0.3 + 0.1 * i)
        pts[5, 1] = np.nan
        cols = rng.integers(0, 255, (2000, 3)).astype(np.uint8)
        fast.add(pts, cols)
        _reference_add(slow, pts, cols)
        for name in ("keys", "sums", "color_sums", "npoints", "counts"):
            a, b = getattr(fast, name), getattr(slow, name)
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), (i, name)
    assert len(fast) == 3000  # the budget was reached and applied the same way
