"""Frontier points from measurement density (after Surface Edge Explorer), pure numpy.

A map voxel is *observed* (core) when its 26-neighbourhood is well populated and its summed
observation count is high; otherwise it is a *frontier*: the edge of an observed surface, or a
surface seen too sparsely (far away, grazing). Views that see frontier points extend the surfaces.
"""

from __future__ import annotations

import numpy as np

from planner.config import SeeConfig
from planner.geometry import item_blocks, parallel_map

_OFF = 1 << 20
_OFFSETS = np.array(
    [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)]
)


def _encode(ijk: np.ndarray) -> np.ndarray:
    a = ijk.astype(np.int64) + _OFF
    return (a[:, 0] << 42) | (a[:, 1] << 21) | a[:, 2]


def neighbour_stats(
    points: np.ndarray, counts: np.ndarray | None, voxel_m: float, threads: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Per point: occupied 26-neighbour voxels (N,) and summed counts of the voxel and its neighbours (N,).
    The points are split across ``threads`` worker threads (each point's sums are added in the same order
    whatever the count)."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    N = P.shape[0]
    c = np.ones(N) if counts is None else np.asarray(counts, dtype=np.float64).reshape(N)
    if N == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    ijk = np.floor(P / voxel_m).astype(np.int64)  # same voxel keys as the mapper (floor)
    keys = _encode(ijk)
    order = np.argsort(keys, kind="stable")
    skeys = keys[order]
    # Collapse duplicate voxels (a map may hold more than one point per voxel).
    uk, start = np.unique(skeys, return_index=True)
    ucount = np.add.reduceat(c[order], start)
    c_sorted = c[order]

    def block(ab: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        q = skeys[ab[0] : ab[1]]
        n_occ = np.zeros(q.shape[0], np.int64)
        dens = c_sorted[ab[0] : ab[1]].copy()
        for off in _OFFSETS:
            # A neighbour's key is the key plus a constant (the fields do not carry for voxel indices within
            # +-2**20): the queries stay sorted, which keeps the binary searches cache friendly.
            nk = q + (int(off[0]) << 42) + (int(off[1]) << 21) + int(off[2])
            pos = np.searchsorted(uk, nk)
            pos = np.minimum(pos, uk.shape[0] - 1)
            hit = uk[pos] == nk
            n_occ += hit
            dens += np.where(hit, ucount[pos], 0.0)
        return n_occ, dens

    done = parallel_map(block, item_blocks(N, threads, 8192), threads)
    out_occ, out_dens = np.empty(N, np.int64), np.empty(N)
    out_occ[order] = np.concatenate([o for o, _ in done])
    out_dens[order] = np.concatenate([d for _, d in done])
    return out_occ, out_dens


def classify_frontier(
    points: np.ndarray, counts: np.ndarray | None, voxel_m: float, cfg: SeeConfig, threads: int = 1
) -> np.ndarray:
    """(N,) bool: frontier (sparse or surface-edge) points of the map."""
    n_occ, dens = neighbour_stats(points, counts, voxel_m, threads)
    return (n_occ < cfg.min_neighbors) | (dens < cfg.min_density)
