"""The decision-time machinery of issue 14: exact equivalents of the dense visibility and gain computations."""

from __future__ import annotations

import math

import numpy as np

from planner import synthetic as S
from planner.config import VisibilityConfig
from planner.frontier import neighbour_stats
from planner.gain import factored_gain
from planner.geometry import (
    Panoramas,
    candidates_from_viewpoints,
    changed_points,
    detect_matrix,
    downsample_occluders,
    image_cone_cos,
    in_view_pairs,
    project_many,
)


def _dense_detect(T, pos_index, pano, K, w, h, X, far, cfg, sizes=None, min_px=0.0, margin=None):
    """The dense (pre-issue-14) detection: every camera against every target, occlusion per position."""
    margin = cfg.image_margin_frac if margin is None else margin
    ok, z = project_many(T, K, w, h, X, cfg.near_m, far, margin)
    if sizes is not None and min_px > 0:
        with np.errstate(divide="ignore", invalid="ignore"):
            ok &= K[0, 0] * sizes[None, :] / np.maximum(z, 1e-6) >= min_px
    if not ok.any():
        return ok
    cols = np.flatnonzero(ok.any(axis=0))
    uniq, inv = np.unique(pos_index, return_inverse=True)
    ok[:, cols] &= pano.unoccluded(X[cols], uniq)[inv.reshape(-1)]
    return ok


def _scene(seed: int = 0):
    w = S.apartment(seed)
    c = candidates_from_viewpoints(S.grid_viewpoints("r", (0.3, 0.3), (9.7, 8.7), spacing_m=1.2))
    occ = downsample_occluders(w["points"][::2], 0.1, 60000)
    return w, c, occ


def test_detect_matrix_equals_the_dense_test() -> None:
    _, c, occ = _scene()
    cfg = VisibilityConfig()
    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(-1, 11, 3000), rng.uniform(-1, 10, 3000), rng.uniform(0, 2.6, 3000)])
    sizes = rng.uniform(0.05, 1.0, 3000)
    for sz, mp, margin in ((None, 0.0, None), (sizes, 22.0, None), (sizes, 22.0, 0.1)):
        pano = Panoramas(c.positions, occ, cfg, far_m=6.0)
        want = _dense_detect(c.T_world_cam, c.pos_index, pano, c.K, c.width, c.height, X, 6.0, cfg, sz, mp, margin)
        got = detect_matrix(c.T_world_cam, c.pos_index, pano, c.K, c.width, c.height, X, 6.0, cfg, sz, mp, margin)
        assert want.any() and not want.all()
        np.testing.assert_array_equal(got, want)


def test_in_view_pairs_lists_the_frustum_test() -> None:
    _, c, _ = _scene()
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-1, 11, 2000), rng.uniform(-1, 10, 2000), rng.uniform(0, 2.6, 2000)])
    ok, _ = project_many(c.T_world_cam, c.K, c.width, c.height, X, 0.2, 6.0, 0.03)
    cams, tgts = in_view_pairs(c.T_world_cam, c.K, c.width, c.height, X, 0.2, 6.0, 0.03)
    got = np.zeros_like(ok)
    got[cams, tgts] = True
    np.testing.assert_array_equal(got, ok)
    assert len(set(zip(cams.tolist(), tgts.tolist(), strict=True))) == cams.shape[0]  # each pair once
    empty = in_view_pairs(c.T_world_cam, c.K, c.width, c.height, np.zeros((0, 3)), 0.2, 6.0)
    assert empty[0].shape == (0,) and empty[1].shape == (0,)


def test_image_cone_holds_the_image_corners() -> None:
    _, c, _ = _scene()
    K, w, h = c.K, c.width, c.height
    cos = image_cone_cos(K, w, h)
    # a 90 deg x 73.7 deg image: the corner ray's angle to the axis is atan(sqrt(1 + 0.75^2)) (half-pixel border)
    assert math.isclose(cos, 1 / math.sqrt(1 + ((w / 2) / K[0, 0]) ** 2 + ((h / 2) / K[1, 1]) ** 2), rel_tol=1e-12)
    corner = np.array([(-0.5 - K[0, 2]) / K[0, 0], (-0.5 - K[1, 2]) / K[1, 1], 1.0])
    assert math.isclose(corner[2] / np.linalg.norm(corner), cos, rel_tol=1e-12)
    assert image_cone_cos(K, w, h, 0.1) > cos  # a margin narrows the cone


def test_pairs_occlusion_equals_the_dense_occlusion() -> None:
    _, c, occ = _scene()
    cfg = VisibilityConfig()
    rng = np.random.default_rng(6)
    X = np.column_stack([rng.uniform(0, 10, 500), rng.uniform(0, 9, 500), rng.uniform(0, 2.5, 500)])
    pano = Panoramas(c.positions, occ, cfg, far_m=6.0)
    dense = pano.unoccluded(X)
    rows = rng.integers(0, c.positions.shape[0], 4000)
    tg = rng.integers(0, 500, 4000)
    np.testing.assert_array_equal(pano.unoccluded_pairs(X[tg], rows), dense[rows, tg])
    assert pano.unoccluded_pairs(np.zeros((0, 3)), np.zeros(0, np.int64)).shape == (0,)


def test_changed_points_bit_for_bit() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    b = np.array([[4.0, 5.0, 6.0], [1.0, 2.0, 3.0 + 1e-12], [7.0, 8.0, 9.0]])
    got = {tuple(p) for p in changed_points(a, b).tolist()}
    assert got == {(0.0, 0.0, 0.0), (1.0, 2.0, 3.0), (1.0, 2.0, 3.0 + 1e-12), (7.0, 8.0, 9.0)}
    assert changed_points(a, a[::-1]).shape == (0, 3)  # order does not matter
    assert changed_points(a, np.concatenate([a, a])).shape == (0, 3)  # nor duplicates
    assert changed_points(np.array([[0.0, 0.0, 0.0]]), np.array([[-0.0, 0.0, 0.0]])).shape == (2, 3)  # bits differ
    assert changed_points(a, np.zeros((0, 3))).shape == (3, 3)
    rng = np.random.default_rng(8)
    big = rng.normal(size=(20000, 3))
    moved = np.concatenate([big[500:], rng.normal(size=(300, 3))])
    assert changed_points(big, moved).shape == (800, 3)


def test_reused_panoramas_are_the_ones_a_build_gives() -> None:
    """Rows whose occluders in range did not change are taken over (and equal a fresh build); a change within
    range of a position forces its rebuild."""
    _, c, occ = _scene()
    cfg = VisibilityConfig()
    prev = Panoramas(c.positions, occ, cfg, far_m=3.0)
    for i in range(c.positions.shape[0]):
        prev.row(i)
    # the map changes in one corner only: a new patch near (9.5, 4.5), and the old points there removed
    corner = np.linalg.norm(occ[:, :2] - [9.5, 4.5], axis=1) < 0.5
    assert corner.any()
    new_occ = np.concatenate([occ[~corner], [[9.6, 4.6, z] for z in np.linspace(0.1, 2.5, 25)]])
    cur = Panoramas(c.positions, new_occ, cfg, far_m=3.0)
    n = cur.reuse(prev)
    reused = sorted(cur._rows)
    assert 0 < n == len(reused) < c.positions.shape[0]
    changed = changed_points(occ, new_occ)
    assert changed.shape[0] == int(corner.sum()) + 25
    dist = np.linalg.norm(c.positions[:, None, :] - changed[None, :, :], axis=2).min(axis=1)
    assert np.all(dist[reused] > 3.0 + 0.5)  # no changed occluder within the build's range of a reused row
    assert np.all(np.isin(np.flatnonzero(dist > 3.0 + 0.5 + 1e-3), reused))  # and every such row is reused
    fresh = Panoramas(c.positions, new_occ, cfg, far_m=3.0)
    for i in range(c.positions.shape[0]):
        np.testing.assert_array_equal(cur.row(i), fresh.row(i))
    assert Panoramas(c.positions, new_occ, cfg, far_m=4.0).reuse(prev) == 0  # another range: nothing reused
    assert Panoramas(c.positions, new_occ, cfg, far_m=3.0).reuse(None) == 0


def test_factored_gain_skips_constant_rows_exactly() -> None:
    """Counts that are the same in every sample carry no information: the gain is the one computed on all rows."""
    rng = np.random.default_rng(7)
    V = rng.random((60, 400)) < 0.05
    lab, smp = rng.integers(0, 12, 400), rng.integers(0, 32, 400)
    g = factored_gain(V, lab, smp, 12, 8, 4)
    assert g.shape == (60,) and np.all(g >= 0) and g.max() > 0
    # the gain of each row alone is that row's gain (rows are independent), empty rows give exactly 0
    for i in (0, 7, 33):
        assert factored_gain(V[i : i + 1], lab, smp, 12, 8, 4)[0] == g[i]
    assert factored_gain(np.zeros((3, 400), bool), lab, smp, 12, 8, 4).tolist() == [0.0, 0.0, 0.0]


def test_neighbour_stats_on_a_known_cluster() -> None:
    """A 3x3x3 block of voxels: the centre has 26 occupied neighbours, a corner 7, an edge-middle 11, a face
    centre 17; a density is the point's count plus its neighbour voxels' summed counts (duplicates add up)."""
    g = np.array([(i, j, k) for i in range(3) for j in range(3) for k in range(3)], float) * 0.1 + 0.05
    pts = np.concatenate([g, g[13:14]])  # the centre voxel twice
    counts = np.ones(pts.shape[0])
    n_occ, dens = neighbour_stats(pts, counts, 0.1)
    assert n_occ[13] == 26 and n_occ[0] == 7 and n_occ[1] == 11 and n_occ[4] == 17
    assert dens[13] == 1.0 + 26 * 1.0  # its own count, plus the 26 neighbour voxels (its own voxel twin is not one)
    assert dens[0] == 1.0 + 6 * 1.0 + 2.0  # 7 neighbours, one of them the doubled centre
    assert n_occ[27] == 26 and dens[27] == dens[13]
    far = neighbour_stats(np.array([[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]]), None, 0.1)
    assert far[0].tolist() == [0, 0] and far[1].tolist() == [1.0, 1.0]


def test_split_even_gives_contiguous_non_empty_ranges_of_about_equal_weight() -> None:
    from planner.geometry import split_even

    assert split_even(np.ones(10), 2) == [(0, 5), (5, 10)]
    assert split_even(np.array([9.0, 1, 1, 1, 1, 1, 1, 1, 1, 1]), 2) == [(0, 1), (1, 10)]
    assert split_even(np.ones(3), 8) == [(0, 1), (1, 2), (2, 3)]  # never more parts than items
    assert split_even(np.zeros(4), 2) == [(0, 3), (3, 4)]  # no weight: still covers everything
    assert split_even(np.ones(1), 2) == [(0, 1)]
    assert split_even(np.ones(0), 2) == []


def test_worker_threads_change_nothing_but_the_time() -> None:
    """Decisions are split across ``visibility.threads`` worker threads: the same panoramas, detections and
    frontier statistics for 1, 2 and 3 threads, bit for bit (the look-ups are split once past 4,096 pairs
    per thread, so the targets here are enough to split every stage)."""
    w, c, occ = _scene(1)
    rng = np.random.default_rng(7)
    X = np.column_stack([rng.uniform(-1, 11, 20000), rng.uniform(-1, 10, 20000), rng.uniform(0, 2.6, 20000)])
    sizes = rng.uniform(0.05, 1.0, X.shape[0])
    pts = w["points"]
    counts = rng.uniform(0.5, 5.0, pts.shape[0])  # not integers: the sums must be added in the same order
    got = []
    for threads in (1, 2, 3):
        cfg = VisibilityConfig(threads=threads, panorama_batch_pairs=200_000)
        pano = Panoramas(c.positions, occ, cfg, far_m=6.0)
        det = detect_matrix(c.T_world_cam, c.pos_index, pano, c.K, c.width, c.height, X, 6.0, cfg, sizes, 22.0)
        rows = np.stack([pano.row(i) for i in range(c.positions.shape[0])])
        got.append((det, rows, *neighbour_stats(pts, counts, 0.05, threads)))
    assert got[0][0].any() and got[0][1].size
    for other in got[1:]:
        for a, b in zip(got[0], other, strict=True):
            np.testing.assert_array_equal(a, b)
