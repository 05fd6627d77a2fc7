"""Compiled inner loops of the plane sweep (numba): census cost and SGM aggregation.

SGM is a sequential scan over a (D, H, W) volume that torch can only express as hundreds of small
per-row operations; compiled, each is one pass over memory. The census cost compares every plane with
every census neighbour: as OpenCV calls that is four calls per plane and neighbour (thousands per source),
compiled it is one pass per plane. ``planesweep`` uses these when numba is
installed (it is in the ``server`` extra) and falls back to its torch version otherwise; a test checks
that both give the same numbers. Compiled code is cached on disk, so only the first run pays for it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

try:
    import numba

    AVAILABLE = True
except ImportError:  # optional: planesweep falls back to torch
    numba = None  # type: ignore[assignment]
    AVAILABLE = False

F32 = NDArray[np.float32]


def compiled(fn: Any) -> Any:
    """``fn`` compiled by numba (cached on disk, no GIL), or None without numba (the caller keeps a Python path)."""
    return numba.njit(cache=True, nogil=True)(fn) if AVAILABLE else None


def _jit(fn: Any) -> Any:
    return compiled(fn) if AVAILABLE else fn


@_jit
def _min(a: Any) -> Any:  # pragma: no cover - compiled
    m = a[0]
    for d in range(1, a.shape[0]):
        m = min(m, a[d])
    return m


@_jit
def _step(prev: Any, c: Any, p1: float, p2: float, cur: Any, total: Any) -> None:  # pragma: no cover - compiled
    # cur[d] = c[d] + min(prev[d], prev[d -+ 1] + p1, min(prev) + p2) - min(prev), added to total[d]. The ends apart,
    # the loop has no branch, so it runs on vector registers (min is exact: any order of the candidates gives the
    # same number).
    n = prev.shape[0]
    pmin = _min(prev)
    jump = pmin + p2
    if n == 1:
        cur[0] = c[0] + min(prev[0], jump) - pmin
        total[0] += cur[0]
        return
    cur[0] = c[0] + min(min(prev[0], prev[1] + p1), jump) - pmin
    for d in range(1, n - 1):
        cur[d] = c[d] + min(min(prev[d], min(prev[d - 1], prev[d + 1]) + p1), jump) - pmin
    cur[n - 1] = c[n - 1] + min(min(prev[n - 1], prev[n - 2] + p1), jump) - pmin
    for d in range(n):
        total[d] += cur[d]


@_jit
def _sgm4(cost: Any, p1: float, p2x: Any, p2y: Any) -> Any:  # pragma: no cover - compiled
    # cost: (H, W, D) contiguous; p2x[y, x]: penalty for entering x from x-1 (and x+1 from x when reversed).
    # The paths add into total in a fixed order (x forward, x backward, y forward, y backward) at every pixel.
    h, w, n = cost.shape
    total = np.zeros_like(cost)
    path = np.empty((w, n), np.float32)  # one row's path costs: the previous pixel's are read, none copied
    for y in range(h):
        path[0] = cost[y, 0]
        total[y, 0] += path[0]
        for x in range(1, w):
            _step(path[x - 1], cost[y, x], p1, p2x[y, x], path[x], total[y, x])
        path[w - 1] = cost[y, w - 1]
        total[y, w - 1] += path[w - 1]
        for x in range(w - 2, -1, -1):
            _step(path[x + 1], cost[y, x], p1, p2x[y, x + 1], path[x], total[y, x])
    # Vertical paths row by row over all columns at once: memory is read in order; two row buffers take turns.
    rows = np.empty((2, w, n), np.float32)
    for y0, y1, yedge in ((0, h, 0), (h - 1, -1, 1)):
        step = 1 if yedge == 0 else -1
        rows[0] = cost[y0]
        total[y0] += rows[0]
        k = 0
        for y in range(y0 + step, y1, step):
            for x in range(w):
                _step(rows[k, x], cost[y, x], p1, p2y[y + yedge, x], rows[1 - k, x], total[y, x])
            k = 1 - k
    return total


@_jit
def _census_best(planes: Any, ref_bits: Any, dys: Any, dxs: Any, radius: int, scale: Any, inside: Any,
                 outside_cost: Any, best1: Any, best2: Any, n_seen: int) -> None:  # pragma: no cover - compiled
    n_planes, h, w = planes.shape
    n = dys.shape[0]
    pad = np.empty((h + 2 * radius, w + 2 * radius), np.float32)
    acc = np.empty(w, np.uint8)
    cost = np.empty(w, np.float32)
    for d in range(n_planes):
        for y in range(h + 2 * radius):  # the plane, edge-replicated by ``radius`` on every side
            ys = min(max(y - radius, 0), h - 1)
            for x in range(w + 2 * radius):
                pad[y, x] = planes[d, ys, min(max(x - radius, 0), w - 1)]
        for y in range(h):
            acc[:] = 0
            centre = pad[y + radius, radius: radius + w]
            for k in range(n):
                row = pad[y + radius + dys[k], radius + dxs[k]: radius + dxs[k] + w]
                bits = ref_bits[k, y]
                for x in range(w):
                    acc[x] += np.uint8(row[x] > centre[x]) ^ bits[x]  # bits 0 / 1: ~10% faster than bools
            ins = inside[d, y]
            for x in range(w):
                cost[x] = np.float32(acc[x]) * scale if ins[x] else outside_cost
            b1 = best1[d, y]
            b2 = best2[d, y]
            if n_seen == 0:
                b1[:] = cost
            elif n_seen == 1:
                for x in range(w):
                    b2[x] = max(b1[x], cost[x])
                    b1[x] = min(b1[x], cost[x])
            else:
                for x in range(w):
                    b2[x] = min(b2[x], max(b1[x], cost[x]))
                    b1[x] = min(b1[x], cost[x])


def census_best(planes: F32, ref_bits: NDArray[np.bool_ | np.uint8], offsets: list[tuple[int, int]], radius: int,
                inside: NDArray[np.bool_], outside_cost: float, best1: F32, best2: F32, n_seen: int) -> None:
    """Merge one source's census cost into the running two cheapest costs of the sources before it, in place.

    The cost of a plane's pixel is the fraction of census bits (neighbours at ``offsets``, within ``radius``) that
    differ between that plane of ``planes`` (D, H, W), edge-replicated, and the reference's ``ref_bits`` (n, H, W;
    bool, or uint8 0 / 1 as the kernel reads them: a caller with several sources converts them once),
    and ``outside_cost`` where ``inside`` (D, H, W) is False. ``best1`` / ``best2`` (D, H, W): the cheapest and second
    cheapest cost of the ``n_seen`` sources merged so far (neither is read when ``n_seen`` is 0, ``best2`` not when
    it is 1). Same numbers as ``planesweep``'s OpenCV and torch version."""
    dys = np.array([o[0] for o in offsets], np.int64)
    dxs = np.array([o[1] for o in offsets], np.int64)
    _census_best(np.ascontiguousarray(planes, np.float32), np.ascontiguousarray(ref_bits, np.uint8), dys, dxs,
                 radius, np.float32(1.0 / len(offsets)), np.ascontiguousarray(inside, np.bool_),
                 np.float32(outside_cost), best1, best2, n_seen)


@_jit
def _plane_inside(rays_src: Any, depth: Any, t: Any, fx: Any, cx: Any, fy: Any, cy: Any, w_max: Any, h_max: Any,
                  inside: Any) -> None:  # pragma: no cover - compiled
    # planesweep.warp_grid's float32 arithmetic, one operation at a time in its order (no fused multiply-add).
    h, w = inside.shape
    z_min = np.float32(1e-4)
    for y in range(h):
        for x in range(w):
            pz = depth * rays_src[y, x, 2] + t[2]
            if pz <= z_min:
                inside[y, x] = False
                continue
            us = (depth * rays_src[y, x, 0] + t[0]) / pz * fx + cx
            vs = (depth * rays_src[y, x, 1] + t[1]) / pz * fy + cy
            inside[y, x] = us >= 0 and us <= w_max and vs >= 0 and vs <= h_max


def plane_inside(rays_src: F32, depth: float, t: F32, K_src: NDArray[np.float64], src_hw: tuple[int, int],
                 inside: NDArray[np.bool_]) -> None:
    """Which reference pixels of the plane at ``depth`` land on the source image and in front of it, written to
    ``inside`` (H, W): ``planesweep.warp_grid`` and its bounds test in one pass, the same float32 numbers.
    ``rays_src`` (H, W, 3) float32: ``planesweep.rotated_rays``; ``t`` (3,) float32: the source-from-reference
    translation; ``src_hw``: the source image's rows and columns."""
    f32 = np.float32
    _plane_inside(np.ascontiguousarray(rays_src, np.float32), f32(depth), np.ascontiguousarray(t, np.float32),
                  f32(K_src[0, 0]), f32(K_src[0, 2]), f32(K_src[1, 1]), f32(K_src[1, 2]), f32(src_hw[1] - 1),
                  f32(src_hw[0] - 1), inside)


@_jit
def _nearest_both_ways(m: Any, row_arg: Any, row_top2: Any, col_arg: Any) -> None:  # pragma: no cover - compiled
    rows, cols = m.shape
    col_best = np.empty(cols, np.float32)
    col_best[:] = m[0]
    col_arg[:] = 0
    for i in range(rows):
        row = m[i]
        best = np.float32(-np.inf)
        second = np.float32(-np.inf)
        arg = 0
        for j in range(cols):
            v = row[j]
            if v > best:  # strictly greater: the first of equal maxima stays
                second = best
                best = v
                arg = j
            elif v > second:
                second = v
            if i > 0 and v > col_best[j]:
                col_best[j] = v
                col_arg[j] = i
        row_arg[i] = arg
        row_top2[i, 0] = best
        row_top2[i, 1] = second


def nearest_both_ways(m: F32) -> tuple[NDArray[np.int64], F32, NDArray[np.int64]]:
    """In one pass over ``m`` (R, C) float32, R >= 1, C >= 2: each row's first maximum's column (R,), its two largest
    values (R, 2), as ``topk(2)`` counts them (a repeated maximum is also the second), and each column's first
    maximum's row (C,). One pass down the rows, where a reduction across rows per column strides through memory
    (~5x slower for 2000 x 2000)."""
    m = np.ascontiguousarray(m, np.float32)
    row_arg = np.empty(m.shape[0], np.int64)
    row_top2 = np.empty((m.shape[0], 2), np.float32)
    col_arg = np.empty(m.shape[1], np.int64)
    _nearest_both_ways(m, row_arg, row_top2, col_arg)
    return row_arg, row_top2, col_arg


@_jit
def _bilateral_upsample(depth: Any, conf: Any, guide_lo: Any, guide_hi: Any, two_sigma2: Any, ys: Any, xs: Any,
                        yi: Any, xi: Any, depth_hi: Any, conf_hi: Any) -> None:  # pragma: no cover - compiled
    h, w = depth.shape
    H, W = depth_hi.shape
    for Y in range(H):
        for X in range(W):
            num = np.float32(0.0)
            den = np.float32(0.0)
            best_w = np.float32(-1.0)
            best_c = np.float32(0.0)
            for dy in range(-1, 2):
                yy = min(max(yi[Y] + dy, 0), h - 1)
                for dx in range(-1, 2):
                    xx = min(max(xi[X] + dx, 0), w - 1)
                    e = np.float32(0.0)
                    for ch in range(3):
                        diff = guide_lo[ch, yy, xx] - guide_hi[ch, Y, X]
                        e += diff * diff
                    dist2 = (ys[Y] - np.float32(yy)) ** 2 + (xs[X] - np.float32(xx)) ** 2
                    wc = np.float32(np.exp(-e / two_sigma2)) * np.float32(np.exp(-dist2 * np.float32(0.5)))
                    d = depth[yy, xx]
                    if d > 0:
                        cc = conf[yy, xx]
                        wd = wc * (np.float32(0.05) + cc)
                        num += wd * d
                        den += wd
                    else:
                        cc = np.float32(0.0)
                    if wc > best_w:
                        best_w = wc
                        best_c = cc
            dh = num / den if den > np.float32(1e-6) else np.float32(0.0)
            depth_hi[Y, X] = dh
            conf_hi[Y, X] = best_c if dh > 0 else np.float32(0.0)


def bilateral_upsample(depth: F32, conf: F32, guide_lo: F32, guide_hi: F32, sigma_color: float, ys: F32, xs: F32,
                       yi: NDArray[np.int64], xi: NDArray[np.int64]) -> tuple[F32, F32]:
    """``planesweep.joint_bilateral_upsample`` in one pass over the output pixels (its arithmetic, float32; the
    exponentials may differ from torch's in the last bit). ys / xs (H,) / (W,): each output row / column's
    position on the input grid; yi / xi: the nearest input row / column."""
    H, W = guide_hi.shape[1:]
    depth_hi = np.empty((H, W), np.float32)
    conf_hi = np.empty((H, W), np.float32)
    _bilateral_upsample(np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(conf, np.float32),
                        np.ascontiguousarray(guide_lo, np.float32), np.ascontiguousarray(guide_hi, np.float32),
                        np.float32(2 * sigma_color**2), np.ascontiguousarray(ys, np.float32),
                        np.ascontiguousarray(xs, np.float32), np.ascontiguousarray(yi, np.int64),
                        np.ascontiguousarray(xi, np.int64), depth_hi, conf_hi)
    return depth_hi, conf_hi


def sgm4(cost_dhw: F32, p1: float, p2x: F32, p2y: F32) -> F32:
    """Sum of the 4 scan-line SGM aggregations of a (D, H, W) cost (same recursion as ``planesweep``'s torch
    version). p2x / p2y (H, W): the large-jump penalty for entering a pixel along x / y. The result is a (D, H, W)
    view of (H, W, D) memory: the winner search then reads each pixel's planes in order, not D strided ones."""
    c = np.ascontiguousarray(np.transpose(cost_dhw, (1, 2, 0)), dtype=np.float32)
    out = _sgm4(c, np.float32(p1), np.ascontiguousarray(p2x, np.float32), np.ascontiguousarray(p2y, np.float32))
    return np.transpose(out, (2, 0, 1))

