"""The global voxel point map with per-voxel observation counts (pure: no I/O).

Every update adds a view's confident world points; each voxel keeps the mean point, the mean colour
and how many views observed it (what the planner's frontier detection reads). Memory is bounded by
``max_voxels``: beyond it the least observed voxels are dropped.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mapper.fusion import rows_all, sum_by_index, voxel_keys
from protocol.messages import PointMap


def merge_sorted_keys(keys: np.ndarray, add: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sorted union of two sorted unique key arrays (what ``np.unique(np.concatenate([keys, add]))`` gives, by
    binary search instead of sorting the whole map again at every view), where each of ``add`` lands in it, and
    where in ``keys`` the keys not yet there go (``np.insert`` positions)."""
    pos = np.searchsorted(keys, add)
    known = pos < len(keys)
    known[known] = keys[pos[known]] == add[known]
    fresh = add[~known]
    at = np.searchsorted(keys, fresh)
    merged = np.insert(keys, at, fresh)
    return merged, np.searchsorted(merged, add), at


class VoxelMap:
    """Voxel-hashed accumulation of world points."""

    def __init__(self, voxel_m: float = 0.05, max_voxels: int = 400_000) -> None:
        if voxel_m <= 0 or max_voxels < 1:
            raise ValueError("voxel_m must be > 0 and max_voxels >= 1")
        self.voxel_m = voxel_m
        self.max_voxels = max_voxels
        self.keys = np.zeros(0, dtype=np.int64)
        self.sums = np.zeros((0, 3), dtype=np.float64)
        self.color_sums = np.zeros((0, 3), dtype=np.float64)
        self.npoints = np.zeros(0, dtype=np.int64)
        self.counts = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, points: np.ndarray, colors: np.ndarray | None = None) -> None:
        """Add one view's points (N, 3) with optional uint8 colours (N, 3); a voxel's count grows by one
        per call that touches it."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ok = rows_all(np.isfinite(pts))
        every = bool(ok.all())  # the usual case: no copies to drop nothing
        pts = pts if every else pts[ok]
        if len(pts) == 0:
            return
        if colors is None:
            cols = np.zeros_like(pts)
        else:  # selected before the (exact) conversion: a third of the bytes to copy
            cols = np.asarray(colors).reshape(-1, 3)
            cols = (cols if every else cols[ok]).astype(np.float64)
        k_new = voxel_keys(pts, self.voxel_m)
        uk, inv = np.unique(k_new, return_inverse=True)
        inv = inv.reshape(-1)
        n_new = np.bincount(inv, minlength=len(uk))
        s_new = sum_by_index(inv, pts, len(uk))
        c_new = sum_by_index(inv, cols, len(uk))
        merged, new, at = merge_sorted_keys(self.keys, uk)
        # where the old rows go (``np.insert(a, at, 0)``'s layout, worked out once for the four arrays): ``at`` is
        # sorted, so the k-th new key lands at ``at[k] + k``
        old = np.ones(len(merged), dtype=bool)
        old[at + np.arange(len(at))] = False

        def grown(a: np.ndarray) -> np.ndarray:  # the old rows, a zero row at each new key's place
            out = np.zeros((len(merged), *a.shape[1:]), dtype=a.dtype)
            out[old] = a
            return out

        sums, csum = grown(self.sums), grown(self.color_sums)
        # ``+= 0.0``: what adding the old sums into zeros gave (-0.0 becomes 0.0, nothing else changes)
        sums += 0.0
        csum += 0.0
        npts, cnt = grown(self.npoints), grown(self.counts)
        sums[new] += s_new
        csum[new] += c_new
        npts[new] += n_new
        cnt[new] += 1
        if len(merged) > self.max_voxels:  # trimmed before it is stored: a reader never sees more than the budget
            keep = np.sort(np.argsort(-cnt, kind="stable")[: self.max_voxels])
            merged, sums, csum, npts, cnt = merged[keep], sums[keep], csum[keep], npts[keep], cnt[keep]
        self.keys, self.sums, self.color_sums, self.npoints, self.counts = merged, sums, csum, npts, cnt

    def points(self) -> np.ndarray:
        """(N, 3) float32 mean point per voxel."""
        return (self.sums / np.maximum(self.npoints, 1)[:, None]).astype(np.float32)

    def colors(self) -> np.ndarray:
        return np.clip(self.color_sums / np.maximum(self.npoints, 1)[:, None], 0, 255).astype(np.uint8)

    def message(self, version: int, stamp_ns: int, max_points: int | None = None) -> PointMap:
        """The :class:`PointMap` (at most ``max_points``, the most observed voxels first)."""
        pts, cnt, col = self.points(), self.counts.astype(np.uint32), self.colors()
        if max_points is not None and len(pts) > max_points:
            keep = np.sort(np.argsort(-self.counts, kind="stable")[:max_points])
            pts, cnt, col = pts[keep], cnt[keep], col[keep]
        return PointMap(version=version, stamp_ns=stamp_ns, voxel_m=self.voxel_m, points=pts, counts=cnt, colors=col)

    def state(self) -> dict[str, Any]:
        return {
            "voxel_m": self.voxel_m,
            "keys": self.keys.tobytes(),
            "sums": self.sums.tobytes(),
            "color_sums": self.color_sums.tobytes(),
            "npoints": self.npoints.tobytes(),
            "counts": self.counts.tobytes(),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        if float(state["voxel_m"]) != self.voxel_m:
            return  # a different voxel size: start the map afresh rather than mix grids
        self.keys = np.frombuffer(state["keys"], dtype=np.int64).copy()
        self.sums = np.frombuffer(state["sums"], dtype=np.float64).reshape(-1, 3).copy()
        self.color_sums = np.frombuffer(state["color_sums"], dtype=np.float64).reshape(-1, 3).copy()
        self.npoints = np.frombuffer(state["npoints"], dtype=np.int64).copy()
        self.counts = np.frombuffer(state["counts"], dtype=np.int64).copy()
