"""ConceptGraphs-style 3D fusion of 2D detections into object nodes (pure: no I/O).

Per view: each detection mask is back-projected with the reconstructed world points, low-confidence
depth is dropped, the cloud is voxel-downsampled and denoised (DBSCAN, keep the main cluster). Each
detection is associated to the existing node with the best score ``geo_weight * overlap + sem_weight *
similarity`` (overlap: fraction of the detection's points with a node point within ``overlap_radius_m``;
similarity: cosine of descriptors) when it reaches ``match_threshold``, else it starts a node. Merging
unions the clouds (voxel-downsampled, capped) and averages descriptors weighted by observation count.
Every ``merge_every_updates`` updates duplicate nodes are merged and rarely seen nodes dropped.

With the keyframe's camera and confident depth (``mapper.association``), association also happens in the
image: a node whose visible points project inside a detection's mask counts as overlapping it, and nodes one
mask holds are merged as fragments of one object (estimated depth scatters an object's views apart in 3D;
its masks do not).

Points are world metres (z up). Node ids are stable strings ``n000001``... that never get reused.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.absence import AbsenceParams, Judgement, Verdict, boxes_out_of_view, judge, nearest_depth
from mapper.association import KeyframeView, containment
from mapper.geometry.kernels import compiled
from mapper.perception.base import Detection, unit
from protocol.messages import GraphNode, LabelScore, OrientedBox
from protocol.poses import invert


class FusionConfig(BaseModel):
    """Fusion thresholds and bounds."""

    model_config = ConfigDict(extra="forbid")
    voxel_m: float = Field(default=0.03, gt=0.0, description="voxel size of node point clouds, metres")
    min_depth_confidence: float = Field(
        default=0.3, ge=0.0, le=1.0, description="pixels with lower depth confidence are not back-projected"
    )
    max_depth_m: float = Field(default=10.0, gt=0.0, description="pixels farther than this are ignored")
    min_points: int = Field(default=15, ge=1, description="detections with fewer valid 3D points are dropped")
    min_depth_fraction: float = Field(
        default=0.1, ge=0.0, le=1.0,
        description="detections with valid depth on less of their mask than this are dropped (sparse estimated "
        "depth on an object is mostly its edges and texture, where it is least reliable)",
    )
    min_object_points: int = Field(
        default=10, ge=3, description="detections with fewer points after downsampling and denoising are dropped"
    )
    min_z_m: float = Field(default=-0.15, description="points below this height (under the floor) are dropped")
    max_z_m: float = Field(default=3.5, description="points above this height are dropped")
    max_outside_fraction: float = Field(
        default=0.3, ge=0.0, le=1.0,
        description="a view whose confident points lie outside the [min_z_m, max_z_m] slab (under the floor, "
        "over the ceiling) more often than this has implausible depth (e.g. a stereo window without overlap) "
        "and is not fused at all; 1 disables the check",
    )
    min_mask_pixels: int = Field(default=30, ge=1, description="masks smaller than this are dropped")
    mask_erosion_px: int = Field(
        default=0, ge=0, le=8,
        description="erode masks by this many pixels (at the depth's resolution) before back-projection: "
        "estimated depth bleeds across object edges",
    )
    dbscan_eps_m: float = Field(
        default=0.2, gt=0.0,
        description="DBSCAN neighbourhood radius, metres; a detection keeps its largest cluster. Estimated depth on "
        "a textureless object is its textured parts (a table's two ends, a stool's legs): at 0.1 m only one part "
        "was kept and each view made a fragment",
    )
    dbscan_min_samples: int = Field(default=4, ge=1, description="DBSCAN core point neighbour count")
    depth_window_rel: float = Field(
        default=0.0, ge=0.0,
        description="a detection keeps only the pixels in its densest depth interval of width max(depth_window_min_m, "
        "this x the mask's size at its median depth); estimated depth smears across object edges and through "
        "thin objects to the background, and an object is seldom much deeper than it is wide. 0 disables",
    )
    depth_window_min_m: float = Field(default=0.3, gt=0.0, description="... the narrowest depth interval, metres")
    overlap_radius_m: float | None = Field(
        default=0.06,
        description="neighbour radius of the overlap measure (None: voxel_m). Two keyframes' estimated depth of "
        "one surface differs by a few centimetres; at the 3 cm voxel they did not overlap and made two nodes",
    )
    geo_weight: float = Field(default=1.0, ge=0.0, description="weight of geometric overlap in the match score")
    sem_weight: float = Field(default=1.0, ge=0.0, description="weight of descriptor similarity in the score")
    match_threshold: float = Field(default=1.1, description="score needed to associate with a node")
    min_overlap: float = Field(default=0.05, ge=0.0, le=1.0, description="overlap needed to associate at all")
    max_points_per_node: int = Field(default=3000, ge=10, description="cap on points kept per node")
    merge_every_updates: int = Field(default=5, ge=1, description="duplicate merge / prune period (updates)")
    merge_overlap: float = Field(
        default=0.5, ge=0.0, le=1.0, description="duplicates: overlap (either direction) needed to merge"
    )
    merge_similarity: float = Field(default=0.8, ge=-1.0, le=1.0, description="duplicates: descriptor cosine")
    coarse_same_ray_deg: float = Field(
        default=1.0, ge=0.0, le=10.0,
        description="a single-view detection whose ray (its camera centre to its points) lies within this many "
        "degrees of a ray of a coarse node from the same camera centre is that node, wherever other cameras moved "
        "it along the ray (its guessed points no longer overlap it): without this, a fixed camera without depth "
        "added a duplicate at every keyframe; 0 disables",
    )
    coarse_max_gap_m: float = Field(
        default=0.25, ge=0.0,
        description="coarse (single-view) nodes of one object seen from different cameras are merged at the "
        "point their viewing rays meet when the rays pass this close to it",
    )
    coarse_max_shift_m: float = Field(
        default=1.0, ge=0.0, description="... and that point is at most this far from each single-view estimate"
    )
    merge_box_overlap: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="duplicates: box intersection / smaller box volume that also merges similar nodes "
        "(estimated depth scatters one object's views too far apart for the point overlap)",
    )
    one_node_per_view: bool = Field(
        default=True,
        description="a node takes at most one detection of a keyframe (the assignment of highest total score); "
        "the others make their own nodes",
    )
    mask_association: bool = Field(
        default=True,
        description="also associate in the image: a node whose visible points project inside a detection's mask "
        "is that detection's object whatever its depth (estimated depth scatters one object's views along the "
        "rays; see mapper/association.py)",
    )
    min_containment: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="fraction of a node's visible points inside a detection's mask that counts as overlap",
    )
    merge_containment: float = Field(
        default=0.6, ge=0.0, le=1.0,
        description="nodes this much inside one detection's mask (and similar to it) are fragments of one object "
        "and merge into the node the detection joins",
    )
    containment_min_points: int = Field(
        default=10, ge=1, description="a node with fewer points visible in a keyframe is not judged by its masks"
    )
    occlusion_margin_m: float = Field(
        default=0.2, ge=0.0,
        description="a node point farther than the keyframe's confident depth by this (plus occlusion_margin_rel "
        "of that depth) is hidden there and does not count",
    )
    occlusion_margin_rel: float = Field(default=0.15, ge=0.0, description="... relative part of that margin")
    ghost_merge: bool = Field(
        default=True,
        description="merge a ghost into its host: a rarely seen node that lies, along its own viewing rays, nearer "
        "or farther than a similar node. Estimated depth that is wrong for one keyframe (or a few from one place) "
        "puts a copy of the object there, out of the other views' masks, where neither point overlap nor mask "
        "association joins them. The host keeps its points. Two nodes that one keyframe showed as two "
        "detections are never merged; when each lies on the other's rays (both seen from one side), the better "
        "seen one is the host. A coarse (single-view) node is the ghost of a measured node on its placement rays "
        "at any distance (its depth is a guess)",
    )
    ghost_max_observations: int = Field(
        default=3, ge=1, description="ghost merge: only nodes seen at most this often can be ghosts"
    )
    ghost_max_across_m: float = Field(
        default=0.25, ge=0.0,
        description="ghost merge: the host's centre passes at most this far (or half the host's largest "
        "horizontal size, if more) from each of the ghost's viewing rays (camera centre to the observation's "
        "mean point) ...",
    )
    ghost_across_ratio: float = Field(
        default=0.6, ge=0.0,
        description="... and at most this fraction of its distance from the ghost along that ray (a depth error "
        "moves a copy along the ray; a neighbour of the same class sits beside it)",
    )
    ghost_max_angle_deg: float = Field(
        default=7.0, ge=0.0, le=45.0,
        description="... and within this angle of the ray seen from its camera (the host projects near where the "
        "ghost's detection was in that keyframe; a neighbour on a table seen from close by is farther off)",
    )
    ghost_min_along_m: float = Field(
        default=0.15, ge=0.0, description="ghost merge: the two nodes are at least this far apart along each ray ..."
    )
    ghost_max_along_m: float = Field(
        default=1.5, ge=0.0, description="... and at most this far, or ghost_max_along_rel of the host's distance"
    )
    ghost_max_along_rel: float = Field(
        default=0.5, ge=0.0, le=0.9,
        description="... (stereo depth errors grow with distance: far objects came back at half their depth)",
    )
    max_sight_lines: int = Field(
        default=8, ge=1,
        description="viewing rays remembered per node for ghost merging (the latest); a node seen more often "
        "than ghost_max_observations is never a ghost, so more are not needed",
    )
    max_keyframes_per_node: int = Field(
        default=64, ge=1,
        description="keyframes remembered per node (the latest) to know which nodes one keyframe told apart",
    )
    min_observations: int = Field(default=1, ge=1, description="nodes seen fewer times are dropped after ...")
    prune_after_updates: int = Field(default=15, ge=1, description="... this many updates since creation")
    weak_node_points: int = Field(
        default=40, ge=0, description="nodes seen once with fewer points are dropped after prune_after_updates"
    )
    max_nodes: int = Field(default=2000, ge=1, description="hard cap on nodes (least observed dropped)")
    box_trim_fraction: float = Field(
        default=0.005, ge=0.0, lt=0.5,
        description="node boxes ignore this fraction of points at each end of each axis (robust to strays)",
    )
    centroid_trim_fraction: float = Field(
        default=0.05, ge=0.0, lt=0.5,
        description="a node's centroid is the centre of its points' extent after ignoring this fraction at each "
        "end of each axis: estimated depth leaves tails along the viewing rays that would drag it off the object",
    )
    growth_factor: float = Field(
        default=1.5, ge=0.0,
        description="a node may not grow (by a detection joining it or a node merging into it) to a horizontal "
        "size (footprint diagonal) over this times the largest that one of its single observations showed, plus "
        "growth_slack_m: one view shows most of an object, so a node that keeps growing past it is swallowing "
        "its neighbours (chairs round two tables as one 6 m chair) or estimated depth smeared along the rays. "
        "Measured depth only; 0 disables",
    )
    growth_slack_m: float = Field(default=0.3, ge=0.0, description="... plus this, metres")
    keep_told_apart: bool = Field(
        default=True,
        description="duplicate and fragment merging leave alone two nodes that one keyframe showed as two "
        "detections (as ghost merging does): books side by side on a shelf, whose estimated depth makes their "
        "boxes overlap, are two objects",
    )
    absence_check: bool = Field(
        default=True,
        description="evidence for absence (mapper/absence.py): a measured keyframe that should see a node (in view, "
        "in range, not occluded by anything nearer) and sees through where it stands counts against it; "
        "absence_to_retire such keyframes with no detection of it in between retire it (removed in a delta, kept "
        "queryable as retired). Detected again, or a surface seen where it stands, clears the count",
    )
    absence_to_retire: int = Field(
        default=2, ge=1,
        description="keyframes that must see a node's place empty, with no detection of it in between, to retire "
        "it: two agree where one keyframe's wrong estimated depth would not (a fixed camera's next keyframe, or "
        "another robot keyframe, confirms)",
    )
    absence_max_range_m: float = Field(
        default=6.0, gt=0.0, description="absence: nodes farther than this from the camera are not judged"
    )
    absence_min_pixels: int = Field(
        default=20, ge=1,
        description="absence: a node covering fewer pixels of the keyframe's depth map is not judged (too small "
        "there to have been detected)",
    )
    absence_min_in_view: float = Field(
        default=0.6, ge=0.0, le=1.0,
        description="absence: at least this fraction of a node's points must project inside the image",
    )
    absence_min_known: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="absence: at least this fraction of the node's pixels must have confident depth (missing "
        "depth is no evidence)",
    )
    absence_max_occluded: float = Field(
        default=0.3, ge=0.0, le=1.0,
        description="absence: a node with more of its pixels behind something nearer (a passer-by) is not judged: "
        "occlusion is not absence",
    )
    absence_max_occluded_static: float = Field(
        default=0.7, ge=0.0, le=1.0,
        description="absence: ... when the keyframe's 2D perception says where people are, that limit is for the "
        "pixels people hide, and this one for those anything hides (furniture in front: a wall camera sees half of "
        "a dining chair over the table); the pixels left in sight must still number absence_min_pixels. Set it to "
        "absence_max_occluded for perception that does not label people (fusion.people_labels)",
    )
    absence_min_free: float = Field(
        default=0.7, ge=0.5, le=1.0,
        description="absence: this fraction of the node's unoccluded pixels with depth must show depth clearly "
        "beyond it (free); the same fraction at its depth says it is there",
    )
    absence_missed_to_retire: int = Field(
        default=3, ge=0,
        description="a calibrated fixed camera that detected a node before and now sees its place unoccluded "
        "(absence_missed_max_occluded) with a surface at its depth, or partly one and partly seen through "
        "(mapper.absence's MIXED), but detects nothing there counts a miss: an object flush against a wall or "
        "on a table leaves a surface within the depth margin where it stood, so depth alone cannot see it gone. "
        "Without depth (a single-view keyframe) the camera counts a miss where its previous single-view keyframe "
        "saw the node on a similar detection and this one sees it on none (ObjectMap.count_misses). This many "
        "misses and see-throughs together, with no detection in between, retire the node (the camera confirms "
        "every absence_confirm_s while a count is open); 0 disables misses",
    )
    absence_pixels: bool = Field(
        default=True,
        description="a fixed camera's single-view keyframe asks, for its misses, the pixels where it detected the "
        "node (kept per node and camera) rather than the node's points projected into its view (other cameras' "
        "RGB-only depth spreads a node's points over what stands around it); off: the points",
    )
    absence_missed_max_occluded: float = Field(
        default=0.1, ge=0.0, le=1.0,
        description="a miss needs at most this fraction of the node's pixels behind something nearer: a "
        "passer-by that hides part of an object can shrink its detection away",
    )
    absence_mixed_sight_deg: float = Field(
        default=45.0, ge=0.0, le=180.0,
        description="a moving camera (a robot) that sees a node's place partly seen through and partly a surface "
        "(mapper.absence's MIXED: a low table gone from beside a sofa leaves the sofa within the depth margin) and "
        "detects nothing there counts a miss, as a fixed camera does, when a detection of the node was seen "
        "along a line within this many degrees of its view of the node, from no more than "
        "absence_mixed_max_range_x as far (it saw the object from about there); 0 disables",
    )
    absence_mixed_max_range_x: float = Field(
        default=1.5, gt=0.0, description="... the distance of the view at most this multiple of that sighting's"
    )
    absence_margin_m: float = Field(
        default=0.1, ge=0.0,
        description="absence: depth beyond (or before) the node's surface by this much, metres, plus "
        "absence_margin_rel of its depth, is clearly beyond (nearer)",
    )
    absence_margin_rel: float = Field(default=0.05, ge=0.0, description="... relative part of that margin")
    absence_window_px: int = Field(
        default=1, ge=0, le=8,
        description="absence: a pixel's depth is the nearest confident depth within this many pixels (of the "
        "keyframe's depth map): a thin object covering a pixel or two, whose estimated depth is often the "
        "background's, does not look seen through",
    )
    absence_confirm_s: float = Field(
        default=1.0, ge=0.0,
        description="a calibrated fixed camera whose keyframe saw a node's place empty makes its next frame at "
        "least this many seconds later a keyframe too (it keyframes only on image change, and one keyframe is "
        "not enough to retire); so does one whose measured keyframe made a node (seen once, a small one would be "
        "pruned as a stray, weak_node_points); 0 disables",
    )
    move_min_similarity: float = Field(
        default=0.8, ge=-1.0, le=1.0,
        description="moves: a detection that matches no node, has a node's label and at least this descriptor "
        "similarity to it, while that node's place is seen empty (this keyframe or an earlier one since it was "
        "last detected), moves that node there (same id, a move record) instead of making a new node",
    )
    move_min_m: float = Field(
        default=0.3, ge=0.0, description="moves: ... when the detection is at least this far from the node's centre"
    )
    people_labels: list[str] = Field(
        default_factory=lambda: ["person"],
        description="detection labels that are people: not fused into object nodes (unless fuse_people); their "
        "depth still counts as occlusion, so a passer-by hides objects without making them absent",
    )
    fuse_people: bool = Field(default=False, description="fuse people_labels detections into nodes like objects")
    join_split_by_people: bool = Field(
        default=True,
        description="join the pieces of one object that a person in front cut in two (same label, descriptors "
        "merge_similarity alike, both masks touching that person's): a segmenter that reports connected regions "
        "would make each piece a node (mapper.perception.occluded)",
    )
    max_label_alternatives: int = Field(default=3, ge=0, description="label alternatives kept per node")
    seed: int = Field(default=0, description="seed of point subsampling")

    @property
    def radius_m(self) -> float:
        return self.overlap_radius_m if self.overlap_radius_m is not None else self.voxel_m

    def absence_params(self) -> AbsenceParams:
        """The ``absence_*`` thresholds as :func:`mapper.absence.judge` takes them."""
        return AbsenceParams(
            max_range_m=self.absence_max_range_m, min_pixels=self.absence_min_pixels,
            min_in_view=self.absence_min_in_view, min_known=self.absence_min_known,
            max_occluded=self.absence_max_occluded, max_occluded_static=self.absence_max_occluded_static,
            min_free=self.absence_min_free,
            margin_m=self.absence_margin_m, margin_rel=self.absence_margin_rel, window_px=self.absence_window_px,
        )


# ------------------------------------------------------------------------------------------------
# Point-cloud helpers


def _pack(ijk: np.ndarray) -> np.ndarray:
    off = np.int64(1 << 20)
    ijk = np.clip(ijk, -off + 1, off - 1).astype(np.int64) + off
    return (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]


def voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """int64 keys of the voxels holding ``points`` (N, 3)."""
    return _pack(np.floor(np.asarray(points, dtype=np.float64) / voxel_m).astype(np.int64))


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per occupied voxel (the mean of its points), float32 (M, 3)."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(pts) == 0:
        return pts
    _, inv, counts = np.unique(voxel_keys(pts, voxel_m), return_inverse=True, return_counts=True)
    sums = sum_by_index(inv.reshape(-1), pts, len(counts))
    return (sums / counts[:, None]).astype(np.float32)


def rows_all(mask: np.ndarray) -> np.ndarray:
    """``np.all(mask, axis=-1)`` of a bool array (..., k), one column at a time: the same values, ~10x faster
    for a short last axis (x, y, z), along which numpy reduces row by row."""
    if mask.shape[-1] == 0:
        return np.ones(mask.shape[:-1], dtype=bool)
    out = mask[..., 0].copy()
    for c in range(1, mask.shape[-1]):
        out &= mask[..., c]
    return out


def sum_by_index(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, k) float64 sums of the rows of ``values`` (N, k) by ``index`` (N,): ``np.add.at`` into zeros, the same
    sums bit for bit (each bin adds its values in row order, in float64) but ~10x faster (one ``bincount`` per
    column)."""
    vals = np.asarray(values)
    return np.stack([np.bincount(index, weights=vals[:, c], minlength=n) for c in range(vals.shape[1])], axis=1) \
        if len(index) else np.zeros((n, vals.shape[1]), dtype=np.float64)


def dbscan_labels(points: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """DBSCAN cluster label per point (-1 = noise), via a KD-tree and connected components."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n == 0:
        return np.full(n, -1, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    if _dbscan_compiled is not None:
        # Compiled: the same labels without a sparse matrix per detection (its construction and validation cost
        # more than the search: a detection's cloud has ~100 neighbours per point).
        labels = np.full(n, -1, dtype=np.int64)
        _dbscan_compiled(np.ascontiguousarray(pairs, np.int64).reshape(-1, 2), min_samples, labels)
        return labels
    return _dbscan_from_pairs(pairs, n, min_samples)


def _dbscan_from_pairs(pairs: np.ndarray, n: int, min_samples: int) -> np.ndarray:
    """DBSCAN labels of ``n`` points from their neighbour ``pairs`` (E, 2): core points (at least
    ``min_samples`` with themselves) by connected components, numbered as ``connected_components`` numbers
    them (each component by its lowest point); a border point takes the cluster of its last core neighbour in
    pair order (the pairs with it second take precedence)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels = np.full(n, -1, dtype=np.int64)
    degree = np.bincount(pairs.reshape(-1), minlength=n) + 1  # a point counts itself
    core = degree >= min_samples
    if not core.any():
        return labels
    cc = pairs[core[pairs[:, 0]] & core[pairs[:, 1]]]
    graph = coo_matrix((np.ones(len(cc)), (cc[:, 0], cc[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    labels[core] = comp[core]
    # Border points join the cluster of a core neighbour.
    for a, b in ((0, 1), (1, 0)):
        sel = core[pairs[:, a]] & ~core[pairs[:, b]]
        labels[pairs[sel, b]] = comp[pairs[sel, a]]
    return labels


def _dbscan_loops(pairs: Any, min_samples: int, labels: Any) -> None:  # pragma: no cover - compiled
    # What _dbscan_from_pairs computes, into ``labels`` (n, all -1): union-find with the lowest point as root.
    n = labels.shape[0]
    degree = np.ones(n, np.int64)
    for e in range(pairs.shape[0]):
        degree[pairs[e, 0]] += 1
        degree[pairs[e, 1]] += 1
    core = degree >= min_samples
    if not core.any():
        return
    root = np.arange(n)
    for e in range(pairs.shape[0]):
        i, j = pairs[e, 0], pairs[e, 1]
        if not (core[i] and core[j]):
            continue
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        while root[j] != j:
            root[j] = root[root[j]]
            j = root[j]
        if i < j:
            root[j] = i
        elif j < i:
            root[i] = j
    comp = np.empty(n, np.int64)
    count = 0
    for v in range(n):  # roots come first in their component: number components by their lowest point
        r = v
        while root[r] != r:
            r = root[r]
        root[v] = r
        if r == v:
            comp[v] = count
            count += 1
        else:
            comp[v] = comp[r]
        if core[v]:
            labels[v] = comp[v]
    for a in range(2):
        for e in range(pairs.shape[0]):
            p, q = pairs[e, a], pairs[e, 1 - a]
            if core[p] and not core[q]:
                labels[q] = comp[p]


_dbscan_compiled = compiled(_dbscan_loops)  # None without numba (optional, the ``server`` extra)


def main_cluster(points: np.ndarray, eps: float, min_samples: int) -> np.ndarray:
    """The points of the largest DBSCAN cluster (empty when all are noise)."""
    labels = dbscan_labels(points, eps, min_samples)
    valid = labels[labels >= 0]
    if len(valid) == 0:
        return points[:0]
    best = np.bincount(valid).argmax()
    return points[labels == best]


def trim_outliers(points: np.ndarray, fraction: float, min_points: int = 20) -> np.ndarray:
    """``points`` (N, 3) inside the per-axis ``[fraction, 1 - fraction]`` quantiles (all when too few)."""
    pts = np.asarray(points).reshape(-1, 3)
    if fraction <= 0.0 or len(pts) < min_points:
        return pts
    lo, hi = np.quantile(pts, [fraction, 1.0 - fraction], axis=0)
    keep = rows_all((pts >= lo) & (pts <= hi))
    return pts[keep] if int(keep.sum()) >= 3 else pts


def fit_box(points: np.ndarray, trim: float = 0.0) -> OrientedBox:
    """Gravity-aligned oriented box of ``points`` (N, 3): min-area footprint rectangle, z from min/max.

    ``trim`` > 0 first drops points outside the per-axis ``[trim, 1 - trim]`` quantiles (stray points of
    estimated depth would otherwise stretch the box and move its centre)."""
    import cv2

    pts = trim_outliers(np.asarray(points, dtype=np.float32).reshape(-1, 3), trim)
    if len(pts) == 0:
        return OrientedBox(center=(0.0, 0.0, 0.0), extent=(0.0, 0.0, 0.0))
    zmin, zmax = float(pts[:, 2].min()), float(pts[:, 2].max())
    if len(pts) < 3:
        lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
        c, e, yaw = (lo + hi) / 2.0, hi - lo, 0.0
    else:
        (cx, cy), (w, h), angle_deg = cv2.minAreaRect(np.ascontiguousarray(pts[:, :2]).reshape(-1, 1, 2))
        c, e, yaw = np.array([cx, cy]), np.array([w, h]), math.radians(angle_deg)
        # Keep yaw in [-pi/4, pi/4) by swapping axes: one canonical box per footprint.
        while yaw >= math.pi / 4:
            yaw -= math.pi / 2
            e = e[::-1]
        while yaw < -math.pi / 4:
            yaw += math.pi / 2
            e = e[::-1]
    return OrientedBox(
        center=(float(c[0]), float(c[1]), (zmin + zmax) / 2.0),
        extent=(float(e[0]), float(e[1]), zmax - zmin),
        yaw_rad=float(yaw),
    )


# ------------------------------------------------------------------------------------------------
# Detections in 3D


@dataclass(frozen=True)
class Object3D:
    """A denoised, downsampled 3D detection ready for association."""

    points: np.ndarray  # (M, 3) float32 world
    label: str
    confidence: float
    descriptor: np.ndarray
    alternatives: tuple[tuple[str, float], ...] = ()
    ray_origin: np.ndarray | None = None  # camera centre when the depth is a coarse single-view estimate
    mask: np.ndarray | None = None  # (h, w) bool at the depth map's resolution: the detection in its keyframe


@dataclass
class LiftStats:
    """Why detections were dropped while lifting them to 3D."""

    lifted: int = 0
    dropped_small_mask: int = 0
    dropped_no_depth: int = 0
    dropped_noise: int = 0
    no_depth: list[int] = field(default_factory=list)  # indices of the detections dropped for lack of depth

    @property
    def dropped(self) -> int:
        return self.dropped_small_mask + self.dropped_no_depth + self.dropped_noise


def resize_mask(mask: np.ndarray, h: int, w: int) -> np.ndarray:
    """``mask`` resized to (h, w) by nearest neighbour (bool)."""
    if mask.shape == (h, w):
        return mask
    import cv2

    return cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)


def outside_fraction(points_world: np.ndarray, confidence: np.ndarray, depth_m: np.ndarray, cfg: FusionConfig) -> float:
    """Fraction of a view's confident depth pixels whose world points lie outside the ``[min_z_m, max_z_m]``
    slab (0 when none is confident): true geometry of a room puts (nearly) none under the floor."""
    ok = (
        np.isfinite(depth_m) & (depth_m > 0) & (depth_m <= cfg.max_depth_m) & (confidence >= cfg.min_depth_confidence)
        & rows_all(np.isfinite(points_world))
    )
    n = int(ok.sum())
    if n == 0:
        return 0.0
    z = points_world[..., 2][ok]
    return float(np.count_nonzero((z < cfg.min_z_m) | (z > cfg.max_z_m)) / n)


def densest_interval(values: np.ndarray, width: float) -> tuple[float, float]:
    """The closed interval ``[lo, lo + width]`` holding the most of ``values`` (the nearest such one on ties)."""
    v = np.sort(values)
    counts = np.searchsorted(v, v + width, side="right") - np.arange(len(v))
    lo = float(v[int(np.argmax(counts))])
    return lo, lo + width


def depth_window(m: np.ndarray, full: np.ndarray, depth_m: np.ndarray, focal_px: float,
                 cfg: FusionConfig) -> np.ndarray:
    """``m`` (a mask's pixels with valid depth) less those outside its densest depth interval; the interval is
    ``depth_window_rel`` times the mask ``full``'s larger side in metres at the median depth (at least
    ``depth_window_min_m``). Unchanged when the interval keeps fewer than ``min_points`` pixels."""
    rows, cols = np.nonzero(full)
    side_px = max(int(rows.max() - rows.min()), int(cols.max() - cols.min())) + 1
    d = depth_m[m]
    width = max(cfg.depth_window_min_m, cfg.depth_window_rel * side_px * float(np.median(d)) / focal_px)
    lo, hi = densest_interval(d, width)
    kept = m & (depth_m >= lo) & (depth_m <= hi)
    return kept if int(kept.sum()) >= cfg.min_points else m


def lift_detections(
    detections: Sequence[Detection],
    points_world: np.ndarray,
    confidence: np.ndarray,
    depth_m: np.ndarray,
    cfg: FusionConfig,
    focal_px: float | None = None,
) -> tuple[list[Object3D], LiftStats]:
    """Back-project each mask with a view's reconstruction (``points_world`` (h, w, 3), ``confidence``
    and ``depth_m`` (h, w)); masks at another resolution are resized (nearest). ``focal_px`` (the focal length
    at the depth's resolution) enables ``depth_window_rel``."""
    h, w = depth_m.shape
    stats = LiftStats()
    valid = (
        np.isfinite(depth_m)
        & (depth_m > 0)
        & (depth_m <= cfg.max_depth_m)
        & (confidence >= cfg.min_depth_confidence)
        & rows_all(np.isfinite(points_world))
        & (points_world[..., 2] >= cfg.min_z_m)
        & (points_world[..., 2] <= cfg.max_z_m)
    )
    out: list[Object3D] = []
    for i, det in enumerate(detections):
        if int(det.mask.sum()) < cfg.min_mask_pixels:
            stats.dropped_small_mask += 1
            continue
        m = full = resize_mask(det.mask, h, w)
        if cfg.mask_erosion_px > 0:
            import cv2

            k = 2 * cfg.mask_erosion_px + 1
            eroded = cv2.erode(m.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
            m = eroded if int(eroded.sum()) >= cfg.min_points else m
        n_mask = int(m.sum())
        m = m & valid
        if int(m.sum()) < max(cfg.min_points, cfg.min_depth_fraction * n_mask):
            stats.dropped_no_depth += 1
            stats.no_depth.append(i)
            continue
        if focal_px is not None and cfg.depth_window_rel > 0:
            m = depth_window(m, full, depth_m, focal_px, cfg)
        pts = voxel_downsample(points_world[m], cfg.voxel_m)
        pts = main_cluster(pts, cfg.dbscan_eps_m, cfg.dbscan_min_samples)
        if len(pts) < cfg.min_object_points:
            stats.dropped_noise += 1
            continue
        stats.lifted += 1
        out.append(Object3D(pts, det.label, float(det.confidence), unit(det.descriptor), det.alternatives,
                            mask=full))
    return out, stats


# ------------------------------------------------------------------------------------------------
# Nodes


@dataclass(frozen=True)
class PixelRecord:
    """Where a fixed camera detected a node: flat pixel indices on its SeenView grid of ``shape``, seen from
    ``T_world_cam``."""

    T_world_cam: np.ndarray
    shape: tuple[int, int]
    pixels: np.ndarray


@dataclass
class NodeState:
    """Mutable fusion state of one node."""

    node_id: str
    points: np.ndarray
    descriptor: np.ndarray
    observations: int
    label_votes: dict[str, float]
    sources: set[str]
    first_seen_ns: int
    last_seen_ns: int
    created_update: int
    box_trim: float = 0.0
    centroid_trim: float = 0.0
    # Coarse (single-view) observations only: one (camera centre, unit direction to the placed object) per
    # observation. Empty once any multi-view observation joins the node.
    rays: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    # Measured observations: (camera centre, unit direction to the observation's mean point), the latest
    # ``max_sight_lines`` (ghost merging asks along which rays the node's depth could be wrong).
    sight: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    # The fusion updates (keyframes) in which a detection joined or made the node, the latest
    # ``max_keyframes_per_node``: two nodes that share one were told apart by that keyframe.
    seen_in: list[int] = field(default_factory=list)
    # The largest horizontal size (footprint diagonal, metres) one measured observation showed (growth_factor).
    view_size_m: float = 0.0
    # Keyframes that saw the node's place empty since it was last detected there (mapper.absence), and those of
    # fixed cameras that detected it before and saw its place clear but did not detect it (absence_missed_*).
    absent: int = 0
    missed: int = 0
    # Calibrated fixed cameras' single-view keyframes: where each (source id) last detected the node, as flat pixel
    # indices on its SeenView's grid, with that view's pose (ObjectMap.remember_pixels): its misses ask those pixels,
    # not the node's points projected (RGB-only depth from other cameras spreads the points over what stands around
    # the object). A record of another grid or pose (the camera moved, or changed resolution) is not asked.
    seen_px: dict[str, PixelRecord] = field(default_factory=dict)
    # Capture time of the keyframe that last moved the node (0: never moved), and how often it moved.
    last_moved_ns: int = 0
    moves: int = 0
    _tree: Any = field(default=None, repr=False)
    _box: OrientedBox | None = field(default=None, repr=False)
    _full_box: OrientedBox | None = field(default=None, repr=False)
    _centre: tuple[float, float, float] | None = field(default=None, repr=False)
    _aabb: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)  # (points, lo, hi)

    def touch(self) -> None:
        self._tree = None
        self._box = None
        self._full_box = None
        self._centre = None

    @property
    def centre(self) -> tuple[float, float, float]:
        """The centroid reported for the node: its points' extent centre, ``centroid_trim`` of the points
        ignored at each end of each axis."""
        if self._centre is None:
            self._centre = self.box.center if self.centroid_trim <= self.box_trim else fit_box(
                self.points, self.centroid_trim).center
        return self._centre

    @property
    def tree(self) -> Any:
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.points)
        return self._tree

    @property
    def box(self) -> OrientedBox:
        if self._box is None:
            self._box = fit_box(self.points, self.box_trim)
        return self._box

    @property
    def full_box(self) -> OrientedBox:
        """The box of all points, strays included (duplicate merging compares these)."""
        if self.box_trim <= 0:
            return self.box
        if self._full_box is None:
            self._full_box = fit_box(self.points)
        return self._full_box

    @property
    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Lowest and highest corner of the points, kept while ``points`` is the same array (association and
        maintenance ask for it once per node pair)."""
        cached = self._aabb
        if cached is None or cached[0] is not self.points:
            cached = self._aabb = (self.points, self.points.min(0), self.points.max(0))
        return cached[1], cached[2]

    def label_ranking(self) -> list[tuple[str, float]]:
        total = sum(self.label_votes.values()) or 1.0
        return sorted(((k, v / total) for k, v in self.label_votes.items()), key=lambda kv: (-kv[1], kv[0]))

    def to_message(self, max_alternatives: int = 3, with_embedding: bool = True) -> GraphNode:
        ranking = self.label_ranking() or [("object", 0.0)]
        box = self.box
        return GraphNode(
            node_id=self.node_id,
            label=ranking[0][0],
            label_confidence=float(min(1.0, max(0.0, ranking[0][1]))),
            label_alternatives=[LabelScore(label=k, score=float(v)) for k, v in ranking[1 : 1 + max_alternatives]],
            centroid=self.centre,
            box=box,
            point_count=int(len(self.points)),
            observation_count=int(self.observations),
            sources=sorted(self.sources),
            first_seen_ns=int(self.first_seen_ns),
            last_seen_ns=int(self.last_seen_ns),
            embedding=self.descriptor.astype(np.float32) if with_embedding else None,
        )


def seen_together(a: NodeState, b: NodeState) -> bool:
    """Whether one keyframe (fusion update) showed ``a`` and ``b`` as two detections: two objects."""
    return not set(a.seen_in).isdisjoint(b.seen_in)


# Added to a search radius where points certainly beyond it are skipped: rounding moves a distance by ~1e-16 of it.
_SEARCH_MARGIN_M = 1e-6
# Below a similarity threshold by this much, a batched (float64) similarity refuses a pair for certain: the float32 dot
# product of two unit descriptors that ``similarity`` takes is off by at most ~1e-4 (a few thousand dimensions).
_SIMILARITY_MARGIN = 1e-3


def footprint_diagonal(lo: np.ndarray, hi: np.ndarray) -> float:
    """Horizontal diagonal (metres) of the axis-aligned box ``lo``..``hi`` (x, y, z)."""
    return float(np.hypot(hi[0] - lo[0], hi[1] - lo[1]))


def overlap_fraction(points: np.ndarray, node: NodeState, radius_m: float) -> float:
    """Fraction of ``points`` with a point of ``node`` within ``radius_m``."""
    if len(points) == 0 or len(node.points) == 0:
        return 0.0
    # Only points inside the node's box grown by the radius can have a neighbour in it: the others (most, for
    # a detection beside the node) are not searched. The margin is far above what rounding can move a distance.
    lo, hi = node.aabb
    pad = radius_m + _SEARCH_MARGIN_M
    pts = np.asarray(points)
    near = rows_all((pts >= lo.astype(np.float64) - pad) & (pts <= hi.astype(np.float64) + pad))
    if not near.any():
        return 0.0
    d, _ = node.tree.query(pts[near], k=1, distance_upper_bound=radius_m)
    return float(np.count_nonzero(d <= radius_m) / len(pts))  # the mean over all points, bit for bit


def box_overlap(a: OrientedBox, b: OrientedBox) -> float:
    """Intersection volume of two gravity-aligned boxes over the smaller one's volume (0..1)."""
    from mapper.relations import footprint, footprint_intersection_area

    ea, eb = np.maximum(a.extent, 1e-3), np.maximum(b.extent, 1e-3)
    dz = min(a.center[2] + ea[2] / 2, b.center[2] + eb[2] / 2) - max(a.center[2] - ea[2] / 2, b.center[2] - eb[2] / 2)
    if dz <= 0:
        return 0.0
    inter = footprint_intersection_area(footprint(a, 1e-3), footprint(b, 1e-3)) * dz
    return float(inter / min(float(np.prod(ea)), float(np.prod(eb))))


def _view_size(obj: Object3D) -> float:
    """Horizontal size (footprint diagonal, metres) of one measured observation; 0 for a single-view guess."""
    if obj.ray_origin is not None or len(obj.points) == 0:
        return 0.0
    return footprint_diagonal(obj.points.min(0), obj.points.max(0))


def _rays_of(obj: Object3D) -> list[tuple[np.ndarray, np.ndarray]]:
    if obj.ray_origin is None or len(obj.points) == 0:
        return []
    o = np.asarray(obj.ray_origin, np.float64)
    d = obj.points.mean(0).astype(np.float64) - o
    n = float(np.linalg.norm(d))
    return [(o, d / n)] if n > 1e-9 else []


def _extent(points: np.ndarray) -> float:
    return float(np.max(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0


def _unambiguous_best(pairs: Sequence[tuple[float, str, str, np.ndarray]],
                      ratio: float = 0.5) -> tuple[float, str, str, np.ndarray] | None:
    """The closest pair (gap, a, b, point) whose two nodes have no rival partner nearly as close (a rival's gap
    above ``gap / ratio``): among many similar objects (books on a shelf) crossing rays prove nothing."""
    for cand in sorted(pairs, key=lambda q: (q[0], q[1], q[2])):
        gap, a, b, _ = cand
        rivals = [q[0] for q in pairs if q is not cand and ({q[1], q[2]} & {a, b})]
        if all(r * ratio > gap for r in rivals):
            return cand
    return None


def _share_camera(a: Sequence[tuple[np.ndarray, np.ndarray]], b: Sequence[tuple[np.ndarray, np.ndarray]]) -> bool:
    return any(float(np.linalg.norm(oa - ob)) < 1e-6 for oa, _ in a for ob, _ in b)


def ray_meeting_point(rays: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, float]:
    """Least-squares point closest to rays (origin, unit direction) and its largest distance to any of them
    (inf when the rays are parallel or the point lies behind a camera)."""
    A = np.zeros((3, 3))
    rhs = np.zeros(3)
    for o, d in rays:
        P = np.eye(3) - np.outer(d, d)
        A += P
        rhs += P @ o
    if np.linalg.cond(A) > 1e8:
        return np.full(3, np.nan), math.inf
    p = np.linalg.solve(A, rhs)
    if any(float((p - o) @ d) <= 0 for o, d in rays):
        return p, math.inf
    gap = max(float(np.linalg.norm((np.eye(3) - np.outer(d, d)) @ (p - o))) for o, d in rays)
    return p, gap


def similarity(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine similarity of two unit descriptors (0 when their dimensions differ)."""
    if a.shape != b.shape:
        return 0.0
    return float(np.dot(a, b))


@dataclass
class UpdateResult:
    """What one fusion update changed."""

    changed: set[str] = field(default_factory=set)
    removed: set[str] = field(default_factory=set)
    created: int = 0
    associated: int = 0
    merged_duplicates: int = 0
    pruned: int = 0
    # Of ``removed``: the nodes retired because keyframes saw their place empty, as they were when retired.
    retired: dict[str, NodeState] = field(default_factory=dict)
    # Nodes this update saw gone that are not retired yet (their count is below absence_to_retire).
    seen_gone: set[str] = field(default_factory=set)
    # Nodes moved to where a detection showed them: id -> (centre before, centre after).
    moved: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = field(default_factory=dict)
    # The node each of the update's objects joined or made, in their order (integrate).
    targets: list[str] = field(default_factory=list)


def _pixels_for(record: PixelRecord | None, view: Any) -> np.ndarray | None:
    """The pixels of a ``NodeState.seen_px`` record when ``view`` is of the same grid and pose, else None (and
    for no record, or an empty one)."""
    if record is None or len(record.pixels) == 0 or tuple(view.owner.shape) != record.shape:
        return None
    return record.pixels if np.allclose(record.T_world_cam, view.T_world_cam, atol=1e-4) else None


def _coverage(view: Any, probe: np.ndarray, by_pixels: bool, descriptor: np.ndarray, similarity: float) -> Any:
    """What a SeenView shows of one node: at ``probe`` pixels (flat indices on its grid) or points (world)."""
    if by_pixels:
        return view.coverage_pixels(probe, descriptor, similarity)
    return view.coverage(probe, descriptor, similarity)


class ObjectMap:
    """The fused object nodes. Not thread-safe: one owner (the mapper core) calls it."""

    def __init__(self, cfg: FusionConfig | None = None) -> None:
        self.cfg = cfg or FusionConfig()
        self.nodes: dict[str, NodeState] = {}
        self.next_id = 1
        self.updates = 0
        self._rng = np.random.default_rng(self.cfg.seed)

    # -- association ---------------------------------------------------------------------------
    def _node_boxes(self) -> tuple[list[NodeState], np.ndarray, np.ndarray]:
        """The nodes and their ``aabb`` corners stacked (n, 3) each, for :meth:`_candidates`."""
        nodes = list(self.nodes.values())
        return nodes, np.stack([n.aabb[0] for n in nodes]), np.stack([n.aabb[1] for n in nodes])

    def _candidates(self, pts: np.ndarray,
                    boxes: tuple[list[NodeState], np.ndarray, np.ndarray] | None = None) -> list[NodeState]:
        """The nodes whose point box comes within ``radius_m`` of ``pts``' (one vectorised test of every node's
        ``aabb``, element for element the comparisons a loop over the nodes makes). ``boxes``: :meth:`_node_boxes`
        when the caller has them (the nodes unchanged since)."""
        if not self.nodes:
            return []
        r = self.cfg.radius_m
        lo, hi = pts.min(0) - r, pts.max(0) + r
        nodes, nlo, nhi = self._node_boxes() if boxes is None else boxes
        near = np.all(nlo <= hi, axis=1) & np.all(nhi >= lo, axis=1)
        return [n for n, ok in zip(nodes, near.tolist(), strict=True) if ok]

    def scores(self, obj: Object3D, contained: dict[str, float] | None = None,
               boxes: tuple[list[NodeState], np.ndarray, np.ndarray] | None = None) -> dict[str, float]:
        """Per node that ``obj`` may join, its match score (only nodes reaching ``match_threshold``).
        ``contained``: per node id, the fraction of its visible points inside ``obj``'s mask (mask
        association); a fraction of at least ``min_containment`` counts as overlap. ``boxes``:
        :meth:`_node_boxes` when the caller has them (the nodes unchanged since)."""
        cfg = self.cfg
        inside = {k: v for k, v in (contained or {}).items() if v >= cfg.min_containment and k in self.nodes}
        cands = {n.node_id: n for n in self._candidates(obj.points, boxes)}
        cands.update((k, self.nodes[k]) for k in inside)
        same_ray = {k for k, n in self.nodes.items() if self._same_ray(n, obj)} if obj.ray_origin is not None else set()
        cands.update((k, self.nodes[k]) for k in same_ray)
        size = _view_size(obj)
        lo, hi = (obj.points.min(0), obj.points.max(0)) if size > 0 else (np.zeros(3), np.zeros(3))
        out: dict[str, float] = {}
        for node in cands.values():
            sim = similarity(obj.descriptor, node.descriptor)
            # Being in front of a node proves nothing about a different object: the image only vouches for
            # a node that looks like the detection.
            held = inside.get(node.node_id, 0.0) if sim >= cfg.merge_similarity else 0.0
            # Two single-view guesses are one object when their rays say so (triangulate_coarse), not because
            # their guessed boxes touch: they are judged at the voxel, measured depth at its noise.
            radius = cfg.voxel_m if (node.rays and obj.ray_origin is not None) else cfg.radius_m
            ov = 1.0 if node.node_id in same_ray else max(overlap_fraction(obj.points, node, radius), held)
            if ov < cfg.min_overlap or self._overgrown(node, lo, hi, size):
                continue
            score = cfg.geo_weight * ov + cfg.sem_weight * sim
            if score >= cfg.match_threshold:
                out[node.node_id] = score
        return out

    def assign(self, objects: Sequence[Object3D], inside: Sequence[dict[str, float]]) -> list[NodeState | None]:
        """The node each of one view's detections joins (None: a new node). With ``one_node_per_view`` a node
        takes at most one detection of the view (the assignment of highest total score): two detections of one
        view are two objects, and letting both join one node makes it swallow its neighbours (books on a shelf,
        chairs round a table). Otherwise each detection takes its best node."""
        # Scoring changes no node: the nodes' boxes are stacked once for all of the view's detections.
        boxes = self._node_boxes() if self.nodes else None
        table = [self.scores(obj, held, boxes) for obj, held in zip(objects, inside, strict=True)]
        if not self.cfg.one_node_per_view:
            return [self.nodes[min(t, key=lambda k: (-t[k], k))] if t else None for t in table]
        ids = sorted({k for t in table for k in t})
        out: list[NodeState | None] = [None] * len(objects)
        if not ids:
            return out
        from scipy.optimize import linear_sum_assignment

        col = {k: j for j, k in enumerate(ids)}
        gain = np.full((len(objects), len(ids)), -1e9)  # pairs below the threshold: never chosen
        for i, t in enumerate(table):
            for k, v in t.items():
                gain[i, col[k]] = v
        rows, cols = linear_sum_assignment(gain, maximize=True)
        for i, j in zip(rows, cols, strict=True):
            if ids[int(j)] in table[int(i)]:
                out[int(i)] = self.nodes[ids[int(j)]]
        return out

    def _overgrown(self, node: NodeState, lo: np.ndarray, hi: np.ndarray, size_m: float) -> bool:
        """Whether ``node`` joined by points with corners ``lo``, ``hi`` (from observations of horizontal size
        ``size_m``) would be larger than ``growth_factor`` times the largest single observation of either, plus
        ``growth_slack_m``. A single-view (coarse) side (size 0) is never judged: its size is a guess."""
        cfg = self.cfg
        if cfg.growth_factor <= 0 or node.rays or node.view_size_m <= 0 or size_m <= 0:
            return False
        nlo, nhi = node.aabb
        union = footprint_diagonal(np.minimum(nlo, lo), np.maximum(nhi, hi))
        return union > cfg.growth_factor * max(node.view_size_m, size_m) + cfg.growth_slack_m

    def _told_apart(self, a: NodeState, b: NodeState) -> bool:
        """Whether one keyframe showed ``a`` and ``b`` as two detections (and ``keep_told_apart`` is on)."""
        return self.cfg.keep_told_apart and seen_together(a, b)

    def _near_similar(self, obj: Object3D) -> NodeState | None:
        """The nearest node within ``coarse_max_shift_m`` of ``obj``'s centre with a similar descriptor."""
        c = obj.points.mean(0)
        best, best_d = None, self.cfg.coarse_max_shift_m
        for k in sorted(self.nodes):
            node = self.nodes[k]
            d = float(np.linalg.norm(node.points.mean(0) - c))
            if d <= best_d and similarity(obj.descriptor, node.descriptor) >= self.cfg.merge_similarity:
                best, best_d = node, d
        return best

    def containment(self, objects: Sequence[Object3D], view: KeyframeView) -> list[dict[str, float]]:
        """Per detection, the fraction of each node's visible points in ``view`` inside its mask (only nodes
        that reach ``min(min_containment, merge_containment)``)."""
        cfg = self.cfg
        with_mask = [i for i, o in enumerate(objects) if o.mask is not None]
        # at the view's depth resolution: a coarse placement's mask comes at the image's (layout depth)
        masks = [resize_mask(m, *view.depth_m.shape) for o in objects if (m := o.mask) is not None]
        out: list[dict[str, float]] = [{} for _ in objects]
        ids = sorted(self.nodes)
        if not with_mask or not ids:
            return out
        frac = containment(view, [self.nodes[k].points for k in ids], masks,
                           min_points=cfg.containment_min_points, margin_m=cfg.occlusion_margin_m,
                           margin_rel=cfg.occlusion_margin_rel)
        floor = min(cfg.min_containment, cfg.merge_containment)
        for col, i in enumerate(with_mask):
            out[i] = {ids[r]: float(frac[r, col]) for r in np.flatnonzero(frac[:, col] >= floor)}
        return out

    def _cap(self, pts: np.ndarray) -> np.ndarray:
        if len(pts) > self.cfg.max_points_per_node:
            idx = self._rng.choice(len(pts), self.cfg.max_points_per_node, replace=False)
            pts = pts[np.sort(idx)]
        return pts

    def _new_node(self, obj: Object3D, source_id: str, stamp_ns: int) -> NodeState:
        node_id = f"n{self.next_id:06d}"
        self.next_id += 1
        votes = {obj.label: max(obj.confidence, 1e-3)}
        for lab, score in obj.alternatives:
            votes[lab] = votes.get(lab, 0.0) + 0.5 * max(score, 0.0)
        node = NodeState(
            node_id=node_id,
            points=self._cap(obj.points.astype(np.float32)),
            descriptor=unit(obj.descriptor),
            observations=1,
            label_votes=votes,
            sources={source_id},
            first_seen_ns=stamp_ns,
            last_seen_ns=stamp_ns,
            created_update=self.updates,
            box_trim=self.cfg.box_trim_fraction,
            centroid_trim=self.cfg.centroid_trim_fraction,
            rays=_rays_of(obj),
            view_size_m=_view_size(obj),
        )
        self.nodes[node_id] = node
        return node

    def _same_ray(self, node: NodeState, obj: Object3D) -> bool:
        """Whether ``obj`` (a single-view detection) lies along a ray of ``node`` (coarse) from the same camera
        centre, within ``coarse_same_ray_deg``: the camera sees again what it placed there."""
        if obj.ray_origin is None or not node.rays or self.cfg.coarse_same_ray_deg <= 0:
            return False
        mine = _rays_of(obj)
        if not mine:
            return False
        o, d = mine[0]
        cos_min = math.cos(math.radians(self.cfg.coarse_same_ray_deg))
        return any(float(np.linalg.norm(ro - o)) < 1e-3 and float(rd @ d) >= cos_min for ro, rd in node.rays)

    def _absorb(self, node: NodeState, obj: Object3D, source_id: str, stamp_ns: int) -> None:
        n = node.observations
        again = self._same_ray(node, obj)  # seen again along a ray it has: its place along it stays as it is
        if again:
            pass
        elif node.rays and obj.ray_origin is None:
            node.points = self._cap(obj.points.astype(np.float32))  # measured depth replaces a coarse guess
        elif not node.rays and obj.ray_origin is not None:
            pass  # a coarse guess adds nothing to measured depth: the observation and its label still count
        else:
            node.points = self._cap(voxel_downsample(np.concatenate([node.points, obj.points]), self.cfg.voxel_m))
        node.descriptor = unit(node.descriptor * n + obj.descriptor)
        node.observations = n + 1
        node.label_votes[obj.label] = node.label_votes.get(obj.label, 0.0) + max(obj.confidence, 1e-3)
        for lab, score in obj.alternatives:
            node.label_votes[lab] = node.label_votes.get(lab, 0.0) + 0.5 * max(score, 0.0)
        node.sources.add(source_id)
        node.first_seen_ns = min(node.first_seen_ns, stamp_ns)
        node.last_seen_ns = max(node.last_seen_ns, stamp_ns)
        if not again:
            node.rays = node.rays + _rays_of(obj) if (node.rays and obj.ray_origin is not None) else []
        node.view_size_m = max(node.view_size_m, _view_size(obj))
        node.touch()

    def integrate(self, objects: Sequence[Object3D], source_id: str, stamp_ns: int,
                  view: KeyframeView | None = None,
                  detected: Sequence[tuple[np.ndarray, np.ndarray]] | None = None, fixed: bool = False) -> UpdateResult:
        """Fuse one view's 3D detections; runs maintenance every ``merge_every_updates`` updates. With the
        keyframe's ``view`` (and ``mask_association``), detections are also matched in the image, and nodes
        that one detection's mask holds are merged as fragments of its object; and the view judges the nodes
        it should see (``absence_*``, ``move_*``). ``detected``: every 2D detection of the keyframe as (mask,
        unit descriptor), those that could not be lifted to 3D included (default: the
        masks of ``objects``): a node one of them holds was detected there, whatever the depth says. ``fixed``:
        the keyframe is a calibrated fixed camera's (its misses count: ``absence_missed_*``)."""
        self.updates += 1
        res = UpdateResult()
        # What this keyframe's depth says about the nodes it should see, judged before its detections move any.
        judged = self.absence_judgements(view) if view is not None and self.cfg.absence_check else {}
        verdicts = {k: j.verdict for k, j in judged.items()}
        # Nodes this fixed camera detected before and now sees clear: not detected here, they count a miss.
        # A moving camera's MIXED view counts a miss where the node was detected from about there before.
        missable = {k for k, j in judged.items() if self.cfg.absence_missed_to_retire > 0
                    and j.occluded <= self.cfg.absence_missed_max_occluded * j.pixels
                    and ((j.verdict in (Verdict.THERE, Verdict.MIXED) and fixed and source_id in self.nodes[k].sources)
                         or (j.verdict is Verdict.MIXED and not fixed and self._sighted_from(self.nodes[k], view)))}
        inside = (self.containment(objects, view) if view is not None and self.cfg.mask_association
                  else [{} for _ in objects])
        # Match everything against the map as it was before this view: detections of one view are
        # distinct instances and must not absorb each other.
        matches = self.assign(objects, inside)
        if view is not None:
            # A coarse guess in a measured keyframe (an object stereo gave no depth) is poor along its ray: a
            # similar node near it is that object, not a new one.
            matches = [self._near_similar(obj) if node is None and obj.ray_origin is not None else node
                       for obj, node in zip(objects, matches, strict=True)]
        targets: list[str] = []
        matched = {n.node_id for n in matches if n is not None}
        # A node a similar detection's mask holds is that detection's, whatever its depth: never a move.
        held_any = {k for obj, held in zip(objects, inside, strict=True) for k, v in held.items()
                    if v >= self.cfg.min_containment and k in self.nodes
                    and similarity(obj.descriptor, self.nodes[k].descriptor) >= self.cfg.merge_similarity}
        for obj, node, held in zip(objects, matches, inside, strict=True):
            if node is None and view is not None:
                node = self._moving(obj, verdicts, missable, matched | set(targets) | set(held) | held_any)
                if node is not None:
                    self._move(node, obj, stamp_ns, res)
            if node is not None and node.node_id in self.nodes:
                self._absorb(node, obj, source_id, stamp_ns)
                node.absent = node.missed = 0
                res.associated += 1
                res.changed.add(node.node_id)
                targets.append(node.node_id)
            else:
                targets.append(self._new_node(obj, source_id, stamp_ns).node_id)
                res.changed.add(targets[-1])
                res.created += 1
            self._remember_sight(self.nodes[targets[-1]], obj, view)
        self._merge_fragments(objects, targets, inside, res)
        if verdicts and view is not None:
            if detected is None:
                detected = [(o.mask, o.descriptor) for o in objects if o.mask is not None]
            gone = sorted(k for k, v in verdicts.items() if (v is Verdict.FREE or k in missable) and k in self.nodes
                          and k not in targets)
            self._weigh_absence(verdicts, missable, set(targets) | self._held(view, gone, detected), res)
        if self.updates % self.cfg.merge_every_updates == 0:
            self.maintain(res)
        self._enforce_cap(res)
        res.changed -= res.removed
        res.targets = targets
        return res

    # -- absence and moves -------------------------------------------------------------------------
    def absence_verdicts(self, view: KeyframeView) -> dict[str, Verdict]:
        """Per measured node that ``view`` judges (``mapper.absence``), FREE, THERE or MIXED. Single-view (coarse)
        nodes are not judged: their depth is a guess (``check_coarse`` and ``forget_gone`` handle them)."""
        return {k: j.verdict for k, j in self.absence_judgements(view).items()}

    def absence_judgements(self, view: KeyframeView) -> dict[str, Judgement]:
        """:meth:`absence_verdicts` with the pixel counts behind each verdict."""
        params = self.cfg.absence_params()
        if not self.nodes:
            return {}
        view = nearest_depth(view, params.window_px)
        o = np.asarray(view.T_world_cam[:3, 3], np.float64)
        T_cam_world = invert(view.T_world_cam)
        reach = params.max_range_m + 2.0  # a node whose box is that far cannot have its median point in range
        near: list[str] = []
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            if node.rays or len(node.points) == 0:
                continue
            lo, hi = node.aabb
            if float(np.linalg.norm(np.clip(o, lo, hi) - o)) > reach:
                continue
            near.append(node_id)
        if not near:
            return {}
        # Most nodes lie outside the view: their verdict (UNKNOWN) shows in their boxes' corners, all at once.
        out_of_view = boxes_out_of_view(view, np.stack([self.nodes[k].aabb[0] for k in near]),
                                        np.stack([self.nodes[k].aabb[1] for k in near]), params.max_range_m,
                                        T_cam_world)
        out: dict[str, Judgement] = {}
        for node_id, skip in zip(near, out_of_view.tolist(), strict=True):
            if skip:
                continue
            j = judge(view, self.nodes[node_id].points, params, T_cam_world)
            if j.verdict is not Verdict.UNKNOWN:
                out[node_id] = j
        return out

    def _sighted_from(self, node: NodeState, view: KeyframeView | None) -> bool:
        """Whether a detection of ``node`` was seen along a line within ``absence_mixed_sight_deg`` of ``view``'s
        line to it, from at least 1 / ``absence_mixed_max_range_x`` of ``view``'s distance (``node.sight``):
        a camera there would have detected it."""
        cfg = self.cfg
        if view is None or cfg.absence_mixed_sight_deg <= 0 or not node.sight:
            return False
        o = np.asarray(view.T_world_cam[:3, 3], np.float64)
        c = np.asarray(node.centre, np.float64)
        dist = float(np.linalg.norm(c - o))
        if dist < 1e-9:
            return False
        cos_max = math.cos(math.radians(cfg.absence_mixed_sight_deg))
        for so, sd in node.sight:
            if float(np.dot(sd, (c - o) / dist)) >= cos_max \
                    and dist <= cfg.absence_mixed_max_range_x * float(np.linalg.norm(c - so)):
                return True
        return False

    def _moving(self, obj: Object3D, verdicts: dict[str, Verdict], missable: set[str], taken: set[str]
                ) -> NodeState | None:
        """The node that a detection matching no node shows moved (``move_*``): one with its label and a similar
        descriptor, at least ``move_min_m`` away, whose place was seen empty often enough to retire it, this
        keyframe included (:meth:`_retires`: one wrong estimated depth must not move a node onto its twin), and
        not ``taken`` (by another detection of this keyframe, or projecting inside this detection's mask: then
        the detection is that node at a wrong estimated depth, not moved); the nearest."""
        if obj.ray_origin is not None or len(obj.points) == 0:
            return None

        def seen_gone(node_id: str, node: NodeState) -> bool:
            if node_id in taken or node.rays:
                return False
            miss = node_id in missable
            if verdicts.get(node_id) is Verdict.THERE and not miss:
                return False
            return self._retires(node.absent + (verdicts.get(node_id) is Verdict.FREE), node.missed + miss)

        candidates = [(k, n) for k, n in self.nodes.items() if seen_gone(k, n)]
        return self._nearest_twin(obj.label, obj.descriptor, obj.points.mean(0).astype(np.float64), candidates)

    def _nearest_twin(self, label: str, descriptor: np.ndarray, centre: np.ndarray,
                      candidates: Iterable[tuple[str, NodeState]]) -> NodeState | None:
        """Of ``candidates`` (id, node), the nearest to ``centre`` whose top label is ``label``, whose descriptor
        is at least ``move_min_similarity`` like ``descriptor`` and which lies at least ``move_min_m`` away (ties
        by id): the object itself, moved, for :meth:`_moving` and :meth:`_moved_before`."""
        cfg = self.cfg
        best: tuple[float, str] | None = None
        for node_id, node in candidates:
            ranking = node.label_ranking()
            if not ranking or ranking[0][0] != label:
                continue
            if similarity(descriptor, node.descriptor) < cfg.move_min_similarity:
                continue
            d = float(np.linalg.norm(np.asarray(node.centre, np.float64) - centre))
            if d >= cfg.move_min_m and (best is None or (d, node_id) < best):
                best = (d, node_id)
        return None if best is None else self.nodes[best[1]]

    def _move(self, node: NodeState, obj: Object3D, stamp_ns: int, res: UpdateResult) -> None:
        """Put ``node`` where ``obj`` shows it (its old points, rays and sight lines are of the old place); the
        caller then absorbs ``obj`` as an observation."""
        before = node.centre
        node.points = self._cap(obj.points.astype(np.float32))
        node.rays, node.sight = [], []
        node.seen_px = {}  # of the old place; the camera that moved it notes the new one (remember_pixels)
        node.view_size_m = _view_size(obj)
        node.last_moved_ns = stamp_ns
        node.moves += 1
        node.touch()
        start = res.moved[node.node_id][0] if node.node_id in res.moved else before
        res.moved[node.node_id] = (start, node.centre)

    def _held(self, view: KeyframeView, ids: Sequence[str], detected: Sequence[tuple[np.ndarray, np.ndarray]]
              ) -> set[str]:
        """Of ``ids``, the nodes a similar detection's mask holds (``min_containment`` of their visible points):
        detected there, whatever depth the detection came with (estimated depth beyond an object on its pixels
        and its detection alike, or none to lift it with)."""
        cfg = self.cfg
        if not ids or not detected:
            return set()
        h, w = view.depth_m.shape
        frac = containment(view, [self.nodes[k].points for k in ids], [resize_mask(m, h, w) for m, _ in detected],
                           min_points=cfg.containment_min_points, margin_m=cfg.occlusion_margin_m,
                           margin_rel=cfg.occlusion_margin_rel)
        out = set()
        for r, k in enumerate(ids):
            for j, (_, desc) in enumerate(detected):
                if frac[r, j] >= cfg.min_containment and similarity(
                        unit(desc), self.nodes[k].descriptor) >= cfg.merge_similarity:
                    out.add(k)
                    break
        return out

    def _retires(self, absent: int, missed: int) -> bool:
        """Whether ``absent`` see-throughs and ``missed`` misses (``absence_*``) retire a node."""
        cfg = self.cfg
        return absent >= cfg.absence_to_retire or (
            cfg.absence_missed_to_retire > 0 and missed > 0 and absent + missed >= cfg.absence_missed_to_retire)

    def _weigh_absence(self, verdicts: dict[str, Verdict], missable: set[str], detected: set[str],
                       res: UpdateResult) -> None:
        """Add this keyframe's verdicts to each node's counts (a detection clears them; a surface where it stands
        clears the see-throughs, unless it is a fixed camera's miss); retire the nodes that reach
        ``absence_to_retire`` see-throughs, or ``absence_missed_to_retire`` see-throughs and misses."""
        for node_id in detected:
            if node_id in self.nodes:
                self.nodes[node_id].absent = self.nodes[node_id].missed = 0
        for node_id, verdict in sorted(verdicts.items()):
            node = self.nodes.get(node_id)
            if node is None or node_id in detected or node_id in res.moved:
                continue
            if verdict is not Verdict.FREE and node_id not in missable:
                if verdict is Verdict.THERE:
                    node.absent = 0
                continue
            if verdict is Verdict.FREE:
                node.absent += 1
            else:
                node.missed += 1
            if not self._retires(node.absent, node.missed):
                res.seen_gone.add(node_id)
                continue
            newcomer = self._moved_before(node, verdicts)
            if newcomer is None:
                self.retire(node_id, res)
                continue
            # Seen at its new place first (a robot that came round the other way): the node moves there and the
            # newcomer, a copy of it under another id, folds into it.
            self._move(node, Object3D(newcomer.points, "", 0.0, newcomer.descriptor), newcomer.first_seen_ns, res)
            self.merge_nodes(node, newcomer)
            node.rays = list(newcomer.rays)  # a single-view camera's placement stays coarse (its checks go on)
            node.absent = node.missed = 0
            res.removed.add(newcomer.node_id)
            res.changed.add(node_id)
            res.merged_duplicates += 1

    def _moved_before(self, node: NodeState, verdicts: dict[str, Verdict]) -> NodeState | None:
        """A node that is ``node`` seen at a new place before its old place was seen empty: first detected after
        ``node`` was last detected, never in one keyframe with it, its label and a similar descriptor
        (``move_min_similarity``), at least ``move_min_m`` away and not itself seen gone; the nearest such one.
        Single-view (coarse) placements take part: a fixed camera without depth sees an object go that another
        camera placed anew in its room."""
        ranking = node.label_ranking()
        if not ranking:
            return None
        candidates = [(k, o) for k, o in self.nodes.items()
                      if not (o is node or o.first_seen_ns <= node.last_seen_ns or o.absent or o.missed
                              or verdicts.get(k) is Verdict.FREE or seen_together(node, o))]
        return self._nearest_twin(ranking[0][0], node.descriptor, np.asarray(node.centre, np.float64), candidates)

    def remember_pixels(self, objects: Sequence[Object3D], targets: Sequence[str], source_id: str, seen: Any
                        ) -> None:
        """A fixed camera's single-view keyframe fused ``objects`` into ``targets`` (``UpdateResult.targets``):
        note on each node where this camera detected it, on the grid of ``seen`` (its SeenView), with its pose."""
        h, w = seen.owner.shape
        for obj, k in zip(objects, targets, strict=False):
            node = self.nodes.get(k)
            if node is None or obj.mask is None:
                continue
            px = np.flatnonzero(resize_mask(obj.mask, h, w)).astype(np.int32)
            if len(px):
                node.seen_px[source_id] = PixelRecord(np.array(seen.T_world_cam, np.float64), (h, w), px)

    def retire(self, node_id: str, res: UpdateResult) -> None:
        """Remove ``node_id`` because its place was seen empty: ``res`` records it as removed and retired."""
        node = self.nodes.pop(node_id)
        res.removed.add(node_id)
        res.retired[node_id] = node
        res.changed.discard(node_id)
        res.pruned += 1

    def _remember_sight(self, node: NodeState, obj: Object3D, view: KeyframeView | None) -> None:
        """Note that this update's detection ``obj`` joined ``node`` and, for measured depth seen from ``view``'s
        camera, along which ray."""
        node.seen_in = (node.seen_in + [self.updates])[-self.cfg.max_keyframes_per_node:]
        if view is None or obj.ray_origin is not None or len(obj.points) == 0:
            return
        o = np.asarray(view.T_world_cam[:3, 3], np.float64)
        d = obj.points.mean(0).astype(np.float64) - o
        n = float(np.linalg.norm(d))
        if n > 1e-9:
            node.sight = (node.sight + [(o, d / n)])[-self.cfg.max_sight_lines:]

    def _merge_fragments(self, objects: Sequence[Object3D], targets: Sequence[str],
                         inside: Sequence[dict[str, float]], res: UpdateResult) -> None:
        """Merge into each detection's node the other nodes its mask holds (``merge_containment`` of their
        visible points, descriptors similar): one mask, one object. A node another detection of this view
        joined, held by two masks, or placed by single-view geometry is left alone."""
        cfg = self.cfg
        claimed = set(targets)
        holders: dict[str, int] = {}
        for held in inside:
            for k, v in held.items():
                if v >= cfg.merge_containment:
                    holders[k] = holders.get(k, 0) + 1
        for obj, target, held in zip(objects, targets, inside, strict=True):
            for k in sorted(held):
                if k == target:
                    continue
                if held[k] < cfg.merge_containment or k in claimed or holders[k] > 1 or target not in self.nodes:
                    continue
                node, keep = self.nodes.get(k), self.nodes[target]
                if node is None or node.rays or keep.rays:
                    continue
                if similarity(node.descriptor, obj.descriptor) < cfg.merge_similarity:
                    continue
                if self._overgrown(keep, *node.aabb, node.view_size_m) or self._told_apart(keep, node):
                    continue
                # The longer-lived node keeps its id (consumers already know it).
                keep, gone = (keep, node) if (keep.observations, node.node_id) >= (node.observations, target) \
                    else (node, keep)
                self.merge_nodes(keep, gone)
                target = keep.node_id
                res.merged_duplicates += 1
                res.removed.add(gone.node_id)
                res.changed.add(target)

    # -- maintenance ---------------------------------------------------------------------------
    def merge_nodes(self, keep: NodeState, gone: NodeState, keep_points: bool = False) -> None:
        """Fold ``gone`` into ``keep`` (clouds, descriptors weighted by observations, votes, sources);
        ``keep_points``: ``gone``'s points are dropped (they are misplaced)."""
        a, b = keep.observations, gone.observations
        if keep_points:
            pass
        elif bool(keep.rays) != bool(gone.rays):
            keep.points = (gone if keep.rays else keep).points  # measured depth replaces a coarse guess
        else:
            keep.points = self._cap(voxel_downsample(np.concatenate([keep.points, gone.points]), self.cfg.voxel_m))
        keep.descriptor = unit(keep.descriptor * a + gone.descriptor * b)
        keep.observations = a + b
        for lab, v in gone.label_votes.items():
            keep.label_votes[lab] = keep.label_votes.get(lab, 0.0) + v
        keep.sources |= gone.sources
        keep.seen_px = {**gone.seen_px, **keep.seen_px}
        keep.first_seen_ns = min(keep.first_seen_ns, gone.first_seen_ns)
        keep.last_seen_ns = max(keep.last_seen_ns, gone.last_seen_ns)
        keep.created_update = min(keep.created_update, gone.created_update)
        keep.rays = keep.rays + gone.rays if (keep.rays and gone.rays) else []
        if not keep_points:  # a ghost's rays led to where it was misplaced, not to ``keep``
            keep.sight = (keep.sight + gone.sight)[-self.cfg.max_sight_lines:]
        keep.seen_in = sorted(set(keep.seen_in) | set(gone.seen_in))[-self.cfg.max_keyframes_per_node:]
        keep.view_size_m = max(keep.view_size_m, gone.view_size_m)
        keep.absent = min(keep.absent, gone.absent)
        keep.missed = min(keep.missed, gone.missed)
        keep.last_moved_ns = max(keep.last_moved_ns, gone.last_moved_ns)
        keep.moves += gone.moves
        keep.touch()
        del self.nodes[gone.node_id]

    def triangulate_coarse(self, res: UpdateResult | None = None) -> UpdateResult:
        """Merge coarse (single-view) nodes of one object seen by different cameras at the point where their
        viewing rays meet, and move each coarse node seen from several cameras to that point.

        A single-view estimate is good along the image and poor in depth; two cameras' rays through the same
        object fix the depth. Pairs need similar descriptors, rays that pass within ``coarse_max_gap_m`` (and
        half the smaller node's size) of their least-squares meeting point, a point within
        ``coarse_max_shift_m`` of both estimates, and no rival pair for either node nearly as close; the
        closest such pair merges first, one merge at a time, until none is left. Two nodes that one camera
        has seen both of are never merged: it told them apart already."""
        res = res if res is not None else UpdateResult()
        cfg = self.cfg
        while True:
            coarse = [n for n in (self.nodes[k] for k in sorted(self.nodes)) if n.rays]
            pairs: list[tuple[float, str, str, np.ndarray]] = []
            for i, a in enumerate(coarse):
                for b in coarse[i + 1:]:
                    if _share_camera(a.rays, b.rays) or similarity(a.descriptor, b.descriptor) < cfg.merge_similarity:
                        continue  # one camera that saw both told them apart already
                    p, gap = ray_meeting_point(a.rays + b.rays)
                    size = min(_extent(a.points), _extent(b.points))
                    if gap > min(cfg.coarse_max_gap_m, max(0.05, 0.5 * size)) or max(
                        float(np.linalg.norm(p - a.points.mean(0))), float(np.linalg.norm(p - b.points.mean(0)))
                    ) > cfg.coarse_max_shift_m:
                        continue
                    pairs.append((gap, a.node_id, b.node_id, p))
            best = _unambiguous_best(pairs)
            if best is None:
                break
            _, a_id, b_id, p = best
            a, b = self.nodes[a_id], self.nodes[b_id]
            for n in (a, b):
                n.points = (n.points - n.points.mean(0) + p).astype(np.float32)
            keep, gone = (a, b) if (a.observations, b.node_id) >= (b.observations, a.node_id) else (b, a)
            self.merge_nodes(keep, gone)
            res.merged_duplicates += 1
            res.removed.add(gone.node_id)
            res.changed.add(keep.node_id)
        res.changed -= res.removed
        return res

    def maintain(self, res: UpdateResult | None = None) -> UpdateResult:
        """Merge duplicate nodes, then drop nodes seen too rarely."""
        res = res if res is not None else UpdateResult()
        cfg = self.cfg
        ids = sorted(self.nodes)
        pairs: list[tuple[float, str, str]] = []
        near = self._near_pairs(ids)
        for i, a_id in enumerate(ids):
            a = self.nodes[a_id]
            for j in np.flatnonzero(near[i, i + 1 :]) + i + 1:
                b_id = ids[j]
                b = self.nodes[b_id]
                sim = similarity(a.descriptor, b.descriptor)
                if sim < cfg.merge_similarity or (a.rays and b.rays):
                    continue  # two coarse (single-view) nodes are one object only if their rays say so
                if self._told_apart(a, b):
                    continue
                ov = max(overlap_fraction(a.points, b, cfg.radius_m), overlap_fraction(b.points, a, cfg.radius_m))
                # A coarse (single-view) node's box is a guess: containment in it proves nothing.
                boxes_count = not (a.rays or b.rays)
                if ov >= cfg.merge_overlap or (
                    boxes_count and box_overlap(a.full_box, b.full_box) >= cfg.merge_box_overlap
                ):
                    pairs.append((ov + sim, a_id, b_id))
        for _, a_id, b_id in sorted(pairs, key=lambda p: (-p[0], p[1], p[2])):
            if a_id not in self.nodes or b_id not in self.nodes:
                continue
            a, b = self.nodes[a_id], self.nodes[b_id]
            if self._overgrown(a, *b.aabb, b.view_size_m):
                continue
            keep, gone = (a, b) if (a.observations, b.node_id) >= (b.observations, a.node_id) else (b, a)
            self.merge_nodes(keep, gone)
            res.merged_duplicates += 1
            res.removed.add(gone.node_id)
            res.changed.add(keep.node_id)
        if cfg.ghost_merge:
            self.merge_ghosts(res)
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            aged = self.updates - node.created_update >= cfg.prune_after_updates
            # A coarse (single-view) node is a deliberate placement of a whole mask, not a stray: few points
            # there mean a small object.
            weak = node.observations < 2 and len(node.points) < cfg.weak_node_points and not node.rays
            if (aged and (node.observations < cfg.min_observations or weak)) or len(node.points) < 3:
                del self.nodes[node_id]
                res.pruned += 1
                res.removed.add(node_id)
        res.changed -= res.removed
        return res

    def _on_rays(self, ghost: NodeState, host: NodeState) -> float | None:
        """The largest distance of ``host``'s centre across ``ghost``'s viewing rays when it lies on every one of
        them at a ghost's distance (``FusionConfig.ghost_*``); None when it does not, or ``ghost`` has none. A
        coarse (single-view) ghost's depth is a guess: its rays are those of its placements, at any distance."""
        cfg = self.cfg
        coarse = bool(ghost.rays)
        lines = ghost.rays or ghost.sight
        if not lines:
            return None
        cg, ch = np.asarray(ghost.centre, np.float64), np.asarray(host.centre, np.float64)
        wide = 0.5 * float(max(host.box.extent[0], host.box.extent[1]))
        worst, tan_max = 0.0, math.tan(math.radians(cfg.ghost_max_angle_deg))
        for o, d in lines:
            tg, th = float((cg - o) @ d), float((ch - o) @ d)
            across = float(np.linalg.norm(ch - o - th * d))
            gap = math.inf if coarse else abs(th - tg)
            if th <= 0 or not (coarse or cfg.ghost_min_along_m <= gap <= max(
                    cfg.ghost_max_along_m, cfg.ghost_max_along_rel * th)):
                return None
            if across > min(max(cfg.ghost_max_across_m, wide), cfg.ghost_across_ratio * gap, tan_max * th):
                return None
            worst = max(worst, across)
        return worst

    def ghost_host(self, ghost: NodeState, host: NodeState) -> float | None:
        """How far (the largest distance across a ray) ``host``'s centre lies from ``ghost``'s viewing rays, when
        ``ghost`` looks like a copy of ``host`` misplaced along them (see ``FusionConfig.ghost_merge``); None
        when it does not. Pure: reads the two nodes only."""
        cfg = self.cfg
        if (host.rays or host is ghost or ghost.observations > cfg.ghost_max_observations
                or ghost.observations > host.observations
                or seen_together(ghost, host)
                or similarity(ghost.descriptor, host.descriptor) < cfg.merge_similarity):
            return None
        across = self._on_rays(ghost, host)
        if across is None:
            return None
        # The host is seen at least as often; each on the other's rays (seen from one side only): more often,
        # or as often with more points.
        if not ghost.rays and self._on_rays(host, ghost) is not None and (
                (ghost.observations, len(ghost.points)) >= (host.observations, len(host.points))):
            return None
        return across

    def merge_ghosts(self, res: UpdateResult | None = None) -> UpdateResult:
        """Merge each ghost (a rarely seen node that is a copy of a better seen one misplaced along its own
        viewing rays, ``ghost_host``) into its host; the host keeps its points. Closest pairs first."""
        res = res if res is not None else UpdateResult()
        cfg = self.cfg
        ids = sorted(self.nodes)
        if len(ids) < 2:
            return res
        centres = np.array([self.nodes[k].centre for k in ids], np.float64)
        # ghost_host's cheap refusals, for every host of a ghost at once: a host with rays, the ghost itself, a host
        # seen less often (exact: flags and counts), and a dissimilar host (by a margin far above the float32
        # rounding of a descriptor's dot product). Only the hosts left are asked, in the same order.
        nodes = [self.nodes[k] for k in ids]
        observed = np.array([n.observations for n in nodes])
        no_rays = np.array([not n.rays for n in nodes])
        shapes = {n.descriptor.shape for n in nodes}
        descs = np.stack([n.descriptor for n in nodes]).astype(np.float64) if len(shapes) == 1 else None
        pairs: list[tuple[float, str, str]] = []
        for i, g_id in enumerate(ids):
            ghost = self.nodes[g_id]
            if not (ghost.rays or ghost.sight) or ghost.observations > cfg.ghost_max_observations:
                continue
            if ghost.rays:  # a coarse ghost's depth is a guess: a host at any distance
                reach = math.inf
            else:  # at most (1 + ghost_across_ratio) times the largest gap along a ray from the ghost
                far = max(float((centres[i] - o) @ d) for o, d in ghost.sight)
                rel = cfg.ghost_max_along_rel
                reach = (1 + cfg.ghost_across_ratio) * max(cfg.ghost_max_along_m, rel / (1 - rel) * far) + 1e-6
            host_ok = np.linalg.norm(centres - centres[i], axis=1) <= reach
            host_ok &= no_rays & (observed >= ghost.observations)
            host_ok[i] = False
            if descs is not None:  # NaN: asked, as similarity's own test refuses nothing then
                host_ok &= ~(descs @ descs[i] < cfg.merge_similarity - _SIMILARITY_MARGIN)
            for j in np.flatnonzero(host_ok):
                across = self.ghost_host(ghost, self.nodes[ids[j]])
                if across is not None:
                    pairs.append((across, g_id, ids[j]))
        for _, g_id, h_id in sorted(pairs):
            if g_id not in self.nodes or h_id not in self.nodes:
                continue
            self.merge_nodes(self.nodes[h_id], self.nodes[g_id], keep_points=True)
            res.merged_duplicates += 1
            res.removed.add(g_id)
            res.changed.add(h_id)
        res.changed -= res.removed
        return res

    def _near_pairs(self, ids: Sequence[str]) -> np.ndarray:
        """(n, n) whether the nodes ``ids``' point boxes come within ``radius_m`` of each other (the same test,
        element for element, as comparing each pair's ``aabb``)."""
        if not ids:
            return np.zeros((0, 0), dtype=bool)
        r = self.cfg.radius_m
        lo = np.stack([self.nodes[k].aabb[0] for k in ids])
        hi_r = np.stack([self.nodes[k].aabb[1] + r for k in ids])  # added in each node's own dtype, as before
        apart = np.any(lo[:, None, :] > hi_r[None, :, :], axis=-1)
        return ~(apart | apart.T)

    def forget_gone(self, seen: Any, res: UpdateResult | None = None, min_points: int = 15,
                    min_free: float = 0.6) -> int:
        """Coarse nodes that the camera of ``seen`` (a ``SeenView`` of its new keyframe) placed before and now
        sees as free floor are gone (moved or taken away): retired (:meth:`retire`), and ``res`` says so. This is
        the single-view camera's evidence for absence (measured keyframes judge nodes in ``absence_verdicts``);
        the camera that placed the node from this very view is trusted at once. Nodes this keyframe just
        updated stay. Returns how many went."""
        res = res if res is not None else UpdateResult()
        origin = seen.T_world_cam[:3, 3]
        gone = 0
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            if node_id in res.changed or not any(float(np.linalg.norm(o - origin)) < 1e-6 for o, _ in node.rays):
                continue
            n, free, _ = seen.votes(node.points, node.descriptor, self.cfg.merge_similarity)
            if n >= min_points and free >= min_free * n:
                self.retire(node_id, res)
                gone += 1
        return gone

    def count_misses(self, seen: Any, before: Any, source_id: str, res: UpdateResult, min_points: int = 15,
                     min_pixels: int = 4, min_seen: float = 0.3, max_same: float = 0.1) -> set[str]:
        """A calibrated fixed camera's single-view keyframe (``seen``, a ``SeenView``; ``before``, its previous
        one or None) as evidence of absence without depth: a node this camera detected (``source_id`` among its
        sources), within ``absence_max_range_m``, whose points (at least ``absence_min_in_view`` of them and
        ``min_points``, on ``min_pixels`` pixels) land in view on almost no similar detection (``max_same``) and
        mostly on no other one (``absence_max_occluded``: a passer-by in front is no evidence; when ``seen``
        knows which detections are people, that limit is for them and ``absence_max_occluded_static`` for any,
        with ``min_points`` left on no detection) counts a miss,
        as in measured keyframes (``absence_missed_*``). The first miss also needs ``before`` to have seen the
        node on a similar detection (``min_seen`` of its points): the camera saw it there from this very pose,
        so a node its estimated geometry puts elsewhere in this view never starts a count. Where this camera
        noted the pixels it detected the node on (``absence_pixels``, :meth:`remember_pixels`), those pixels are
        asked instead of the node's points projected, with ``min_pixels`` of them left in sight. Nodes this keyframe
        updated are skipped. Returns the nodes that counted; retires (or moves, :meth:`_moved_before`) those
        that reach the count."""
        cfg = self.cfg
        if not cfg.absence_check or cfg.absence_missed_to_retire <= 0:
            return set()
        params = cfg.absence_params()
        misses = set()
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            if node_id in res.changed or source_id not in node.sources or len(node.points) < min_points:
                continue
            record = node.seen_px.get(source_id) if cfg.absence_pixels else None
            px = _pixels_for(record, seen)
            # where this camera detected the node: the pixels, not the points, which other cameras' RGB-only depth
            # may have spread over the table and the chairs around it
            by_pixels = px is not None
            probe = px if px is not None else node.points[:: max(1, -(-len(node.points) // params.max_points))]
            c = _coverage(seen, probe, by_pixels, node.descriptor, cfg.merge_similarity)
            if by_pixels:
                least: float = min_pixels
                min_left = min_pixels
                far = float(np.linalg.norm(np.asarray(node.centre) - seen.T_world_cam[:3, 3])) > params.max_range_m
            else:
                least, min_left = max(min_points, params.min_in_view * len(probe)), min_points
                far = c.depth_m > params.max_range_m
            if (c.points < least or c.pixels < min_pixels or far or c.same > max_same * c.points
                    or params.too_hidden(c.points, c.other, c.people, min_left)):
                continue
            if node.missed == 0 and node.absent == 0:
                b = (None if before is None or (by_pixels and _pixels_for(record, before) is None)
                     else _coverage(before, probe, by_pixels, node.descriptor, cfg.merge_similarity))
                if b is None or b.points == 0 or b.same < min_seen * b.points:
                    continue
            misses.add(node_id)
        self._weigh_absence(dict.fromkeys(misses, Verdict.MIXED), misses, set(), res)
        return misses

    def check_coarse(self, views: Sequence[Any], res: UpdateResult | None = None, min_points: int = 15,
                     max_free: float = 0.6, remove_refuted: bool = False) -> int:
        """Check coarse nodes placed from one camera against what other calibrated cameras saw
        (``mapper.geometry.singleview.SeenView``): a node most of whose points another camera saw as free space
        (the floor, with nothing in front of it) is misplaced. It is moved along its own camera's ray to where
        the other cameras saw a similar detection; when there is no such place it stays, unless
        ``remove_refuted`` (off: a wall that looks like the floor would remove correct nodes; measured on the
        sim apartments, removing cost 0.02 F1 with 3 cameras). Returns how many nodes moved or went;
        ``res`` records them."""
        from mapper.geometry.singleview import relocate_along_ray

        res = res if res is not None else UpdateResult()
        sim = self.cfg.merge_similarity
        acted = 0
        for node_id in sorted(self.nodes):
            node = self.nodes[node_id]
            origin = node.rays[0][0] if node.rays else None
            if origin is None or any(float(np.linalg.norm(o - origin)) > 1e-6 for o, _ in node.rays):
                continue  # not coarse, or already fixed by several cameras
            others = [v for v in views if float(np.linalg.norm(v.T_world_cam[:3, 3] - origin)) > 1e-6]
            refuted = False
            for v in others:
                n, free, same = v.votes(node.points, node.descriptor, sim)
                if n >= min_points and free >= max_free * n and same < 0.3 * n:
                    refuted = True
                    break
            if not refuted:
                continue
            shift = relocate_along_ray(node.points, origin, node.descriptor, others, sim)
            if shift is None and not remove_refuted:
                continue
            if shift is None:
                del self.nodes[node_id]
                res.removed.add(node_id)
                res.pruned += 1
                acted += 1
                continue
            node.points = (node.points + shift).astype(np.float32)
            node.rays = [(origin, unit((node.points.mean(0) - origin).astype(np.float64)))]
            node.touch()
            res.changed.add(node_id)
            acted += 1
        res.changed -= res.removed
        return acted

    def _enforce_cap(self, res: UpdateResult) -> None:
        excess = len(self.nodes) - self.cfg.max_nodes
        if excess <= 0:
            return
        order = sorted(self.nodes.values(), key=lambda n: (n.observations, n.last_seen_ns, n.node_id))
        for node in order[:excess]:
            del self.nodes[node.node_id]
            res.removed.add(node.node_id)
            res.pruned += 1

    # -- export / persistence --------------------------------------------------------------------
    def messages(self, ids: Sequence[str] | None = None, with_embedding: bool = True) -> list[GraphNode]:
        """GraphNode messages of ``ids`` (default all), sorted by id."""
        sel = sorted(self.nodes) if ids is None else sorted(i for i in ids if i in self.nodes)
        return [self.nodes[i].to_message(self.cfg.max_label_alternatives, with_embedding) for i in sel]

    def boxes(self) -> dict[str, OrientedBox]:
        return {i: n.box for i, n in self.nodes.items()}

    def state(self) -> dict[str, Any]:
        """Plain-data state (numpy arrays as ``(dtype, shape, bytes)``) for persistence."""
        return {
            "next_id": self.next_id,
            "updates": self.updates,
            "nodes": [
                {
                    "node_id": n.node_id,
                    "points": n.points.astype(np.float32).tobytes(),
                    "descriptor": n.descriptor.astype(np.float32).tobytes(),
                    "observations": n.observations,
                    "label_votes": dict(n.label_votes),
                    "sources": sorted(n.sources),
                    "first_seen_ns": n.first_seen_ns,
                    "last_seen_ns": n.last_seen_ns,
                    "created_update": n.created_update,
                    "sight": [[float(x) for x in (*o, *d)] for o, d in n.sight],
                    "seen_in": list(n.seen_in),
                    "view_size_m": float(n.view_size_m),
                    "absent": int(n.absent),
                    "missed": int(n.missed),
                    "last_moved_ns": int(n.last_moved_ns),
                    "moves": int(n.moves),
                }
                for n in (self.nodes[k] for k in sorted(self.nodes))
            ],
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state` output (raises ``ValueError``/``KeyError`` on malformed state)."""
        nodes: dict[str, NodeState] = {}
        for d in state["nodes"]:
            pts = np.frombuffer(d["points"], dtype=np.float32).reshape(-1, 3).copy()
            nodes[str(d["node_id"])] = NodeState(
                node_id=str(d["node_id"]),
                points=pts,
                descriptor=np.frombuffer(d["descriptor"], dtype=np.float32).copy(),
                observations=int(d["observations"]),
                label_votes={str(k): float(v) for k, v in d["label_votes"].items()},
                sources=set(map(str, d["sources"])),
                first_seen_ns=int(d["first_seen_ns"]),
                last_seen_ns=int(d["last_seen_ns"]),
                created_update=int(d["created_update"]),
                # states written before ghost merging have neither: such a node is no ghost until seen again
                sight=[(np.array(v[:3], np.float64), np.array(v[3:6], np.float64)) for v in d.get("sight", [])],
                seen_in=[int(u) for u in d.get("seen_in", [])],
                # states written before the growth limit: the node's own size counts as one observation's
                view_size_m=float(d["view_size_m"]) if "view_size_m" in d else (
                    footprint_diagonal(pts.min(0), pts.max(0)) if len(pts) else 0.0),
                box_trim=self.cfg.box_trim_fraction,
                centroid_trim=self.cfg.centroid_trim_fraction,
                # states written before absence and moves: never seen gone, never moved
                absent=int(d.get("absent", 0)),
                missed=int(d.get("missed", 0)),
                last_moved_ns=int(d.get("last_moved_ns", 0)),
                moves=int(d.get("moves", 0)),
            )
        self.nodes = nodes
        self.next_id = int(state["next_id"])
        self.updates = int(state["updates"])
