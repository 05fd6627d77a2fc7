"""Dense depth by plane-sweep stereo on the CPU with torch (pure tensor functions, no I/O).

Per reference view: fronto-parallel planes uniform in inverse depth over a range fitted to the scene,
each source image warped onto every plane, census-transform Hamming cost per source, the best half of
the sources averaged (occlusion-robust), SGM-style aggregation along 4 scan-line paths, winner-take-all
with a parabola fit between planes. Confidence comes later from multi-view geometric consistency
(``consistency_count``), which measured best.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray

from mapper.geometry import kernels

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SweepParams:
    """Plane-sweep settings (see ``MvsConfig`` for their meaning)."""

    n_planes: int = 64
    census_radius: int = 3
    census_stride: int = 1
    p1: float = 0.04
    p2: float = 0.25
    best_k_sources: int = 2  # 1 or 2


def census_offsets(radius: int, stride: int = 1) -> list[tuple[int, int]]:
    """Neighbour offsets of a census window: every ``stride``-th pixel of the (2r+1)^2 square, no centre."""
    steps = range(-radius, radius + 1, stride)
    return [(dy, dx) for dy in steps for dx in steps if (dy, dx) != (0, 0)]


def census_bits(gray: torch.Tensor, radius: int, stride: int = 1) -> torch.Tensor:
    """Census transform of (H, W): one bool per neighbour, (n, H, W), edge-replicated."""
    padded = F.pad(gray[None, None], (radius,) * 4, mode="replicate")[0, 0]
    h, w = gray.shape[-2:]
    bits = [
        padded[radius + dy : radius + dy + h, radius + dx : radius + dx + w] > gray
        for dy, dx in census_offsets(radius, stride)
    ]
    return torch.stack(bits, dim=0)


def _census_cost(warped: torch.Tensor, ref_bits: torch.Tensor, radius: int, stride: int) -> torch.Tensor:
    """Fraction of census bits that differ between each warped plane (D, H, W) and the reference.

    OpenCV's saturating uint8 compare / xor / add per plane and offset: one pass of SIMD code each, ~2x
    faster than the same arithmetic on the whole (D, H, W) volume in torch (identical numbers)."""
    planes = np.ascontiguousarray(warped.numpy(), dtype=np.float32)
    n_planes, h, w = planes.shape
    offsets = census_offsets(radius, stride)
    ref = [np.where(b, 255, 0).astype(np.uint8) for b in ref_bits.numpy()]
    out = np.empty((n_planes, h, w), np.float32)
    acc = np.empty((h, w), np.uint8)
    bit = np.empty((h, w), np.uint8)
    for d in range(n_planes):
        pad = cv2.copyMakeBorder(planes[d], radius, radius, radius, radius, cv2.BORDER_REPLICATE)
        centre = pad[radius : radius + h, radius : radius + w]
        acc[:] = 0
        for (dy, dx), ref_k in zip(offsets, ref, strict=True):
            cv2.compare(pad[radius + dy : radius + dy + h, radius + dx : radius + dx + w], centre, cv2.CMP_GT, dst=bit)
            cv2.bitwise_xor(bit, ref_k, dst=bit)
            cv2.threshold(bit, 0, 1, cv2.THRESH_BINARY, dst=bit)
            cv2.add(acc, bit, dst=acc)
        out[d] = acc
    out *= 1.0 / len(offsets)
    return torch.from_numpy(out)


OUTSIDE_COST = 0.6
"""Census cost where a plane's pixel falls outside the source image: no evidence, a pessimistic cost lets the other
sources decide."""


def rotated_rays(K_ref: F64, T_src_ref: F64, h: int, w: int) -> torch.Tensor:
    """Reference pixel rays (z = 1) rotated into the source camera's axes: (H, W, 3) float32."""
    u = torch.arange(w, dtype=torch.float32)
    v = torch.arange(h, dtype=torch.float32)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    rays = torch.stack([(uu - K_ref[0, 2]) / K_ref[0, 0], (vv - K_ref[1, 2]) / K_ref[1, 1], torch.ones_like(uu)], -1)
    R = torch.as_tensor(T_src_ref[:3, :3], dtype=torch.float32)
    return rays @ R.T


def warp_grid(K_ref: F64, K_src: F64, T_src_ref: F64, depths: torch.Tensor, h: int, w: int,
              rays_src: torch.Tensor | None = None) -> torch.Tensor:
    """Source-image pixel coordinates (D, H, W, 2) of every reference pixel on every depth plane. ``rays_src``:
    :func:`rotated_rays` of the same arguments when the caller already has them (they do not depend on depth)."""
    Rr = rotated_rays(K_ref, T_src_ref, h, w) if rays_src is None else rays_src  # (H, W, 3)
    t = torch.as_tensor(T_src_ref[:3, 3], dtype=torch.float32)
    p = depths.view(-1, 1, 1, 1) * Rr.unsqueeze(0) + t  # (D, H, W, 3)
    z = p[..., 2].clamp(min=1e-4)
    us = p[..., 0] / z * float(K_src[0, 0]) + float(K_src[0, 2])
    vs = p[..., 1] / z * float(K_src[1, 1]) + float(K_src[1, 2])
    behind = p[..., 2] <= 1e-4
    us = torch.where(behind, torch.full_like(us, -1e4), us)
    return torch.stack([us, vs], dim=-1)


MAX_PAD_PX = 64
"""Planes that would need a wider replicated margin (seen at a grazing angle) are warped with OpenCV's replicating
border instead."""


def _homography_reach(Hs: F64, h: int, w: int, reach_px: int) -> NDArray[np.int64]:
    """Per homography of ``Hs`` (D, 3, 3; reference -> source pixels), the source pixels beyond the source image that
    reference pixels up to ``reach_px`` from a pixel landing on it can map to: the Jacobian's largest row norm at the
    reference image's corners (a plane in front of both cameras stretches most at a corner, where its depth in the
    source is smallest), with a margin."""
    corners = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [0.0, h - 1.0, 1.0], [w - 1.0, h - 1.0, 1.0]])
    q = np.einsum("dij,cj->dci", Hs, corners)  # (D, 4, 3): homogeneous source points of the corners
    uv = q[..., :2] / q[..., 2:3]
    # d(uv)/d(xy) at each corner: (H[:2, :2] - uv H[2, :2]) / q_z, (D, 4, 2, 2)
    J = (Hs[:, None, :2, :2] - uv[..., :, None] * Hs[:, None, 2:3, :2]) / q[..., 2, None, None]
    stretch = np.abs(J).sum(axis=3).max(axis=(1, 2))  # a step of one pixel in x and y at once: the L1 row norm
    return np.ceil(1.25 * reach_px * np.maximum(stretch, 1.0)).astype(np.int64) + 2


def warp_planes(
    src: torch.Tensor, K_ref: F64, K_src: F64, T_src_ref: F64, depths: torch.Tensor, h: int, w: int,
    reach_px: int = 5,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The source image warped onto every fronto-parallel reference plane, and where it is seen.

    A plane z = d in the reference frame maps reference pixels to source pixels by the homography
    ``K_src (R + t n^T / d) K_ref^-1`` (n = (0, 0, 1)), so each plane is one ``cv2.warpPerspective`` call,
    much cheaper than projecting every pixel of every plane. Returns warped (D, H, W) float32 (bilinear,
    edge-replicated) and inside (D, H, W) bool (the source pixel exists and lies in front of the source).

    Edge replication is what the census of a pixel near the source's border compares against, but OpenCV's
    replicating border is ~3x slower than its constant one wherever pixels fall outside (most planes). So for a
    plane wholly in front of the source, the source is padded by replication far enough that every pixel within
    ``reach_px`` reference pixels (the census radius) of one that lands on the source still samples the padding
    (:func:`_homography_reach`, at most ``MAX_PAD_PX``), and warped with a constant border: the same numbers there
    (to float32 rounding of the shifted homography); only pixels further out, which no census of a seen pixel reads,
    differ.
    """
    src_np = np.ascontiguousarray(src.numpy(), dtype=np.float32)
    hs, ws = src_np.shape
    ones = np.ones(src_np.shape, np.uint8)  # nearest-neighbour warps copy, so the type does not change the mask
    rays_src: torch.Tensor | None = None  # for planes partly behind the source, computed once
    R, t = T_src_ref[:3, :3], T_src_ref[:3, 3]
    K_ref_inv = np.linalg.inv(K_ref)
    t_n = np.outer(t, np.array([0.0, 0.0, 1.0]))
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], np.float64).T
    rays = K_ref_inv @ corners  # z = 1
    d = depths.numpy().astype(np.float64)
    # z of each plane's corners in the source: R (rays d) + t, every plane at once.
    z_corners = d[:, None] * (R[2] @ rays)[None, :] + t[2]
    in_front = np.all(z_corners > 1e-4, axis=1)  # z is affine in the pixel on a plane: corners in front => all
    warped = np.empty((len(depths), h, w), np.float32)
    inside = np.empty((len(depths), h, w), bool)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    nearest = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    # K_src (R + t n^T / d) K_ref^-1 for every plane: A + B / d.
    homographies = (K_src @ R @ K_ref_inv)[None] + (K_src @ t_n @ K_ref_inv)[None] / d[:, None, None]
    reach = _homography_reach(homographies, h, w, reach_px) if len(d) else np.zeros(0, np.int64)
    padded_ok = in_front & (reach <= MAX_PAD_PX)
    pad = int(reach[padded_ok].max()) if padded_ok.any() else 0
    padded = cv2.copyMakeBorder(src_np, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    shift = np.array([[1.0, 0.0, pad], [0.0, 1.0, pad], [0.0, 0.0, 1.0]])
    for i, H in enumerate(homographies):
        if padded_ok[i]:
            cv2.warpPerspective(padded, shift @ H, (w, h), dst=warped[i], flags=flags, borderMode=cv2.BORDER_CONSTANT,
                                borderValue=0)
        else:
            cv2.warpPerspective(src_np, H, (w, h), dst=warped[i], flags=flags, borderMode=cv2.BORDER_REPLICATE)
        if in_front[i]:
            cv2.warpPerspective(ones, H, (w, h), dst=inside[i].view(np.uint8), flags=nearest,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            continue
        # Part of the plane is behind the source camera: test every pixel.
        if rays_src is None:
            rays_src = rotated_rays(K_ref, T_src_ref, h, w)
        if kernels.AVAILABLE:
            kernels.plane_inside(rays_src.numpy(), depths[i].item(), np.asarray(t, np.float32), K_src, (hs, ws),
                                 inside[i])
        else:
            g = warp_grid(K_ref, K_src, T_src_ref, depths[i: i + 1], h, w, rays_src)[0].numpy()
            inside[i] = (g[..., 0] >= 0) & (g[..., 0] <= ws - 1) & (g[..., 1] >= 0) & (g[..., 1] <= hs - 1)
    return torch.from_numpy(warped), torch.from_numpy(inside)


def sweep_cost(
    ref_gray: torch.Tensor,
    src_grays: list[torch.Tensor],
    K_ref: F64,
    K_srcs: list[F64],
    T_src_ref: list[F64],
    depths: torch.Tensor,
    params: SweepParams,
) -> torch.Tensor:
    """Matching cost volume (D, H, W) in [0, 1]: mean census cost of the best sources per pixel and plane."""
    assert src_grays, "sweep_cost needs at least one source"
    h, w = ref_gray.shape
    ref_bits = census_bits(ref_gray, params.census_radius, params.census_stride)
    warps = (warp_planes(src, K_ref, K_s, T, depths, h, w, params.census_radius)
             for src, K_s, T in zip(src_grays, K_srcs, T_src_ref, strict=True))
    best_two = _best_two_compiled if kernels.AVAILABLE else _best_two_torch
    best1, best2 = best_two(warps, ref_bits, params.census_radius, params.census_stride)
    if min(params.best_k_sources, 2) == 1 or best2 is None:
        return best1
    return 0.5 * (best1 + best2)


def _best_two_torch(warps: Iterable[tuple[torch.Tensor, torch.Tensor]], ref_bits: torch.Tensor, radius: int,
                    stride: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The cheapest and second cheapest census cost (D, H, W) per pixel and plane over the sources' warped planes
    and masks (None: a single source), streamed: no (S, D, H, W) stack is ever built."""
    best1: torch.Tensor | None = None
    best2: torch.Tensor | None = None
    for warped, inside in warps:
        c = _census_cost(warped, ref_bits, radius, stride).masked_fill_(~inside, OUTSIDE_COST)
        if best1 is None:
            best1 = c
        elif best2 is None:
            best1, best2 = torch.minimum(best1, c), torch.maximum(best1, c)
        else:
            best2 = torch.minimum(best2, torch.maximum(best1, c))
            best1 = torch.minimum(best1, c)
    assert best1 is not None
    return best1, best2


def _best_two_compiled(warps: Iterable[tuple[torch.Tensor, torch.Tensor]], ref_bits: torch.Tensor, radius: int,
                       stride: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`_best_two_torch` with the census cost and the running minima fused in one compiled pass per source
    (``kernels.census_best``): the same numbers."""
    offsets = census_offsets(radius, stride)
    bits = ref_bits.numpy().astype(np.uint8)  # what the kernel reads, converted once for every source
    best1 = best2 = np.empty(0, np.float32)
    n = 0
    for warped, inside in warps:
        if n == 0:
            best1, best2 = np.empty(warped.shape, np.float32), np.empty(warped.shape, np.float32)
        kernels.census_best(warped.numpy(), bits, offsets, radius, inside.numpy(), OUTSIDE_COST, best1, best2, n)
        n += 1
    return torch.from_numpy(best1), torch.from_numpy(best2) if n > 1 else None


def _aggregate_path(cost: torch.Tensor, dim: int, reverse: bool, p1: torch.Tensor, p2: torch.Tensor) -> torch.Tensor:
    """SGM recursion along one axis of (D, H, W); p1/p2 broadcast over the slice."""
    n = cost.shape[dim]
    out = torch.empty_like(cost)
    order = range(n - 1, -1, -1) if reverse else range(n)
    prev = None
    big = torch.tensor(1e4, dtype=cost.dtype)
    for i in order:
        c = cost.select(dim, i)
        if prev is None:
            cur = c.clone()
        else:
            pmin = prev.min(dim=0, keepdim=True).values
            up = torch.cat([prev[1:], big.expand_as(prev[:1])], 0)
            down = torch.cat([big.expand_as(prev[:1]), prev[:-1]], 0)
            pp2 = p2.select(dim - 1, i).unsqueeze(0) if p2.dim() > 0 else p2
            best = torch.minimum(torch.minimum(prev, torch.minimum(up, down) + p1), pmin + pp2)
            cur = c + best - pmin
        out.select(dim, i).copy_(cur)
        prev = cur
    return out


def sgm_aggregate(cost: torch.Tensor, ref_gray: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """Sum of 4-path SGM aggregation of a (D, H, W) cost; P2 shrinks across image edges."""
    gy = torch.zeros_like(ref_gray)
    gx = torch.zeros_like(ref_gray)
    gx[:, 1:] = (ref_gray[:, 1:] - ref_gray[:, :-1]).abs()
    gy[1:, :] = (ref_gray[1:, :] - ref_gray[:-1, :]).abs()
    # Intensities are in [0, 1]; an edge of ~0.1 halves P2 so depth may jump there.
    p2x = p2 / (1.0 + gx / 0.1)
    p2y = p2 / (1.0 + gy / 0.1)
    if kernels.AVAILABLE and cost.dtype == torch.float32:
        return torch.from_numpy(kernels.sgm4(cost.numpy(), p1, p2x.numpy(), p2y.numpy()))
    return _sgm_aggregate_torch(cost, p1, p2x, p2y)


def _sgm_aggregate_torch(cost: torch.Tensor, p1: float, p2x: torch.Tensor, p2y: torch.Tensor) -> torch.Tensor:
    p1_t = torch.tensor(p1, dtype=cost.dtype)
    total = _aggregate_path(cost, 2, False, p1_t, p2x)
    total += _aggregate_path(cost, 2, True, p1_t, torch.cat([p2x[:, 1:], p2x[:, -1:]], 1))
    total += _aggregate_path(cost, 1, False, p1_t, p2y)
    total += _aggregate_path(cost, 1, True, p1_t, torch.cat([p2y[1:], p2y[-1:]], 0))
    return total


def winner_depth(agg: torch.Tensor, inv_depths: torch.Tensor) -> torch.Tensor:
    """Winner-take-all plane with a parabola fit between planes: depth (H, W), 0 where the winner is a range end."""
    d_n = agg.shape[0]
    # Each pixel's planes side by side ((H, W, D), as SGM leaves them: no copy then) make the search one pass.
    hwd = np.ascontiguousarray(agg.permute(1, 2, 0).numpy())
    idx_np = hwd.argmin(axis=2)  # the first of equal minima, as torch's argmin
    i0_np = np.clip(idx_np, 1, d_n - 2)
    c0, c1, c2 = (torch.from_numpy(np.take_along_axis(hwd, (i0_np + k)[..., None], axis=2)[..., 0]) for k in (-1, 0, 1))
    idx, i0 = torch.from_numpy(idx_np), torch.from_numpy(i0_np).unsqueeze(0)
    denom = c0 - 2 * c1 + c2
    offset = torch.where(denom > 1e-6, 0.5 * (c0 - c2) / denom.clamp(min=1e-6), torch.zeros_like(c1))
    offset = offset.clamp(-0.5, 0.5)
    edge = (idx == 0) | (idx == d_n - 1)
    pos = torch.where(edge, idx.to(agg.dtype), i0[0].to(agg.dtype) + offset)
    step = inv_depths[1] - inv_depths[0]
    depth = 1.0 / (inv_depths[0] + pos * step).clamp(min=1e-6)
    return torch.where(edge, torch.zeros_like(depth), depth)


def plane_sweep_depth(
    ref_gray: torch.Tensor,
    src_grays: list[torch.Tensor],
    K_ref: F64,
    K_srcs: list[F64],
    T_src_ref: list[F64],
    depth_min_m: float,
    depth_max_m: float,
    params: SweepParams,
) -> torch.Tensor:
    """Depth (H, W) in metres (0 where the winner sits on the range boundary)."""
    inv = torch.linspace(1.0 / depth_max_m, 1.0 / depth_min_m, params.n_planes)
    depths = 1.0 / inv
    cost = sweep_cost(ref_gray, src_grays, K_ref, K_srcs, T_src_ref, depths, params)
    agg = sgm_aggregate(cost, ref_gray, params.p1, params.p2)
    return winner_depth(agg, inv)


def consistency_count(
    depth_ref: NDArray[np.float32],
    K_ref: F64,
    T_world_ref: F64,
    neighbours: list[tuple[NDArray[np.float32], F64, F64]],
    rel_tol: float = 0.02,
    reproj_px: float = 1.5,
    search_px: int = 0,
) -> NDArray[np.int32]:
    """How many neighbour depth maps agree with each reference pixel (forward-backward check).

    A reference pixel's 3D point is projected into the neighbour; the neighbour's depth there is lifted
    back and reprojected into the reference: it agrees when it lands within ``reproj_px`` pixels and its
    depth is within ``rel_tol``. With ``search_px`` > 0 any neighbour pixel within that many pixels of the
    projection may agree (tolerates sub-pixel pose error and depth edges). neighbours: (depth (h, w), K,
    T_world_cam) each.
    """
    h, w = depth_ref.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    d = depth_ref.astype(np.float64)
    X_ref = np.stack([(uu - K_ref[0, 2]) / K_ref[0, 0] * d, (vv - K_ref[1, 2]) / K_ref[1, 1] * d, d], -1)
    count = np.zeros((h, w), np.int32)
    for depth_n, K_n, T_world_n in neighbours:
        hn, wn = depth_n.shape
        T_n_ref = np.linalg.inv(T_world_n) @ T_world_ref
        T_ref_n = np.linalg.inv(T_n_ref)
        p = X_ref @ T_n_ref[:3, :3].T + T_n_ref[:3, 3]
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            # Clipped too: a point just in front of the camera projects beyond int64's range, and the cast below
            # would warn and wrap (such pixels fall outside the image either way).
            un = np.clip(np.nan_to_num(p[..., 0] / z * K_n[0, 0] + K_n[0, 2], nan=-1e6, posinf=-1e6, neginf=-1e6),
                         -1e6, 1e6)
            vn = np.clip(np.nan_to_num(p[..., 1] / z * K_n[1, 1] + K_n[1, 2], nan=-1e6, posinf=-1e6, neginf=-1e6),
                         -1e6, 1e6)
        base = (d > 0) & (z > 1e-3)
        agree_any = np.zeros((h, w), bool)
        for oy in range(-search_px, search_px + 1):
            for ox in range(-search_px, search_px + 1):
                ui = np.round(un).astype(np.int64) + ox
                vi = np.round(vn).astype(np.int64) + oy
                ok = base & (ui >= 0) & (ui < wn) & (vi >= 0) & (vi < hn)
                dn = np.zeros((h, w))
                dn[ok] = depth_n[vi[ok], ui[ok]]
                ok &= dn > 0
                # Lift the neighbour's depth at that pixel and bring it back into the reference view.
                Xn = np.stack([(ui - K_n[0, 2]) / K_n[0, 0] * dn, (vi - K_n[1, 2]) / K_n[1, 1] * dn, dn], -1)
                q = Xn @ T_ref_n[:3, :3].T + T_ref_n[:3, 3]
                with np.errstate(divide="ignore", invalid="ignore"):
                    ur = q[..., 0] / q[..., 2] * K_ref[0, 0] + K_ref[0, 2]
                    vr = q[..., 1] / q[..., 2] * K_ref[1, 1] + K_ref[1, 2]
                    agree = (np.hypot(ur - uu, vr - vv) < reproj_px) & (np.abs(q[..., 2] - d) < rel_tol * d)
                agree_any |= ok & agree
        count += agree_any.astype(np.int32)
    return count


def joint_bilateral_upsample(
    depth: torch.Tensor, conf: torch.Tensor, guide_lo: torch.Tensor, guide_hi: torch.Tensor, sigma_color: float = 0.08
) -> tuple[torch.Tensor, torch.Tensor]:
    """Upsample depth and confidence (h, w) to the guide's (H, W) (guides: (3, h, w) and (3, H, W) in [0, 1]).

    Depth: average of the 3x3 low-res neighbours weighted by colour similarity to the high-res pixel, by
    distance and by confidence, so depth edges follow image edges instead of blurring across them.
    Confidence: that of the most similar neighbour (averaging would erode every confident region's rim).
    """
    h, w = depth.shape
    H, W = guide_hi.shape[-2:]
    ys = (torch.arange(H, dtype=torch.float32) + 0.5) * h / H - 0.5
    xs = (torch.arange(W, dtype=torch.float32) + 0.5) * w / W - 0.5
    yi = ys.round().long().clamp(0, h - 1)
    xi = xs.round().long().clamp(0, w - 1)
    if kernels.AVAILABLE:
        out = kernels.bilateral_upsample(depth.numpy(), conf.numpy(), guide_lo.numpy(), guide_hi.numpy(), sigma_color,
                                         ys.numpy(), xs.numpy(), yi.numpy(), xi.numpy())
        return torch.from_numpy(out[0]), torch.from_numpy(out[1])
    num_d = torch.zeros(H, W)
    den = torch.zeros(H, W)
    best_w = torch.full((H, W), -1.0)
    conf_hi = torch.zeros(H, W)
    valid = (depth > 0).to(torch.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            yy = (yi + dy).clamp(0, h - 1)
            xx = (xi + dx).clamp(0, w - 1)
            g = guide_lo[:, yy][:, :, xx]
            dist2 = (ys.view(-1, 1) - yy.view(-1, 1).float()) ** 2 + (xs.view(1, -1) - xx.view(1, -1).float()) ** 2
            wc = torch.exp(-((g - guide_hi) ** 2).sum(0) / (2 * sigma_color**2)) * torch.exp(-dist2 / 2.0)
            dd = depth[yy][:, xx]
            cc = conf[yy][:, xx] * valid[yy][:, xx]
            wd = wc * valid[yy][:, xx] * (0.05 + cc)
            num_d += wd * dd
            den += wd
            better = wc > best_w
            best_w = torch.where(better, wc, best_w)
            conf_hi = torch.where(better, cc, conf_hi)
    depth_hi = torch.where(den > 1e-6, num_d / den.clamp(min=1e-6), torch.zeros_like(den))
    conf_hi = torch.where(depth_hi > 0, conf_hi, torch.zeros_like(conf_hi))
    return depth_hi, conf_hi
