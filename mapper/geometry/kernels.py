"""Compiled inner loop of the plane sweep (numba): SGM aggregation.

SGM is a sequential scan over a (D, H, W) volume that torch can only express as hundreds of small
per-row operations; compiled, each is one pass over memory. ``planesweep`` uses these when numba is
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


def _jit(fn: Any) -> Any:
    return numba.njit(cache=True, nogil=True)(fn) if AVAILABLE else fn


@_jit
def _step(prev: Any, c: Any, p1: float, p2: float, cur: Any) -> None:  # pragma: no cover - compiled
    n = prev.shape[0]
    pmin = prev[0]
    for d in range(1, n):
        if prev[d] < pmin:
            pmin = prev[d]
    jump = pmin + p2
    for d in range(n):
        best = prev[d]
        if d > 0 and prev[d - 1] + p1 < best:
            best = prev[d - 1] + p1
        if d < n - 1 and prev[d + 1] + p1 < best:
            best = prev[d + 1] + p1
        if jump < best:
            best = jump
        cur[d] = c[d] + best - pmin


@_jit
def _sgm4(cost: Any, p1: float, p2x: Any, p2y: Any) -> Any:  # pragma: no cover - compiled
    # cost: (H, W, D) contiguous; p2x[y, x]: penalty for entering x from x-1 (and x+1 from x when reversed).
    h, w, n = cost.shape
    total = np.zeros_like(cost)
    prev = np.empty(n, np.float32)
    cur = np.empty(n, np.float32)
    for y in range(h):
        prev[:] = cost[y, 0]
        total[y, 0] += prev
        for x in range(1, w):
            _step(prev, cost[y, x], p1, p2x[y, x], cur)
            total[y, x] += cur
            prev[:] = cur
        prev[:] = cost[y, w - 1]
        total[y, w - 1] += prev
        for x in range(w - 2, -1, -1):
            _step(prev, cost[y, x], p1, p2x[y, x + 1], cur)
            total[y, x] += cur
            prev[:] = cur
    # Vertical paths row by row over all columns at once: memory is read in order.
    prev_rows = np.empty((w, n), np.float32)
    cur_row = np.empty(n, np.float32)
    for y0, y1, yedge in ((0, h, 0), (h - 1, -1, 1)):
        step = 1 if yedge == 0 else -1
        prev_rows[:] = cost[y0]
        total[y0] += prev_rows
        for y in range(y0 + step, y1, step):
            for x in range(w):
                _step(prev_rows[x], cost[y, x], p1, p2y[y + yedge, x], cur_row)
                total[y, x] += cur_row
                prev_rows[x] = cur_row
    return total


def sgm4(cost_dhw: F32, p1: float, p2x: F32, p2y: F32) -> F32:
    """Sum of the 4 scan-line SGM aggregations of a (D, H, W) cost (same recursion as ``planesweep``'s torch
    version). p2x / p2y (H, W): the large-jump penalty for entering a pixel along x / y."""
    c = np.ascontiguousarray(np.transpose(cost_dhw, (1, 2, 0)), dtype=np.float32)
    out = _sgm4(c, np.float32(p1), np.ascontiguousarray(p2x, np.float32), np.ascontiguousarray(p2y, np.float32))
    return np.ascontiguousarray(np.transpose(out, (2, 0, 1)))

