"""The compiled SGM kernel gives the torch version's numbers exactly (mapper.geometry.kernels)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from mapper.geometry import kernels, planesweep


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_compiled_sgm_equals_torch_sgm(monkeypatch: pytest.MonkeyPatch) -> None:
    g = torch.Generator().manual_seed(0)
    cost = torch.rand(12, 9, 13, generator=g)
    gray = torch.rand(9, 13, generator=g)
    compiled = planesweep.sgm_aggregate(cost, gray, 0.1, 0.6)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    reference = planesweep.sgm_aggregate(cost, gray, 0.1, 0.6)
    np.testing.assert_allclose(compiled.numpy(), reference.numpy(), rtol=0, atol=1e-5)
    # A single-plane cost aggregates to 4 x the cost (every path adds it and nothing else).
    flat = torch.rand(1, 4, 5, generator=g)
    np.testing.assert_allclose(planesweep.sgm_aggregate(flat, gray[:4, :5], 0.1, 0.6).numpy(), 4 * flat.numpy(),
                               atol=1e-6)


def test_census_cost_equals_the_plain_definition() -> None:
    g = torch.Generator().manual_seed(1)
    ref = torch.rand(11, 14, generator=g)
    warped = torch.rand(5, 11, 14, generator=g)
    radius, stride = 3, 2
    bits = planesweep.census_bits(ref, radius, stride)
    got = planesweep._census_cost(warped, bits, radius, stride).numpy()
    # Definition: for each plane, census bits of the warped image (edge-replicated) vs the reference's bits.
    want = np.stack([(planesweep.census_bits(p, radius, stride) != bits).float().mean(0).numpy() for p in warped])
    np.testing.assert_allclose(got, want, atol=1e-6)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("n_sources,best_k", [(1, 2), (2, 2), (3, 2), (3, 1)])
def test_compiled_sweep_cost_equals_opencv_torch_cost(monkeypatch: pytest.MonkeyPatch, n_sources: int,
                                                      best_k: int) -> None:
    """The fused census + best-k kernel gives the OpenCV / torch path's cost volume bit for bit, planes partly
    outside the sources and partly behind them included."""
    g = torch.Generator().manual_seed(2)
    h, w = 12, 16
    K = np.array([[14.0, 0, 7.5], [0, 14.0, 5.5], [0, 0, 1]])
    ref = torch.rand(h, w, generator=g)
    srcs = [torch.rand(h, w, generator=g) for _ in range(n_sources)]
    poses = []
    for i in range(n_sources):
        T = np.eye(4)
        T[:3, 3] = [0.1 * (i + 1), -0.05 * i, -0.4 * i]  # the third source sits 0.8 m ahead: near planes behind it
        poses.append(T)
    depths = 1.0 / torch.linspace(1 / 4.0, 1 / 0.3, 10)
    params = planesweep.SweepParams(n_planes=10, census_radius=2, census_stride=1, best_k_sources=best_k)
    compiled = planesweep.sweep_cost(ref, srcs, K, [K] * n_sources, poses, depths, params)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    reference = planesweep.sweep_cost(ref, srcs, K, [K] * n_sources, poses, depths, params)
    assert compiled.shape == (10, h, w)
    assert torch.equal(compiled, reference)
    _, inside = planesweep.warp_planes(srcs[-1], K, K, poses[-1], depths, h, w)
    assert not inside.all()  # some pixels fall outside the last source


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_nearest_both_ways_matches_topk_and_argmax() -> None:
    g = torch.Generator().manual_seed(3)
    for rows, cols in ((1, 2), (1, 5), (7, 2), (9, 13), (40, 3)):
        m = torch.randint(0, 4, (rows, cols), generator=g).float()  # many ties: the first row must win a column
        row_arg, top2, col_arg = kernels.nearest_both_ways(m.numpy())
        np.testing.assert_array_equal(col_arg, m.T.contiguous().argmax(dim=1).numpy())
        two = torch.topk(m, 2, dim=1)
        np.testing.assert_array_equal(top2, two.values.numpy())
        unique_max = two.values[:, 0] > two.values[:, 1]  # where topk's index is defined
        np.testing.assert_array_equal(row_arg[unique_max.numpy()], two.indices[unique_max, 0].numpy())
        np.testing.assert_array_equal(m.numpy()[np.arange(rows), row_arg], top2[:, 0])


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_compiled_upsample_equals_torch_upsample(monkeypatch: pytest.MonkeyPatch) -> None:
    """Same weights, same order of sums: confidence bit for bit, depth to float32 rounding of the exponentials."""
    g = torch.Generator().manual_seed(4)
    depth = torch.rand(9, 12, generator=g) * 3
    depth[2:4, 5:9] = 0.0  # no depth there: weightless neighbours
    conf = torch.rand(9, 12, generator=g)
    guide_lo, guide_hi = torch.rand(3, 9, 12, generator=g), torch.rand(3, 14, 19, generator=g)
    d_c, c_c = planesweep.joint_bilateral_upsample(depth, conf, guide_lo, guide_hi)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    d_t, c_t = planesweep.joint_bilateral_upsample(depth, conf, guide_lo, guide_hi)
    assert d_c.shape == (14, 19)
    np.testing.assert_allclose(d_c.numpy(), d_t.numpy(), rtol=1e-6, atol=0)
    assert torch.equal(c_c, c_t)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_compiled_plane_inside_equals_torch_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    # Sources turned and moved so that planes near the reference lie partly behind them: the per-pixel test.
    h, w = 12, 16
    K = np.array([[10.0, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])
    depths = 1.0 / torch.linspace(1 / 8.0, 1 / 0.2, 16)
    src = torch.rand(h, w, generator=torch.Generator().manual_seed(2))
    for yaw, tx, tz in ((1.2, 0.5, -0.8), (-0.9, -1.0, 0.3), (0.1, 0.05, 0.0)):
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        T[:3, 3] = [tx, 0.0, tz]
        warped, inside = planesweep.warp_planes(src, K, K, T, depths, h, w)
        with monkeypatch.context() as m:
            m.setattr(kernels, "AVAILABLE", False)
            warped_ref, inside_ref = planesweep.warp_planes(src, K, K, T, depths, h, w)
        assert torch.equal(warped, warped_ref)
        assert torch.equal(inside, inside_ref)


def test_padded_warp_gives_the_replicated_border_wherever_a_census_reads() -> None:
    """Planes in front of the source are warped from a replicated margin with a constant border (faster): every
    pixel within the census radius of a pixel that lands on the source gets the edge-replicated warp's value
    (to float32 rounding of the shifted homography), and ``inside`` is unchanged."""
    import cv2
    from scipy.ndimage import binary_dilation

    g = torch.Generator().manual_seed(5)
    h, w = 30, 40
    K = np.array([[35.0, 0, 19.5], [0, 35.0, 14.5], [0, 0, 1]])
    src = torch.rand(h, w, generator=g)
    depths = 1.0 / torch.linspace(1 / 6.0, 1 / 0.4, 12)
    radius = 3
    for yaw, tx, tz in ((0.3, 0.4, 0.1), (-0.2, -0.3, 0.2), (0.05, 0.1, -0.1)):
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]]
        T[:3, 3] = [tx, 0.05, tz]
        warped, inside = planesweep.warp_planes(src, K, K, T, depths, h, w, radius)
        assert 0 < inside.float().mean() < 1  # partly outside the source: the border matters
        read = binary_dilation(inside.numpy(), structure=np.ones((1, 2 * radius + 1, 2 * radius + 1), bool))
        for i, d in enumerate(depths.tolist()):
            H = K @ (T[:3, :3] + np.outer(T[:3, 3], [0.0, 0.0, 1.0]) / d) @ np.linalg.inv(K)
            want = cv2.warpPerspective(src.numpy(), H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                       borderMode=cv2.BORDER_REPLICATE)
            np.testing.assert_allclose(warped[i].numpy()[read[i]], want[read[i]], atol=1e-5)
            mask = cv2.warpPerspective(np.ones((h, w), np.uint8), H, (w, h),
                                       flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0)
            np.testing.assert_array_equal(inside[i].numpy(), mask.astype(bool))


def test_consistency_count_takes_points_in_a_neighbours_camera_plane_without_a_warning() -> None:
    """Reference points a hair in front of a neighbour's camera plane (projected: beyond int64) agree with nothing
    and raise no cast warning; an identical neighbour still agrees everywhere."""
    h, w = 6, 8
    K = np.array([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
    depth = np.ones((h, w), np.float32)
    near = np.eye(4)  # a neighbour 1e-16 m behind the reference's depth plane, with a long lens
    near[2, 3] = np.nextafter(1.0, 0.0)
    K_long = np.array([[1e6, 0, 4], [0, 1e6, 3], [0, 0, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        count = planesweep.consistency_count(depth, K, np.eye(4), [(depth, K_long, near), (depth, K, np.eye(4))])
    assert (count == 1).all()
