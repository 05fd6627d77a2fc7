"""Detections of one object that a person in front cut in two, joined again (pure: no I/O).

A passer-by in front of a sofa, a television or a table can leave its mask in two pieces, left and right of them,
and a segmenter that reports regions (SAM's automatic masks) gives two detections. Fusion takes the detections of
one view as distinct objects (one node per view), so the second piece would become a second node, kept apart from
the first afterwards because one keyframe told them apart. Two pieces are joined when they carry the same label,
their descriptors are alike and both touch the same person's mask; the people themselves are left out, as fusion
leaves them out. (The simulator's ORACLE segmenter gives one mask per instance, split or not, so ``argus eval
changes`` does not exercise this.)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from mapper.perception.base import Detection


def _at(mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``mask`` at ``shape`` (h, w): a worker's masks may come at the depth's resolution."""
    if mask.shape == shape:
        return mask
    from mapper.fusion import resize_mask

    return resize_mask(mask, shape[0], shape[1])


def join_split_by_people(dets: Sequence[Detection], people: Sequence[Detection], min_similarity: float,
                         gap_px: int = 2) -> tuple[list[Detection], int]:
    """``dets`` (no people among them) with the pieces of one object that a person of ``people`` cut in two
    joined into one detection each: same label, descriptors at least ``min_similarity`` alike (cosine), both
    masks within ``gap_px`` pixels of that person's mask. A joined detection has the union of the masks, the
    mean descriptor (unit), the highest confidence and the first piece's alternatives and instance key. Returns
    the detections (joined ones where their first piece was) and how many pieces were folded in."""
    dets = list(dets)
    if len(dets) < 2 or not people:
        return dets, 0
    import cv2

    k = np.ones((2 * gap_px + 1, 2 * gap_px + 1), np.uint8)
    grown = [cv2.dilate(p.mask.astype(np.uint8), k) > 0 for p in people]
    touches = [{j for j, g in enumerate(grown) if np.any(d.mask & _at(g, d.mask.shape))} for d in dets]
    parent = list(range(len(dets)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a in range(len(dets)):
        if not touches[a]:
            continue
        for b in range(a + 1, len(dets)):
            if dets[a].label != dets[b].label or not touches[a] & touches[b]:
                continue
            if float(np.dot(dets[a].descriptor, dets[b].descriptor)) < min_similarity:
                continue
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for i in range(len(dets)):
        groups.setdefault(root(i), []).append(i)
    out = []
    for first, members in sorted(groups.items()):
        if len(members) == 1:
            out.append(dets[first])
            continue
        parts = [dets[i] for i in members]
        mask = parts[0].mask.copy()
        for p in parts[1:]:
            mask |= _at(p.mask, mask.shape)
        desc = np.sum([p.descriptor for p in parts], axis=0).astype(np.float32)
        norm = float(np.linalg.norm(desc))
        out.append(dataclasses.replace(parts[0], mask=mask, descriptor=desc / norm if norm > 0 else parts[0].descriptor,
                                       confidence=max(p.confidence for p in parts)))
    return out, len(dets) - len(out)

