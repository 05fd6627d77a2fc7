"""Expected information gain of candidate views over sampled scene completions (pure numpy).

Samples are indexed ``s = k * J + j``: completion ``k`` of ``K`` with position jitter ``j`` of ``J``.
For a candidate ``x`` the predicted observation ``Y`` is the multiset of hypothesised labels the
view would detect. With equal sample weights,

    I(Y; G | x) = H(Y | x) - H(Y | x, G)
                = H(empirical Y over all K*J samples) - mean_k H(empirical Y over the J jitters of k)

in bits. ``joint`` hashes the whole multiset (exact definition; saturates at log2 K). ``factored``
sums the information of each label's count (a per-label decomposition that keeps ranking views by
how many uncertain objects they would resolve once ``joint`` saturates).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix


def row_entropy_bits(values: np.ndarray) -> np.ndarray:
    """Entropy in bits of the empirical distribution of each row of ``values`` (R,S), equal weights."""
    v = np.asarray(values)
    if v.ndim != 2:
        raise ValueError("values must be 2-D (rows, samples)")
    R, S = v.shape
    if S == 0 or R == 0:
        return np.zeros(R)
    s = np.sort(v, axis=1)
    new = np.ones((R, S), bool)
    new[:, 1:] = s[:, 1:] != s[:, :-1]
    gid = np.cumsum(new, axis=1) - 1  # group index within the row
    flat = (np.arange(R)[:, None] * S + gid).ravel()
    counts = np.bincount(flat, minlength=R * S).reshape(R, S).astype(np.float64)
    p = counts / S
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -np.where(p > 0, p * np.log2(p), 0.0)
    return h.sum(axis=1)


def mutual_information(values: np.ndarray, n_completions: int, n_jitter: int) -> np.ndarray:
    """I(Y;G|x) per row of ``values`` (R, K*J): total entropy minus mean within-completion entropy."""
    v = np.asarray(values)
    R = v.shape[0]
    if v.shape[1] != n_completions * n_jitter:
        raise ValueError(f"expected {n_completions * n_jitter} samples per row, got {v.shape[1]}")
    h_total = row_entropy_bits(v)
    h_cond = row_entropy_bits(v.reshape(R * n_completions, n_jitter)).reshape(R, n_completions).mean(axis=1)
    return np.maximum(h_total - h_cond, 0.0)


def _label_hashes(n_labels: int) -> np.ndarray:
    # Fixed pseudo-random weights: the sum over a multiset identifies it (collisions ~2^-30).
    return np.random.default_rng(12345).integers(1, 1 << 30, size=n_labels).astype(np.float64)


def joint_gain(
    visible: np.ndarray,
    label_idx: np.ndarray,
    sample_idx: np.ndarray,
    n_labels: int,
    n_completions: int,
    n_jitter: int,
) -> np.ndarray:
    """I(Y;G|x) (C,) with Y the whole visible label multiset. ``visible`` (C,H) for hypotheses h."""
    V = np.asarray(visible, dtype=np.float64)
    C, H = V.shape
    S = n_completions * n_jitter
    if H == 0:
        return np.zeros(C)
    M = np.zeros((H, S))
    M[np.arange(H), np.asarray(sample_idx)] = _label_hashes(max(n_labels, 1))[np.asarray(label_idx)]
    Y = V @ M  # (C,S) multiset hash of what each sample shows
    return mutual_information(Y, n_completions, n_jitter)


def factored_gain(
    visible: np.ndarray,
    label_idx: np.ndarray,
    sample_idx: np.ndarray,
    n_labels: int,
    n_completions: int,
    n_jitter: int,
) -> np.ndarray:
    """Sum over labels of I(count of label in view; G | x) (C,)."""
    vis = np.asarray(visible, dtype=bool)
    C, H = vis.shape
    S = n_completions * n_jitter
    L = max(n_labels, 1)
    if H == 0:
        return np.zeros(C)
    lab = np.asarray(label_idx)
    smp = np.asarray(sample_idx)
    used = np.unique(lab)
    remap = np.full(L, -1)
    remap[used] = np.arange(used.size)
    lab_c = remap[lab]
    Lu = used.size
    # counts[c, l, s] = number of visible hypotheses of label l in sample s: one sparse product (the
    # visibility matrix is mostly empty; the counts are small integers, exact in float32).
    onehot = csr_matrix((np.ones(H, np.float32), (np.arange(H), lab_c * S + smp)), shape=(H, Lu * S))
    counts = (csr_matrix(vis, dtype=np.float32) @ onehot).toarray().reshape(C * Lu, S)
    mi = np.zeros(C * Lu)
    varies = np.flatnonzero(counts.max(axis=1) != counts.min(axis=1))  # a constant row carries no information
    mi[varies] = mutual_information(counts[varies], n_completions, n_jitter)
    return mi.reshape(C, Lu).sum(axis=1)
