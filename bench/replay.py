"""``argus bench replay``: a recorded sequence through the whole stack, its map scored against the sequence's own depth.

The stack of ``deploy/launch/replay.toml`` runs as separate processes on a free loopback port
(:class:`deploy.up.Stack`): a Zenoh router, ``argus mapper`` (RGB-only ``mvs`` geometry, classical 2D
perception, its own local worker process) and, once the mapper and its worker are alive, ``argus edge-camera``
with the ``recorded`` source, which plays the folder once at ``--rate`` frames per second, each frame with its
recorded pose as a prior and (``--declared``) the accuracy the sequence states for it. When the whole folder
was sent and the mapper is idle with no new graph version for ``--settle-s`` seconds (at most ``--timeout-s``),
this process reads the mapper's point map (``map/points``) and graph snapshot, stops the stack and reads each
node's fused points from the mapper's saved state. Then it scores:

- reference: the recorded depth (inside the sequence's valid range) fused with the recorded poses in an Open3D
  TSDF (voxel ~1 cm, scaled to the scene's depth; truncation 4 voxels), its surface points;
- map accuracy: distance from each map point to the nearest reference point (mean, median); completion: the
  share of reference points within 5 cm and within 10 cm of a map point;
- nodes: per node, the share of its fused points within 10 cm of the reference (its box corners and centroid
  when its points are unknown); nodes per label; same-label pairs whose centroids are under 0.5 m apart;
- capture-to-graph latency (graph deltas that changed nodes, from the capture stamp of the keyframe that made
  them, as ``argus bench system`` measures it), keyframes, dropped frames and keyframes (mapper status), and
  each keyframe's pose as the worker returned it against the recorded one (``work/result``);
- the same frames through an in-process :class:`mapper.core.MapperCore` with the launch file's mapper settings
  (header + JPEG through the mapper's own intake, ``bench.sequences.wire_views``): the same figures, so one
  sees whether transport and process boundaries lose anything.

Writes ``replay.json``, ``replay.md`` (every figure against its bar), ``replay.png`` (top-down view of the
reference with the nodes' boxes) and, when ``rerun`` is importable, ``replay.rrd``; the processes' logs go
to ``<out>/logs/``.

Example::

    argus bench replay --sequence ../shared/data/apc-shelf --out bench_out/replay/apc-shelf
"""

from __future__ import annotations

import argparse
import collections
import math
import shutil
import sys
import tempfile
import textwrap
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench import sequences as seqs
from bench.sequences import RecordedFrame, SequenceError
from bench.system import GraphWatch
from protocol.poses import PoseAccuracy, rotation_angle_deg

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_LAUNCH = REPO_ROOT / "deploy" / "launch" / "replay.toml"
NEAR_M = (0.05, 0.10)
"""Completion radii: a reference point counts as mapped within these distances of a map point."""
NODE_NEAR_M = 0.10
"""A node's point is on the reference surface within this distance."""
DUPLICATE_M = 0.5
"""Two same-label nodes whose centroids are closer than this count as one object mapped twice."""
CONFIRMED_VIEWS = 2
"""The map is also scored over the voxels at least this many keyframes observed (``PointMap.counts``): one view's
wrong depth makes voxels of its own, which a second keyframe rarely confirms. Reported beside the bar, not for it."""
UNLABELLED = "object"
"""The label of class-agnostic nodes (``classical`` perception, or a detector mask without a class)."""
PERCEPTIONS = {"classical": {"segmenter": "classical", "embedder": "classical"},
               "detector": {"segmenter": "detector", "embedder": "detector"}}
"""``--perception`` choices: the mapper's 2D segmenter and the embedder that goes with it (``mapper.perception``)."""
BARS = {"accuracy_median_m": 0.03, "completion_5cm": 0.50, "node_points_within": 0.90, "in_process_gap": 0.10,
        "latency_p99_s": 2.0}
"""The figures' bars (issue 36): median accuracy <= 3 cm, completion@5cm >= 50 %, node points within 10 cm
>= 90 %, replay within 10 % of the in-process path, capture-to-graph p99 <= 2 s."""


def _log(msg: str) -> None:
    print(f"[bench replay] {msg}", file=sys.stderr, flush=True)


# --- scoring (pure) ------------------------------------------------------------------------------
@dataclass(frozen=True)
class NodeCloud:
    """One graph node as scored: its label, centroid, box corners and (when known) its fused points, world frame."""

    node_id: str
    label: str
    centroid: np.ndarray
    corners: np.ndarray
    points: np.ndarray | None = None
    label_confidence: float = math.nan


def box_corners(center: Sequence[float], extent: Sequence[float], yaw_rad: float) -> np.ndarray:
    """(8, 3) corners of a box rotated by ``yaw_rad`` about world z (``protocol.messages.OrientedBox``)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    signs = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    return np.asarray(center, float) + (signs * np.asarray(extent, float)) @ R.T


def node_cloud(node: Any, points: np.ndarray | None = None) -> NodeCloud:
    """A :class:`NodeCloud` of a ``GraphNode`` (and its fused points, when known)."""
    b = node.box
    return NodeCloud(node.node_id, node.label, np.asarray(node.centroid, float),
                     box_corners(b.center, b.extent, b.yaw_rad), points, float(node.label_confidence))


def nearest_m(points: np.ndarray, to: Any) -> np.ndarray:
    """Distance in metres from each of ``points`` (N, 3) to the nearest of ``to``: (M, 3) points or a
    :func:`surface_tree` of them (build it once when querying one surface many times); all inf when ``to`` is
    empty."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    tree = to if isinstance(to, cKDTree) else surface_tree(to)
    if tree.n == 0:
        return np.full(len(pts), np.inf)
    if len(pts) == 0:
        return np.zeros(0)
    d, _ = tree.query(pts, k=1)
    return np.asarray(d, np.float64)


def surface_tree(points: np.ndarray) -> Any:
    """A k-d tree (``scipy.spatial.cKDTree``) of (M, 3) points, for :func:`nearest_m`."""
    from scipy.spatial import cKDTree

    return cKDTree(np.asarray(points, np.float64).reshape(-1, 3))


def map_scores(map_points: np.ndarray, reference: np.ndarray, near_m: Sequence[float] = NEAR_M,
               reference_tree: Any = None) -> dict[str, float]:
    """Accuracy (distance of each map point to the reference: mean, median, metres) and completion (share of the
    reference within each of ``near_m`` of the map). An empty map has no accuracy (NaN) and completion 0.
    ``reference_tree``: the reference's :func:`surface_tree`, when already built."""
    acc = nearest_m(map_points, reference if reference_tree is None else reference_tree)
    acc = acc[np.isfinite(acc)]
    out: dict[str, float] = {
        "map_points": float(len(np.asarray(map_points).reshape(-1, 3))),
        "reference_points": float(len(np.asarray(reference).reshape(-1, 3))),
        "accuracy_mean_m": float(acc.mean()) if len(acc) else math.nan,
        "accuracy_median_m": float(np.median(acc)) if len(acc) else math.nan,
    }
    comp = nearest_m(reference, map_points)
    for r in near_m:
        out[f"completion_{round(r * 100)}cm"] = float((comp <= r).mean()) if len(comp) else math.nan
    return out


def node_scores(nodes: Sequence[NodeCloud], reference: Any, near_m: float = NODE_NEAR_M
                ) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Per node: the share of its points within ``near_m`` of the reference (points, or their
    :func:`surface_tree`; its 8 box corners and centroid when its points are unknown, ``scored_by`` says which)
    and its centroid's distance; and over all nodes: the mean of the per-node shares, the share of all their
    points, the share of nodes with >= 90 % of their points near."""
    rows: list[dict[str, Any]] = []
    near_total = n_total = 0
    from scipy.spatial import cKDTree

    if not isinstance(reference, cKDTree):
        reference = surface_tree(reference)  # one tree for every node
    labelled = has_labels(nodes)
    for n in nodes:
        have = n.points is not None and len(n.points) > 0
        pts = n.points if have and n.points is not None else np.vstack([n.corners, n.centroid[None]])
        d = nearest_m(pts, reference)
        near = int((d <= near_m).sum())
        near_total += near
        n_total += len(d)
        rows.append({"node_id": n.node_id, "label": n.label, "label_confidence": n.label_confidence,
                     "judged_on": "label + geometry" if labelled and n.label != UNLABELLED else "geometry only",
                     "box_center_m": [round(float(v), 3) for v in box_center(n)],
                     "box_size_m": [round(v, 3) for v in box_size(n)],
                     "box_yaw_deg": round(math.degrees(_box_yaw(n)), 1), "scored_by": "points" if have else "box",
                     "points": len(d), "within": near / len(d) if len(d) else math.nan,
                     "centroid_m": float(nearest_m(n.centroid[None], reference)[0])})
    shares = [r["within"] for r in rows if not math.isnan(r["within"])]
    summary = {
        "nodes": float(len(rows)),
        "node_points_within": float(np.mean(shares)) if shares else math.nan,
        "node_points_within_pooled": near_total / n_total if n_total else math.nan,
        "nodes_90pct_within": float(np.mean([s >= 0.9 for s in shares])) if shares else math.nan,
        "nodes_scored_by_box": float(sum(r["scored_by"] == "box" for r in rows)),
    }
    return rows, summary


def labels_count(nodes: Sequence[NodeCloud]) -> dict[str, int]:
    """Nodes per label, most frequent first."""
    return dict(collections.Counter(n.label for n in nodes).most_common())


def has_labels(nodes: Sequence[NodeCloud], unlabelled: str = UNLABELLED) -> bool:
    """Whether any node carries a real class (a label other than ``unlabelled``): a closed-set perception ran."""
    return any(n.label != unlabelled for n in nodes)


def box_center(n: NodeCloud) -> np.ndarray:
    """Centre (3,) of a node's box, world frame: the mean of its corners."""
    return np.asarray(n.corners, float).mean(axis=0)


def box_size(n: NodeCloud) -> list[float]:
    """A node's box side lengths along its own x, y and z axes (metres; :func:`box_corners`' corner order)."""
    c = n.corners
    return [float(np.linalg.norm(c[4] - c[0])), float(np.linalg.norm(c[2] - c[0])), float(np.linalg.norm(c[1] - c[0]))]


def duplicate_pairs(nodes: Sequence[NodeCloud], radius_m: float = DUPLICATE_M, skip_label: str | None = None
                    ) -> list[dict[str, Any]]:
    """Pairs of nodes with the same label whose centroids are closer than ``radius_m``, closest first; nodes
    labelled ``skip_label`` (the class-agnostic label, when real labels exist) are left out."""
    kept = [n for n in nodes if skip_label is None or n.label != skip_label]
    out = []
    for i, a in enumerate(kept):
        for b in kept[i + 1:]:
            d = float(np.linalg.norm(a.centroid - b.centroid))
            if a.label == b.label and d < radius_m:
                out.append({"a": a.node_id, "b": b.node_id, "label": a.label, "distance_m": d})
    return sorted(out, key=lambda p: p["distance_m"])


def label_duplicates(nodes: Sequence[NodeCloud], radius_m: float = DUPLICATE_M) -> tuple[list[dict[str, Any]], str]:
    """Same-label pairs under ``radius_m`` and over which nodes they were counted: only the labelled ones when any
    node has a real class (class-agnostic ``object`` nodes are judged by geometry only), else all nodes."""
    if has_labels(nodes):
        return duplicate_pairs(nodes, radius_m, skip_label=UNLABELLED), "labelled nodes"
    return duplicate_pairs(nodes, radius_m), "all nodes (class-agnostic)"


RANGES_M = (0.0, 1.5, 3.0, 5.0, math.inf)
"""Bins of a map point's distance from the nearest recorded camera position, for :func:`accuracy_by_range`."""


def accuracy_by_range(map_points: np.ndarray, distances_m: np.ndarray, cameras: np.ndarray,
                      edges_m: Sequence[float] = RANGES_M) -> list[dict[str, Any]]:
    """Median accuracy of the map points binned by their distance from the nearest camera position (M, 3): where
    in depth the map's error lies."""
    pts = np.asarray(map_points, np.float64).reshape(-1, 3)
    rng = nearest_m(pts, cameras) if len(pts) else np.zeros(0)
    rows = []
    for lo, hi in zip(edges_m[:-1], edges_m[1:], strict=True):
        m = (rng >= lo) & (rng < hi)
        rows.append({"range_m": f"{lo:g}-{hi:g}", "points": int(m.sum()),
                     "accuracy_median_m": float(np.median(distances_m[m])) if m.any() else math.nan})
    return rows


def relative_gap(value: float, reference: float) -> float:
    """``|value - reference| / |reference|``; NaN when either is NaN or the reference is 0."""
    if not (math.isfinite(value) and math.isfinite(reference)) or reference == 0:
        return math.nan
    return abs(value - reference) / abs(reference)


COMPARED = ("accuracy_mean_m", "accuracy_median_m", "completion_5cm", "completion_10cm")
"""The map figures compared between the replay and the in-process path."""


def compare(replay: dict[str, float], in_process: dict[str, float]) -> dict[str, float]:
    """Relative gap of each of :data:`COMPARED` (replay against in-process) and the largest of them."""
    gaps = {f"gap_{k}": relative_gap(replay.get(k, math.nan), in_process.get(k, math.nan)) for k in COMPARED}
    finite = [g for g in gaps.values() if math.isfinite(g)]
    gaps["gap_max"] = max(finite) if len(finite) == len(COMPARED) else math.nan
    return gaps


def up_axis(poses: Sequence[np.ndarray]) -> tuple[int, int]:
    """The world axis nearest to 'up' as the cameras hold it, opposite the mean of their image-down directions
    (camera +y in the world: cameras are mostly held upright), and its sign (+1: up is +axis)."""
    down = np.mean([np.asarray(T, float)[:3, 1] for T in poses], axis=0) if len(poses) else np.array([0, 0, -1.0])
    axis = int(np.argmax(np.abs(down)))
    return axis, -1 if down[axis] > 0 else 1


def reference_voxel_m(frames: Sequence[RecordedFrame]) -> float:
    """TSDF voxel for the reference: the median valid recorded depth / 200 (0.5 % of the typical depth), clipped to
    5 mm .. 2 cm and rounded to the millimetre: ~1 cm for a room seen from 2 m."""
    depths = [f.depth_m[f.valid][:: max(1, int(f.valid.sum()) // 2000)] for f in frames]
    d = np.concatenate(depths) if depths else np.zeros(0)
    if len(d) == 0:
        return 0.01
    return float(np.clip(round(float(np.median(d)) / 200.0, 3), 0.005, 0.02))


def reference_surface(frames: Sequence[RecordedFrame], voxel_m: float, trunc_voxels: float = 4.0
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (N, 3) and colours (N, 3 uint8) of the recorded depth (valid pixels only) fused with the
    recorded poses in an Open3D TSDF (``voxel_m``, truncation ``trunc_voxels`` voxels), one point per voxel.

    The TSDF is Open3D's ``t.geometry.VoxelBlockGrid``: the legacy ``ScalableTSDFVolume`` of Open3D 0.20 as
    installed here integrates nothing (no volume unit, not even for a synthetic ramp), while its successor does."""
    import open3d as o3d
    import open3d.core as o3c

    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=(o3c.SizeVector([1]), o3c.SizeVector([1]), o3c.SizeVector([3])),
        voxel_size=voxel_m, block_resolution=8, block_count=50_000,
        device=o3c.Device("CPU:0"))
    for f in frames:
        depth_m = np.where(f.valid, f.depth_m, 0.0).astype(np.float32)
        if not depth_m.any():
            continue
        far = float(depth_m.max()) + voxel_m
        depth = o3d.t.geometry.Image(o3c.Tensor.from_numpy(depth_m))
        color = o3d.t.geometry.Image(o3c.Tensor.from_numpy(np.ascontiguousarray(f.rgb, dtype=np.float32) / 255.0))
        K = o3c.Tensor.from_numpy(np.ascontiguousarray(f.K, np.float64))
        T_cam_world = o3c.Tensor.from_numpy(np.linalg.inv(f.T_world_cam))  # Open3D takes world -> camera
        blocks = vbg.compute_unique_block_coordinates(depth, K, T_cam_world, 1.0, far, trunc_voxels)
        vbg.integrate(blocks, depth, color, K, T_cam_world, 1.0, far, trunc_voxels)
    try:
        pcd = vbg.extract_point_cloud(weight_threshold=0.5)  # every surface the depth saw, once is enough
    except RuntimeError:  # Open3D raises instead of returning an empty cloud
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    pts = pcd.point.positions.numpy().astype(np.float64)
    cols = pcd.point.colors.numpy() if "colors" in pcd.point else np.full((len(pts), 3), 0.5)
    return pts, (np.clip(cols, 0.0, 1.0) * 255).astype(np.uint8)


def pose_errors(recorded: dict[int, np.ndarray], mapped: dict[int, np.ndarray]) -> dict[str, Any]:
    """Each mapped keyframe's pose (by frame index) against its recorded one: translation (cm) and rotation (deg)
    differences, their medians and maxima."""
    rows = []
    for i in sorted(mapped):
        if i in recorded:
            T, R = mapped[i], recorded[i]
            rows.append({"frame": i, "trans_cm": 100 * float(np.linalg.norm(T[:3, 3] - R[:3, 3])),
                         "rot_deg": rotation_angle_deg(T[:3, :3], R[:3, :3])})
    tr = [r["trans_cm"] for r in rows]
    rot = [r["rot_deg"] for r in rows]
    return {"keyframes": rows, "n": len(rows),
            "trans_cm_median": float(np.median(tr)) if tr else math.nan, "trans_cm_max": max(tr, default=math.nan),
            "rot_deg_median": float(np.median(rot)) if rot else math.nan, "rot_deg_max": max(rot, default=math.nan)}


def _pct(values: Sequence[float], q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def split_first_keyframe(samples: Sequence[tuple[int, float]], captured: dict[int, int]) -> dict[str, Any]:
    """Capture-to-graph latencies (``samples``: the capture stamp, ns, of the keyframe behind each delta, and its
    latency, ms) with the first frame's apart. One moving camera's first keyframe cannot be reconstructed before
    a second view of it arrives (``keyframes_deferred`` in the mapper's status), so its latency holds one frame
    interval of waiting that no processing causes. Returns the latencies (s) of the other keyframes and their
    p50 / p99, the first keyframe's latencies and the wait: the second frame's capture minus the first's
    (``captured``: seq -> capture stamp, ns, of every frame the camera sent)."""
    stamps = sorted(captured.values())
    first = stamps[0] if stamps else None
    rest = [ms / 1000.0 for t, ms in samples if t != first]
    firsts = [ms / 1000.0 for t, ms in samples if t == first]
    wait = (stamps[1] - stamps[0]) / 1e9 if len(stamps) > 1 else math.nan
    return {"latency_rest_s": rest, "latency_rest_p50_s": _pct(rest, 50), "latency_rest_p99_s": _pct(rest, 99),
            "latency_first_s": firsts, "first_keyframe_wait_s": wait}


# --- one map, however it was made ----------------------------------------------------------------
@dataclass
class MapResult:
    """What a run produced: the point map, the nodes (with their fused points when known), keyframe poses by frame
    index, and the run's own figures."""

    points: np.ndarray
    nodes: list[NodeCloud]
    keyframe_poses: dict[int, np.ndarray]
    figures: dict[str, Any] = field(default_factory=dict)
    counts: np.ndarray | None = None  # keyframes that observed each map point's voxel (PointMap.counts)


def core_settings(mapper_settings: dict[str, Any]) -> Any:
    """The in-process core's configuration: the mapper process's settings, less what only the process has."""
    from mapper.config import MapperCoreConfig

    fields = set(MapperCoreConfig.model_fields)
    return MapperCoreConfig.model_validate({k: v for k, v in mapper_settings.items() if k in fields})


def map_in_process(frames: Sequence[RecordedFrame], declared: PoseAccuracy | None, mapper_settings: dict[str, Any],
                   source_id: str = "replay", progress: Callable[[str], None] = _log, rate_hz: float = 30.0
                   ) -> MapResult:
    """Every frame through the mapper's intake (header + JPEG, as from the wire, stamped as captured at ``rate_hz``:
    the replay's rate, since keyframe selection reads time) into an in-process ``MapperCore`` with
    ``mapper_settings``: its keyframe selection, geometry, perception and fusion, no processes. Keyframe poses:
    the core's last keyframe after each frame (a deferred keyframe retried in the same frame hides the other)."""
    from mapper.core import MapperCore

    t0 = time.monotonic()
    core = MapperCore(core_settings(mapper_settings))
    views = seqs.wire_views(list(frames), declared, source_id, rate_hz)
    poses: dict[int, np.ndarray] = {}
    last = None
    for k, v in enumerate(views):
        core.ingest(v)
        if core.last is not None and core.last is not last:
            last = core.last
            poses[last.view.seq] = np.asarray(last.T_world_cam, float)
        if (k + 1) % 10 == 0 or k + 1 == len(views):
            progress(f"in-process: {k + 1}/{len(views)} frames, {int(core.counters.get('keyframes', 0))} keyframes, "
                     f"{len(core.nodes())} nodes, {len(core.voxels)} map points")
    clouds = {nid: n.points for nid, n in core.objects.nodes.items()}
    nodes = [node_cloud(n, clouds.get(n.node_id)) for n in core.nodes()]
    # WireFeed numbers the frames 0, 1, ... in order: a view's seq is its frame's position in ``frames``.
    by_index = {frames[s].index: T for s, T in poses.items() if s < len(frames)}
    return MapResult(core.voxels.points().astype(np.float64), nodes, by_index,
                     {"seconds": time.monotonic() - t0, "views": len(views),
                      "counters": {k: float(v) for k, v in core.counters.items()}}, core.voxels.counts.copy())


# --- the stack -----------------------------------------------------------------------------------
class StackWatch(GraphWatch):
    """One client session's view of the replay: what ``bench.system.GraphWatch`` follows (graph deltas: count,
    newest version, latency; Status of the mapper and the camera), and the camera's frames (seq, pose, capture
    stamp), keyframe results' poses and the newest point map."""

    def __init__(self, session: Any, keys: Any, camera_id: str) -> None:
        super().__init__(session, keys)
        self.keys, self.camera_id = keys, camera_id
        self.frames: dict[int, np.ndarray] = {}  # seq -> T_world_cam of the header
        self.captured: dict[int, int] = {}  # seq -> the header's capture stamp, ns
        self.samples: list[tuple[int, float]] = []  # (delta's keyframe capture stamp ns, its latency ms)
        self.last_frame_t = 0.0
        self.results: dict[int, np.ndarray] = {}  # seq -> the worker's pose of that keyframe
        self.point_map: Any = None
        self._subs += [session.declare_subscriber(keys.cam_frame(camera_id), self._on_frame),
                       session.declare_subscriber(keys.all_work_results, self._on_result),
                       session.declare_subscriber(keys.map_points, self._on_map)]

    def _on_frame(self, sample: Any) -> None:
        from protocol.codec import DecodeError
        from protocol.transport import decode_frame_sample

        try:
            h = decode_frame_sample(sample).header
        except DecodeError:
            return
        if h.T_world_cam is None:
            return
        with self._lock:
            self.frames[h.seq] = np.asarray(h.T_world_cam, float)
            self.captured[h.seq] = h.stamp_ns
            self.last_frame_t = time.monotonic()

    def _latency(self, delta: Any, ms: float) -> None:
        self.samples.append((int(delta.stamp_ns), ms))

    def _on_result(self, sample: Any) -> None:
        from protocol.codec import DecodeError, decode
        from protocol.messages import WorkResult

        try:
            r = decode(sample.payload.to_bytes(), WorkResult)
        except DecodeError:
            return
        source, _, seq = r.job_id.rpartition("#")
        if r.ok and r.anchored and r.T_world_cam is not None and source == self.camera_id and seq.isdigit():
            with self._lock:
                self.results.setdefault(int(seq), np.asarray(r.T_world_cam, float))  # the first valid one wins

    def _on_map(self, sample: Any) -> None:
        from protocol.codec import DecodeError, decode
        from protocol.messages import PointMap

        try:
            pm = decode(sample.payload.to_bytes(), PointMap)
        except DecodeError:
            return
        with self._lock:
            if self.point_map is None or pm.version >= self.point_map.version:
                self.point_map = pm

    def view(self) -> dict[str, Any]:
        """A consistent copy of what was seen so far."""
        camera = f"edge-camera/{self.camera_id}"
        with self._lock:
            return {"deltas": self.deltas, "version": self.version, "last_change_t": self.last_change_t,
                    "latencies_ms": list(self.latencies_ms), "mapper": dict(self.status),
                    "camera": dict(self.others.get(camera, {})), "camera_error": self.other_errors.get(camera),
                    "frames": dict(self.frames), "last_frame_t": self.last_frame_t, "results": dict(self.results),
                    "point_map": self.point_map, "captured": dict(self.captured), "samples": list(self.samples)}


def frame_index_of(poses_by_seq: dict[int, np.ndarray], frames: Sequence[RecordedFrame]) -> dict[int, int]:
    """Which recorded frame each sent frame was (by its pose: the camera sends each frame's recorded pose)."""
    if not frames:
        return {}
    recorded = np.stack([f.T_world_cam for f in frames])
    out = {}
    for seq, T in poses_by_seq.items():
        k = int(np.argmin(np.abs(recorded - T[None]).reshape(len(frames), -1).max(axis=1)))
        out[seq] = frames[k].index
    return out


@dataclass
class ReplaySetup:
    """What to play and how: the sequence, the launch file and the replay's own settings."""

    sequence: Path
    launch: Path = DEFAULT_LAUNCH
    rate_hz: float = 0.5
    declared: bool = True
    timeout_s: float | None = None
    settle_s: float = 5.0
    health_timeout_s: float = 180.0
    in_process: bool = True
    out: Path = Path("bench_out/replay")
    perception: str | None = None
    """A key of :data:`PERCEPTIONS` for the mapper's segmenter + embedder; None: the launch file's."""


def declaration(seq: seqs.Sequence, declared: bool) -> PoseAccuracy | None:
    """The accuracy the frames declare: the sequence's stated one, else tracking grade (``bench.video``'s
    ``DECLARED_DEFAULT``, as ``argus bench geometry`` declares); None for ``--undeclared``."""
    from bench.video import DECLARED_DEFAULT

    if not declared:
        return None
    return seq.meta.declared() or DECLARED_DEFAULT


def accuracy_text(accuracy: PoseAccuracy | None) -> str:
    """``declared 5 mm / 0.05 deg`` or ``undeclared``."""
    return "undeclared" if accuracy is None else f"declared {1000 * accuracy.trans_m:g} mm / {accuracy.rot_deg:g} deg"


def check_perception(name: str | None) -> None:
    """Build the ``--perception`` choice's segmenter once (the detector loads its weights), so that a missing model
    is a one-line ``ValueError`` before any process starts; None (the launch file's) is not checked here."""
    if name is None:
        return
    if name not in PERCEPTIONS:
        raise ValueError(f"--perception {name!r}: one of {', '.join(PERCEPTIONS)}")
    from mapper.perception.registry import make_segmenter
    from mapper.perception.sam import BackendUnavailable

    try:
        make_segmenter(PERCEPTIONS[name]["segmenter"])
    except BackendUnavailable as e:
        raise ValueError(f"--perception {name}: {e}") from None


def replay_launch(launch_path: Path, sequence: Path, rate_hz: float, accuracy: PoseAccuracy | None, endpoint: str,
                  state_dir: Path, perception: str | None = None, world_from_recording: list[list[float]] | None = None,
                  intrinsics_file: str | None = None) -> tuple[Any, str, dict[str, Any]]:
    """The launch file's stack set up for this replay: on ``endpoint``, its camera playing ``sequence`` once at
    ``rate_hz`` declaring ``accuracy`` (None: nothing) with the sequence's ``world_from_recording`` (None: the
    poses as recorded) and ``intrinsics_file`` (None: the camera's default; a folder described by a sidecar has
    no meta.json the camera could read either from), its
    mapper saving to ``state_dir`` and, when ``perception`` names one of :data:`PERCEPTIONS`, segmenting and
    labelling with it (the launch file's backend options are kept where the backend is the same). Returns the
    launch, the camera's id and the mapper's settings; ``ValueError`` when the file is not a replay stack."""
    from deploy.up import load_launch

    launch = load_launch(launch_path)
    by_cmd: dict[str, list[Any]] = collections.defaultdict(list)
    for p in launch.process:
        by_cmd[p.command].append(p)
    if len(by_cmd["mapper"]) != 1 or len(by_cmd["edge-camera"]) != 1 or len(by_cmd["router"]) != 1:
        raise ValueError(f"{launch_path}: a replay stack is one router, one mapper and one edge-camera")
    procs = []
    for p in launch.process:
        if p.command in ("mapper", "edge-camera") and p.settings is None:
            raise ValueError(f"{launch_path}: process {p.name!r} needs inline [process.settings]")
        settings = dict(p.settings) if p.settings is not None else None
        if p.command == "mapper" and settings is not None:
            settings["state_dir"] = str(state_dir)
            if perception is not None:
                settings["perception"] = perception_settings(dict(settings.get("perception", {})), perception)
        if p.command == "edge-camera" and settings is not None:
            source = {k: v for k, v in dict(settings.get("source", {})).items()
                      if k not in ("pose_sigma_trans_m", "pose_sigma_rot_deg", "start", "stop", "world_from_recording",
                                   "intrinsics_file")}
            if source.get("type") != "recorded":
                raise ValueError(f"{launch_path}: the camera's source must be type = \"recorded\"")
            source.update(path=str(sequence.resolve()), rate_hz=rate_hz, loop=False)
            if accuracy is not None:
                source.update(pose_sigma_trans_m=accuracy.trans_m, pose_sigma_rot_deg=accuracy.rot_deg)
            if world_from_recording is not None:
                source.update(world_from_recording=world_from_recording)
            if intrinsics_file is not None:
                source.update(intrinsics_file=intrinsics_file)
            publish = dict(settings.get("publish", {}))
            publish["max_rate_hz"] = min(120.0, max(float(publish.get("max_rate_hz", 5.0)), 2.0 * rate_hz))
            settings.update(source=source, publish=publish)
        procs.append(p.model_copy(update={"settings": settings, "restart": "never"}))
    launch = launch.model_copy(update={"endpoint": endpoint, "process": procs})
    camera = by_cmd["edge-camera"][0]
    camera_id = str((camera.settings or {}).get("id", "cam0"))
    mapper_settings = dict(by_cmd["mapper"][0].settings or {})  # the file's, without this run's state_dir
    if perception is not None:  # the in-process comparison maps with what the stack's mapper got
        mapper_settings["perception"] = perception_settings(dict(mapper_settings.get("perception", {})), perception)
    return launch, camera_id, mapper_settings


def perception_settings(current: dict[str, Any], name: str) -> dict[str, Any]:
    """The mapper's ``perception`` table with the segmenter and embedder of :data:`PERCEPTIONS` ``[name]``; each
    backend's options from ``current`` stay when that backend is unchanged."""
    if name not in PERCEPTIONS:
        raise ValueError(f"--perception {name!r}: one of {', '.join(PERCEPTIONS)}")
    out = {k: v for k, v in current.items() if k not in ("segmenter", "embedder", "segmenter_options",
                                                          "embedder_options")}
    for kind, backend in PERCEPTIONS[name].items():
        out[kind] = backend
        if current.get(kind) == backend and f"{kind}_options" in current:
            out[f"{kind}_options"] = current[f"{kind}_options"]
    return out


def _failure(lines: Sequence[str], names: Sequence[str]) -> str:
    """The last two output lines of the named processes (their ``[name]`` prefix), for a one-line error."""
    own = [ln.split("] ", 1)[1].strip() for ln in lines if any(ln.startswith(f"[{n}] ") for n in names)]
    return " / ".join(t for t in own[-2:] if t) or "(no output)"


def _wait_workers(session: Any, keys: Any, timeout_s: float, stop: threading.Event) -> int:
    """Wait until a worker's liveliness token is up (the mapper's local worker); the number alive (0 at timeout)."""
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        alive = [r for r in session.liveliness().get(keys.all_alive_of("worker"), timeout=2.0) if r.ok is not None]
        if alive or time.monotonic() > deadline:
            return len(alive)
        stop.wait(0.5)
    return 0


def play(setup: ReplaySetup, frames: Sequence[RecordedFrame], accuracy: PoseAccuracy | None,
         stop: threading.Event | None = None, world_from_recording: list[list[float]] | None = None,
         intrinsics_file: str | None = None) -> MapResult:
    """Run the replay stack until the sequence was played and the graph settled; its map, nodes and figures."""
    from deploy.demo import free_endpoint
    from deploy.query import QueryError, get_snapshot
    from deploy.up import Stack
    from mapper.fusion import FusionConfig, ObjectMap
    from mapper.persistence import load_state
    from protocol.keys import Keys
    from protocol.session import ZenohSettings, open_session

    stop = stop or threading.Event()
    n_frames = len(frames)
    timeout_s = setup.timeout_s if setup.timeout_s is not None else n_frames / setup.rate_hz + 180.0
    state_tmp = Path(tempfile.mkdtemp(prefix="argus-replay-state-"))
    endpoint = free_endpoint()
    launch, camera_id, mapper_settings = replay_launch(setup.launch, setup.sequence, setup.rate_hz, accuracy,
                                                       endpoint, state_tmp, setup.perception, world_from_recording,
                                                       intrinsics_file)
    keys = Keys(launch.site)
    # The camera starts once the mapper and its worker are up, so that every frame meets the deployed mapper.
    core = launch.model_copy(update={"process": [p for p in launch.process if p.command != "edge-camera"]})
    cam = launch.model_copy(update={"process": [p for p in launch.process if p.command == "edge-camera"]})
    lines: collections.deque[str] = collections.deque(maxlen=500)

    def emit(line: str) -> None:
        lines.append(line)
        if "traceback" in line.lower() or " error" in line.lower():
            _log(line)

    logs = setup.out / "logs"
    stacks = [Stack(core, setup.launch.parent, emit=emit, log_dir=logs)]
    session = watch = None
    t0 = time.monotonic()
    try:
        _log(f"starting router + mapper on {endpoint} (site {launch.site}; logs in {logs}/)")
        stacks[0].start()
        if not stacks[0].wait_healthy(setup.health_timeout_s, stop):
            failed = stacks[0].failed
            if failed:
                raise RuntimeError(f"{', '.join(failed)} exited at start: {_failure(list(lines), failed)}")
            raise RuntimeError(f"not up after {setup.health_timeout_s:.0f}s: {', '.join(stacks[0].missing())} "
                               f"(logs in {logs}/)")
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        watch = StackWatch(session, keys, camera_id)
        workers = _wait_workers(session, keys, 60.0, stop)
        _log(f"mapper up after {time.monotonic() - t0:.0f}s with {workers} worker(s); camera {camera_id!r} plays "
             f"{n_frames} frames at {setup.rate_hz:g} Hz "
             f"({accuracy_text(accuracy)})")
        stacks.append(Stack(cam, setup.launch.parent, emit=emit, log_dir=logs))
        stacks[1].start()
        t_play = time.monotonic()
        deadline = t_play + timeout_s
        settled, last_progress = False, 0.0
        while not stop.is_set():
            for s in stacks:
                if not s.step():
                    raise RuntimeError(f"{', '.join(s.failed)} exited: {_failure(list(lines), s.failed)}")
            v = watch.view()
            now = time.monotonic()
            ended = len(v["frames"]) >= n_frames or "end of recording" in (v["camera_error"] or "")
            m = v["mapper"]
            idle = m.get("jobs_pending", 0.0) == 0 and m.get("jobs_in_flight", 0.0) == 0
            quiet = now - max(v["last_change_t"], v["last_frame_t"]) >= setup.settle_s
            if ended and idle and quiet and v["deltas"] > 0:
                settled = True
                break
            if ended and idle and quiet and now - v["last_frame_t"] >= 2 * setup.settle_s:
                settled = True  # played, idle and quiet, but no graph change at all (nothing mapped)
                break
            if now > deadline:
                _log(f"not settled after {timeout_s:.0f}s (--timeout-s): scoring what there is")
                break
            if now - last_progress >= 5.0:
                last_progress = now
                pm = v["point_map"]
                _log(f"{now - t_play:5.0f}s: frames {len(v['frames'])}/{n_frames} sent, keyframes "
                     f"{int(m.get('keyframes', 0))} (results {len(v['results'])}), graph v{v['version']}, "
                     f"map {0 if pm is None else len(pm.points)} points"
                     + (" | played, settling" if ended else ""))
            stop.wait(0.5)
        if stop.is_set():
            raise RuntimeError("interrupted")
        wall = time.monotonic() - t_play
        try:
            snap = get_snapshot(session, keys, timeout_s=10.0)
        except QueryError as e:
            snap = None
            _log(f"no graph snapshot: {e}")
        pm = _latest_point_map(session, keys) or watch.view()["point_map"]
        v = watch.view()
    finally:
        if watch is not None:
            watch.close()
        if session is not None:
            session.close()
        for s in reversed(stacks):  # the camera first, the router last; the mapper saves its state as it stops
            s.stop()
        state = load_state(state_tmp)
        shutil.rmtree(state_tmp, ignore_errors=True)
    clouds: dict[str, np.ndarray] = {}
    if state is not None:
        objects = ObjectMap(FusionConfig())
        objects.load_state(state["objects"])
        clouds = {nid: n.points for nid, n in objects.nodes.items()}
    nodes = [node_cloud(n, clouds.get(n.node_id)) for n in (snap.nodes if snap is not None else [])]
    index = frame_index_of(v["frames"], frames)
    mapped = {index[s]: T for s, T in v["results"].items() if s in index}
    from bench.system import drops_by_reason

    m = v["mapper"]
    lat_s = [x / 1000.0 for x in v["latencies_ms"]]
    figures: dict[str, Any] = {
        "settled": settled, "wall_s": wall, "graph_version": snap.version if snap is not None else v["version"],
        "deltas": v["deltas"], "frames_sent": len(v["frames"]), "frames_in_folder": n_frames,
        "camera_frames_dropped": v["camera"].get("frames_dropped", math.nan),
        "mapper_frames_in": m.get("frames_in", math.nan), "mapper_frames_dropped": m.get("frames_dropped", math.nan),
        "keyframes": m.get("keyframes", math.nan), "keyframes_dropped": m.get("keyframes_dropped", 0.0),
        **drops_by_reason({}, m), "keyframe_results_seen": len(v["results"]),
        "keyframes_done_locally": m.get("work_jobs_done_locally", 0.0),
        "keyframe_results_rejected": m.get("work_results_rejected", 0.0),
        "latency_n": len(lat_s), "latency_p50_s": _pct(lat_s, 50), "latency_p99_s": _pct(lat_s, 99),
        "latencies_s": lat_s, **split_first_keyframe(v["samples"], v["captured"]),
        "point_map_version": None if pm is None else pm.version,
        "mapper_status": m, "camera_status": v["camera"], "camera_id": camera_id, "endpoint": endpoint,
        "site": launch.site, "mapper_settings": mapper_settings,
    }
    points = np.zeros((0, 3)) if pm is None else np.asarray(pm.points, np.float64)
    counts = None if pm is None else np.asarray(pm.counts, np.int64)
    return MapResult(points, nodes, mapped, figures, counts)


def _latest_point_map(session: Any, keys: Any, timeout_s: float = 5.0) -> Any:
    """The mapper's newest point map (``map/points`` answers a get with its latest value), None without one."""
    from protocol.codec import DecodeError, decode
    from protocol.messages import PointMap

    best = None
    for reply in session.get(keys.map_points, timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            pm = decode(reply.ok.payload.to_bytes(), PointMap)
        except DecodeError:
            continue
        if best is None or pm.version > best.version:
            best = pm
    return best


# --- outputs -------------------------------------------------------------------------------------
def _fmt(v: Any, unit: str = "") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if unit == "cm":
        return f"{100 * v:.2f} cm"
    if unit == "%":
        return f"{100 * v:.1f} %"
    if unit == "s":
        return f"{v:.2f} s"
    if isinstance(v, float):
        return str(int(v)) if v == int(v) else f"{v:.3g}"
    return str(v)


def _bar(value: float, bar: float, higher: bool) -> str:
    if value is None or not math.isfinite(value):
        return "**miss** (no figure)"
    ok = value >= bar if higher else value <= bar
    return "met" if ok else "**miss**"


def summary_rows(res: dict[str, Any]) -> list[dict[str, str]]:
    """The Markdown table's rows: figure, replay (stack), in-process, bar, met."""
    r, i, f = res["replay"], res.get("in_process") or {}, res["figures"]
    counters = (res.get("in_process_run") or {}).get("counters", {})
    gap = (res.get("comparison") or {}).get("gap_max", math.nan)

    def pose(d: dict[str, Any]) -> str:
        return f"{_fmt(d.get('pose_trans_cm_median'))} cm / {_fmt(d.get('pose_rot_deg_median'))} deg" if d else "-"

    def bar(value: float, key: str, higher: bool) -> str:
        return _bar(value, BARS[key], higher)

    table: list[tuple[str, str, str, str, str]] = [
        ("map points (8 cm voxel means)", _fmt(r["map_points"]), _fmt(i.get("map_points")), "", ""),
        ("reference points (TSDF surface)", _fmt(r["reference_points"]), "", "", ""),
        ("accuracy, mean", _fmt(r["accuracy_mean_m"], "cm"), _fmt(i.get("accuracy_mean_m"), "cm"), "", ""),
        ("accuracy, median", _fmt(r["accuracy_median_m"], "cm"), _fmt(i.get("accuracy_median_m"), "cm"), "<= 3 cm",
         bar(r["accuracy_median_m"], "accuracy_median_m", False)),
        ("completion @ 5 cm", _fmt(r["completion_5cm"], "%"), _fmt(i.get("completion_5cm"), "%"), ">= 50 %",
         bar(r["completion_5cm"], "completion_5cm", True)),
        ("completion @ 10 cm", _fmt(r["completion_10cm"], "%"), _fmt(i.get("completion_10cm"), "%"), "", ""),
        (f"voxels seen by >= {CONFIRMED_VIEWS} keyframes: points", _fmt(r.get("confirmed_map_points")),
         _fmt(i.get("confirmed_map_points")), "", ""),
        (f"voxels seen by >= {CONFIRMED_VIEWS} keyframes: accuracy, median", _fmt(r.get("confirmed_accuracy_median_m"),
                                                                                   "cm"),
         _fmt(i.get("confirmed_accuracy_median_m"), "cm"), "", ""),
        (f"voxels seen by >= {CONFIRMED_VIEWS} keyframes: completion @ 5 cm", _fmt(r.get("confirmed_completion_5cm"),
                                                                                   "%"),
         _fmt(i.get("confirmed_completion_5cm"), "%"), "", ""),
        ("replay vs in-process, largest gap of the four above", _fmt(gap, "%"), "", "<= 10 %",
         bar(gap, "in_process_gap", False) if i else "(not run)"),
        ("nodes", _fmt(r["nodes"]), _fmt(i.get("nodes")), "", ""),
        ("node points within 10 cm (mean over nodes)", _fmt(r["node_points_within"], "%"),
         _fmt(i.get("node_points_within"), "%"), ">= 90 %", bar(r["node_points_within"], "node_points_within", True)),
        ("node points within 10 cm (all nodes' points)", _fmt(r["node_points_within_pooled"], "%"),
         _fmt(i.get("node_points_within_pooled"), "%"), "", ""),
        ("nodes with >= 90 % of their points within 10 cm", _fmt(r["nodes_90pct_within"], "%"),
         _fmt(i.get("nodes_90pct_within"), "%"), "", ""),
        (f"same-label node pairs < 0.5 m apart (over {r.get('duplicates_over', 'all nodes')})",
         _fmt(r["duplicates"]), _fmt(i.get("duplicates")), "", ""),
        ("capture -> graph latency p50", _fmt(f.get("latency_p50_s"), "s"), "", "", ""),
        ("capture -> graph latency p99", _fmt(f.get("latency_p99_s"), "s"), "", "<= 2 s",
         bar(f.get("latency_p99_s", math.nan), "latency_p99_s", False)),
        ("  the same, p50 / p99 without the first keyframe",
         f"{_fmt(f.get('latency_rest_p50_s'), 's')} / {_fmt(f.get('latency_rest_p99_s'), 's')}", "", "<= 2 s",
         bar(f.get("latency_rest_p99_s", math.nan), "latency_p99_s", False)),
        ("  the first keyframe: latency / its wait for a second view",
         f"{'/'.join(_fmt(x, 's') for x in f.get('latency_first_s', [])) or '-'} / "
         f"{_fmt(f.get('first_keyframe_wait_s'), 's')}", "", "", ""),
        ("frames sent / in the folder", f"{f.get('frames_sent')} / {f.get('frames_in_folder')}", "", "", ""),
        ("frames dropped (mapper)", _fmt(f.get("mapper_frames_dropped")), "", "", ""),
        ("keyframes selected (mapper)", _fmt(f.get("keyframes")), _fmt(counters.get("keyframes")), "", ""),
        ("keyframes dropped (mapper; stale / superseded / full)", _fmt(f.get("keyframes_dropped")), "", "", ""),
        ("keyframes mapped with a known pose", _fmt(r["keyframes"]), _fmt(i.get("keyframes")), "", ""),
        ("keyframe pose vs recorded, median", pose(r), pose(i), "", ""),
    ]
    return [{"figure": a, "replay (stack)": b, "in-process": c if i else "-", "bar": d, "met": e}
            for a, b, c, d, e in table]


def numbered_nodes(nodes: Sequence[NodeCloud]) -> list[NodeCloud]:
    """The nodes the top-down view numbers and lists in its legend, in legend order: the labelled ones when any
    node has a real class (by label, then most points first), else every node (most points first)."""
    def n_points(n: NodeCloud) -> int:
        return 0 if n.points is None else len(n.points)

    if has_labels(nodes):
        return sorted((n for n in nodes if n.label != UNLABELLED), key=lambda n: (n.label, -n_points(n), n.node_id))
    return sorted(nodes, key=lambda n: (-n_points(n), n.node_id))


def spread_labels(anchors: np.ndarray, min_sep: float, max_rings: int = 6) -> np.ndarray:
    """Text positions (N, 2) for markers at ``anchors`` (N, 2), greedily in order: each at its anchor when no
    earlier one lies within ``min_sep``, else on the nearest free point of rings of 8 directions ``min_sep``
    apart around it (the last ring's first point when all are taken)."""
    a = np.asarray(anchors, float).reshape(-1, 2)
    placed: list[np.ndarray] = []
    dirs = [np.array([math.cos(t), math.sin(t)]) for t in np.arange(8) * math.pi / 4]
    for p in a:
        candidates = [p] + [p + k * min_sep * d for k in range(1, max_rings + 1) for d in dirs]
        pick = next((c for c in candidates if all(np.linalg.norm(c - q) >= min_sep for q in placed)), candidates[-8])
        placed.append(pick)
    return np.array(placed).reshape(-1, 2)


def plot_top_down(path: Path, reference: np.ndarray, ref_colors: np.ndarray, map_points: np.ndarray,
                  nodes: Sequence[NodeCloud], up: tuple[int, int], title: str, max_listed: int = 40) -> None:
    """Reference points seen from above (the two axes other than ``up``), the map's points and each node's box
    outline (convex hull of its projected corners). The nodes of :func:`numbered_nodes` carry a number (moved
    off its neighbours, with a leader line) and are listed beside the map: number, label, confidence, id,
    points (at most ``max_listed``); with real labels each label has its own colour and the class-agnostic
    ``object`` boxes are thin grey outlines without a number."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import ConvexHull, QhullError

    ax0, ax1 = [a for a in range(3) if a != up[0]]
    names = "xyz"
    fig, (ax, lx) = plt.subplots(1, 2, figsize=(14, 9), gridspec_kw={"width_ratios": [3, 1.25]})
    rng = np.random.default_rng(0)
    if len(reference):
        pick = rng.choice(len(reference), min(len(reference), 150_000), replace=False)
        order = pick[np.argsort(up[1] * reference[pick, up[0]])]  # the highest drawn last (on top)
        ax.scatter(reference[order, ax0], reference[order, ax1], c=ref_colors[order] / 255.0, s=1.5, linewidths=0,
                   rasterized=True)
    if len(map_points):
        ax.scatter(map_points[:, ax0], map_points[:, ax1], c="tab:red", s=2, linewidths=0, alpha=0.5,
                   label="map points (replay)")
    labelled = has_labels(nodes)
    numbered = numbered_nodes(nodes)
    palette = plt.get_cmap("tab10" if len({n.label for n in numbered}) <= 10 else "tab20")
    colour = {lab: palette(k % palette.N) for k, lab in enumerate(dict.fromkeys(n.label for n in numbered))}

    def hull_of(n: NodeCloud) -> np.ndarray:
        xy = n.corners[:, [ax0, ax1]]
        try:
            return np.asarray(xy[ConvexHull(xy).vertices])
        except (QhullError, ValueError):  # a flat box: its outline is a segment
            return np.asarray(xy[[int(np.argmin(xy[:, 0])), int(np.argmax(xy[:, 0]))]])

    ids = {n.node_id for n in numbered}
    for n in nodes:
        if n.node_id not in ids:
            h = hull_of(n)
            ax.fill(h[:, 0], h[:, 1], fill=False, edgecolor="0.45", linewidth=0.7, linestyle="--")
    for n in numbered:
        h = hull_of(n)
        ax.fill(h[:, 0], h[:, 1], fill=False, edgecolor=colour[n.label], linewidth=2.0)
    if numbered:
        anchors = np.array([box_center(n)[[ax0, ax1]] for n in numbered])
        lo, hi = ax.get_xlim(), ax.get_ylim()
        span = max(hi[1] - hi[0], lo[1] - lo[0], 1e-6)
        spots = spread_labels(anchors, 0.035 * span)
        for k, (n, a, t) in enumerate(zip(numbered, anchors, spots, strict=True), start=1):
            if np.linalg.norm(t - a) > 0:
                ax.plot([a[0], t[0]], [a[1], t[1]], color=colour[n.label], linewidth=0.8)
            ax.text(float(t[0]), float(t[1]), str(k), fontsize=10, fontweight="bold", ha="center", va="center",
                    color="black", bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": colour[n.label],
                                         "lw": 1.5, "alpha": 0.9})
    ax.set_xlabel(f"world {names[ax0]} (m)")
    ax.set_ylabel(f"world {names[ax1]} (m)")
    ax.set_aspect("equal")
    ax.set_title("\n".join(textwrap.wrap(title, 90)), fontsize=10)
    if len(map_points):
        ax.legend(loc="upper right", fontsize=8)
    lx.axis("off")
    head = ("labelled nodes" if labelled else "nodes (class-agnostic, every one 'object')")
    lines: list[tuple[str, Any, str]] = [(f"#  {head}", "black", "bold")]
    lines += [(f"{k:>2}  {n.label[:18]:<18} {n.label_confidence:4.2f}  {n.node_id[:10]:<10} "
               f"{0 if n.points is None else len(n.points):>5} pts", colour[n.label], "normal")
              for k, n in enumerate(numbered[:max_listed], start=1)]
    if len(numbered) > max_listed:
        lines.append((f"+ {len(numbered) - max_listed} more (replay.md)", "black", "normal"))
    if labelled and len(nodes) > len(numbered):
        lines.append((f"grey dashed: {len(nodes) - len(numbered)} class-agnostic", "0.35", "normal"))
        lines.append(("'object' nodes (geometry only)", "0.35", "normal"))
    if not numbered:
        lines.append(("no nodes", "black", "normal"))
    for i, (text, c, weight) in enumerate(lines):
        lx.text(0.0, 1.0 - i * 0.024, text, transform=lx.transAxes, fontsize=9, family="monospace", color=c,
                fontweight=weight, va="top")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_rerun(path: Path, reference: np.ndarray, ref_colors: np.ndarray, replay: MapResult,
                in_process: MapResult | None, up: tuple[int, int], voxel_m: float) -> bool:
    """A Rerun recording of the reference, both maps, the nodes' boxes and the keyframes' camera positions; False
    (with a message) when ``rerun`` is not importable."""
    try:
        import rerun as rr
    except ImportError:
        _log("rerun is not installed: no .rrd written (pip install rerun-sdk)")
        return False
    view = getattr(rr.ViewCoordinates, f"RIGHT_HAND_{'XYZ'[up[0]]}_{'UP' if up[1] > 0 else 'DOWN'}")
    rec = rr.RecordingStream(application_id="argus-bench-replay")
    rec.save(str(path))
    rec.log("world", view, static=True)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(reference), min(len(reference), 300_000), replace=False)
    rec.log("world/reference", rr.Points3D(reference[pick], colors=ref_colors[pick], radii=voxel_m / 2), static=True)
    runs = [("replay", replay, (230, 60, 60))] + ([("in_process", in_process, (60, 120, 230))] if in_process else [])
    for name, res, color in runs:
        rec.log(f"world/{name}/map", rr.Points3D(res.points, colors=[color], radii=0.02), static=True)
        if res.keyframe_poses:
            rec.log(f"world/{name}/keyframes", rr.Points3D([T[:3, 3] for T in res.keyframe_poses.values()],
                                                            colors=[color], radii=0.03), static=True)
        if res.nodes:
            centers = [box_center(n) for n in res.nodes]
            rec.log(f"world/{name}/nodes", rr.Boxes3D(
                centers=centers,
                sizes=[box_size(n) for n in res.nodes],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), angle=_box_yaw(n)) for n in res.nodes],
                labels=[f"{n.label} {n.node_id}" for n in res.nodes], colors=[color]), static=True)
    rec.flush()
    rec.disconnect()
    return True


def _box_yaw(n: NodeCloud) -> float:
    edge = n.corners[4] - n.corners[0]  # corner 0 -> 4 runs along the box's x axis (box_corners' order)
    return math.atan2(edge[1], edge[0])


def scored(result: MapResult, reference: np.ndarray, recorded: dict[int, np.ndarray]
           ) -> tuple[dict[str, Any], list[dict[str, Any]], list[dict[str, Any]]]:
    """A run's map, node and keyframe-pose figures against the reference; its per-node rows; its duplicates."""
    tree = surface_tree(reference)
    figs: dict[str, Any] = dict(map_scores(result.points, reference, reference_tree=tree))
    cams = np.stack([T[:3, 3] for T in recorded.values()]) if recorded else np.zeros((0, 3))
    figs["accuracy_by_range"] = accuracy_by_range(result.points, nearest_m(result.points, tree), cams)
    if result.counts is not None and len(result.counts) == len(result.points):
        # The map as a consumer that trusts only voxels several keyframes agree on reads it (PointMap.counts).
        seen = result.points[result.counts >= CONFIRMED_VIEWS]
        figs.update({f"confirmed_{k}": v for k, v in map_scores(seen, reference, reference_tree=tree).items()})
    rows, summary = node_scores(result.nodes, tree)
    figs.update(summary)
    dups, over = label_duplicates(result.nodes)
    figs["duplicates"] = float(len(dups))
    figs["duplicates_over"] = over
    figs["labelled_nodes"] = float(sum(n.label != UNLABELLED for n in result.nodes))
    figs["labels"] = labels_count(result.nodes)
    pe = pose_errors(recorded, result.keyframe_poses)
    figs.update(keyframes=float(pe["n"]), pose_trans_cm_median=pe["trans_cm_median"],
                pose_trans_cm_max=pe["trans_cm_max"], pose_rot_deg_median=pe["rot_deg_median"],
                pose_rot_deg_max=pe["rot_deg_max"], keyframe_poses=pe["keyframes"])
    return figs, rows, dups


def load_checked(setup: ReplaySetup) -> seqs.Sequence:
    """The sequence, read for the reference and checked for what the recorded camera needs; one-line
    :class:`SequenceError` naming the file otherwise."""
    seq = seqs.load(setup.sequence)
    own_meta = seqs.meta_path(setup.sequence)
    if not setup.declared and own_meta == setup.sequence / "meta.json" and seq.meta.declared() is not None:
        raise SequenceError(f"{own_meta}: declares a pose accuracy, which the recorded camera always sends: "
                            "--undeclared cannot replay it undeclared")
    return seq


def run(setup: ReplaySetup, stop: threading.Event | None = None, seq: seqs.Sequence | None = None) -> dict[str, Any]:
    """The whole benchmark: play, map in-process, build the reference, score, write the outputs; the results.
    Raises :class:`SequenceError` for a folder that cannot be read (``seq``: already read by :func:`load_checked`),
    ``ValueError`` for a launch file that is no replay stack and ``RuntimeError`` for a stack that fails."""
    from bench.report import write_report

    seq = seq if seq is not None else load_checked(setup)
    accuracy = declaration(seq, setup.declared)
    frames = seq.frames
    setup.out.mkdir(parents=True, exist_ok=True)
    _log(f"{seq.name}: {len(frames)} frames, {frames[0].rgb.shape[1]}x{frames[0].rgb.shape[0]}; pose accuracy "
         f"{accuracy_text(accuracy)}")
    replay = play(setup, frames, accuracy, stop, seq.meta.world_from_recording, seq.meta.intrinsics_file)
    _log(f"replay: {len(replay.points)} map points, {len(replay.nodes)} nodes, "
         f"{replay.figures['keyframe_results_seen']} keyframe results seen; settled: {replay.figures['settled']}")
    inproc = None
    if setup.in_process and not (stop is not None and stop.is_set()):
        _log("the same frames through an in-process MapperCore")
        inproc = map_in_process(frames, accuracy, replay.figures["mapper_settings"], rate_hz=setup.rate_hz)
    voxel_m = reference_voxel_m(frames)
    _log(f"reference: TSDF of the recorded depth, voxel {voxel_m * 100:.1f} cm, truncation {4 * voxel_m * 100:.1f} cm")
    reference, ref_colors = reference_surface(frames, voxel_m)
    recorded = {f.index: f.T_world_cam for f in frames}
    up = up_axis([f.T_world_cam for f in frames])
    r_figs, r_nodes, r_dups = scored(replay, reference, recorded)
    results: dict[str, Any] = {
        "sequence": seq.name, "folder": str(setup.sequence.resolve()), "frames": len(frames),
        "rate_hz": setup.rate_hz, "declared": None if accuracy is None else {"trans_m": accuracy.trans_m,
                                                                            "rot_deg": accuracy.rot_deg},
        "launch": str(setup.launch), "perception": replay.figures["mapper_settings"].get("perception", "default"),
        "perception_option": setup.perception,
        "geometry": replay.figures["mapper_settings"].get("geometry", "default"),
        "reference": {"voxel_m": voxel_m, "sdf_trunc_m": 4 * voxel_m, "points": len(reference),
                      "valid_depth_m": list(seq.meta.valid_depth_m)},
        "top_down": {"up_axis": "xyz"[up[0]], "up_sign": up[1]},
        "figures": replay.figures, "replay": r_figs, "replay_nodes": r_nodes, "replay_duplicates": r_dups,
    }
    if inproc is not None:
        i_figs, i_nodes, i_dups = scored(inproc, reference, recorded)
        results.update(in_process=i_figs, in_process_nodes=i_nodes, in_process_duplicates=i_dups,
                       in_process_run=inproc.figures, comparison=compare(r_figs, i_figs))
    rows = summary_rows(results)
    title = f"argus bench replay: {seq.name} through router, mapper + worker and edge camera"
    _, md = write_report(setup.out, "replay", results, rows, title)
    _append_notes(md, results, up)
    png = setup.out / "replay.png"
    plot_top_down(png, reference, ref_colors, replay.points, replay.nodes, up,
                  f"{seq.name}: reference (recorded depth, TSDF) seen along world {'xyz'[up[0]]} (up: opposite the "
                  f"cameras' mean image-down direction), map points, node boxes")
    rrd = setup.out / "replay.rrd"
    wrote = write_rerun(rrd, reference, ref_colors, replay, inproc, up, voxel_m)
    _log(f"wrote {setup.out / 'replay.json'}, {md}, {png}" + (f", {rrd}" if wrote else ""))
    for r in rows:
        _log(f"{r['figure']}: {r['replay (stack)']}" + (f" (in-process {r['in-process']})" if r["in-process"] else "")
             + (f" [{r['bar']}: {r['met']}]" if r["bar"] else ""))
    return results


def _append_notes(md: Path, res: dict[str, Any], up: tuple[int, int]) -> None:
    from bench.report import markdown_table

    f, r = res["figures"], res["replay"]
    decl = res["declared"]
    notes = [
        f"Sequence `{res['folder']}`, {res['frames']} frames played once at {res['rate_hz']:g} Hz; pose accuracy "
        + (f"declared ({decl['trans_m']} m, {decl['rot_deg']} deg per axis)." if decl else "undeclared."),
        f"Mapper: geometry {res['geometry']}, 2D perception {perception_text(res['perception'])} (launch file "
        f"`{res['launch']}`" + (f", `--perception {res['perception_option']}`" if res.get("perception_option") else "")
        + "); "
        f"settled: {f['settled']} after {f['wall_s']:.0f} s of playing; graph version {f['graph_version']}.",
        f"Reference: TSDF of the recorded depth inside {res['reference']['valid_depth_m']} m with the recorded poses, "
        f"voxel {100 * res['reference']['voxel_m']:.1f} cm, {res['reference']['points']} surface points. The map is "
        "the mapper's published point map (one mean point per 8 cm voxel, so completion within 5 cm is bounded "
        "below 100 % even for a perfect map).",
        "Node points: each node's fused points from the mapper's saved state (box corners and centroid for "
        f"{int(r.get('nodes_scored_by_box', 0))} node(s) without them). Keyframe poses: the worker's results "
        f"(`work/result`), {f['keyframe_results_seen']} seen ({int(f['keyframe_results_rejected'])} results rejected "
        f"by the mapper); keyframes done in the mapper itself ({int(f['keyframes_done_locally'])}) are not on the "
        "wire.",
        labels_note(res),
        f"Top-down view: world {'xyz'[up[0]]} taken as up (the axis nearest to the opposite of the cameras' mean "
        "image-down direction).",
    ]
    text = ["", *(f"- {n}" for n in notes if n), "", "## Nodes per label (replay)", "",
            markdown_table([{"label": k, "nodes": v} for k, v in r["labels"].items()])]
    if res["replay_duplicates"]:
        text += ["## Same-label pairs under 0.5 m (replay)", "", markdown_table(res["replay_duplicates"][:30])]
    text += ["## Accuracy by distance from the nearest camera (replay)", "",
             markdown_table([{"range (m)": b["range_m"], "map points": b["points"],
                              "median accuracy": _fmt(b["accuracy_median_m"], "cm")} for b in r["accuracy_by_range"]])]
    text += ["## Nodes (replay)", "",
             "Labelled nodes first, then by points. `judged on`: a class-agnostic `object` node is scored by "
             "geometry only (its points against the reference), a labelled one also by its class (judge it on "
             "`replay.png` and the frames). `within`: share of its points within 10 cm of the reference.", "",
             markdown_table(node_table(res["replay_nodes"])[:60])]
    with md.open("a") as fh:
        fh.write("\n".join(text) + "\n")


def perception_text(perception: Any) -> str:
    """``segmenter / embedder`` of a mapper's ``perception`` settings (the default when it has none)."""
    if not isinstance(perception, dict):
        return str(perception)
    seg, emb = perception.get("segmenter", "classical"), perception.get("embedder", "classical")
    return seg if seg == emb else f"{seg} / {emb}"


def labels_note(res: dict[str, Any]) -> str:
    """What the labels of a run mean for its scores: class-agnostic (every pair under 0.5 m counts), real classes
    (pairs among the labelled nodes only), or a closed-set perception that found none of its classes."""
    r = res["replay"]
    seg = res["perception"].get("segmenter", "classical") if isinstance(res["perception"], dict) else ""
    if r["labelled_nodes"] > 0:
        return (f"Labels: {int(r['labelled_nodes'])} of {int(r['nodes'])} nodes carry a class; same-label pairs are "
                f"counted over those only, the class-agnostic `{UNLABELLED}` nodes are scored by geometry only.")
    if seg == "detector":
        return (f"Labels: the detector saw nothing it knows (none of its classes in any keyframe, or no labelled "
                f"node kept): every node is `{UNLABELLED}`, scored by geometry only; same-label pairs count every "
                "pair under 0.5 m apart.")
    return (f"Labels: {seg or 'this'} 2D perception labels every node `{UNLABELLED}` (class-agnostic, scored by "
            "geometry only), so 'same-label pairs' counts every pair of nodes under 0.5 m apart, duplicates or "
            "neighbours.")


def _conf(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.2f}"


def node_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, str]]:
    """The per-node Markdown rows: labelled nodes first (most points first), then the class-agnostic ones."""
    def xyz(v: Sequence[float]) -> str:
        return ", ".join(f"{x:.2f}" for x in v)

    ordered = sorted(rows, key=lambda r: (r["label"] == UNLABELLED, r["label"], -r["points"]))
    return [{"node": r["node_id"], "label": r["label"], "confidence": _conf(r.get("label_confidence", math.nan)),
             "judged on": r.get("judged_on", "geometry only"), "box centre (m)": xyz(r.get("box_center_m", [])),
             "box size (m)": xyz(r.get("box_size_m", [])), "points": str(r["points"]),
             "within 10 cm": _fmt(r["within"], "%"), "scored by": r["scored_by"]} for r in ordered]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench replay",
        description="Replay a recorded sequence folder through edge camera, router, mapper and its worker (separate "
        "processes on loopback) and score the map against the sequence's own depth; also the same frames "
        "through an in-process mapper for comparison.",
        epilog="example: argus bench replay --sequence ../shared/data/apc-shelf --out bench_out/replay/apc-shelf",
    )
    p.add_argument("--sequence", type=Path, required=True,
                   help="sequence folder: frames/frame-NNNNNN.{color.png,depth.png,pose.txt}, camera-intrinsics.txt, "
                   "meta.json (or bench/sequence_meta/<name>.json)")
    p.add_argument("--rate", type=float, default=0.5,
                   help="frames per second the camera plays (default 0.5: the mapper keeps up on two CPU cores)")
    decl = p.add_mutually_exclusive_group()
    decl.add_argument("--declared", dest="declared", action="store_true", default=True,
                      help="frames declare the sequence's stated pose accuracy, else tracking grade "
                      "(5 mm, 0.05 deg) (default)")
    decl.add_argument("--undeclared", dest="declared", action="store_false",
                      help="frames declare no pose accuracy: the mapper judges the poses from the images")
    p.add_argument("--out", type=Path, default=Path("bench_out/replay"), help="output folder")
    p.add_argument("--timeout-s", type=float, default=None,
                   help="longest wait for the sequence to play and the graph to settle (default: frames / rate + 180)")
    p.add_argument("--settle-s", type=float, default=5.0, help="the graph has settled after this long without a change")
    p.add_argument("--launch", type=Path, default=DEFAULT_LAUNCH,
                   help="launch file of the stack (one router, one mapper, one edge-camera with a recorded source)")
    p.add_argument("--no-in-process", dest="in_process", action="store_false",
                   help="skip the in-process comparison run")
    p.add_argument("--perception", choices=sorted(PERCEPTIONS), default=None,
                   help="the mapper's 2D segmenter + embedder: classical (class-agnostic 'object' nodes, no weights) "
                   "or detector (the bundled offline SSD, 24 classes; weights from make install); default: the "
                   "launch file's (classical in deploy/launch/replay.toml)")
    a = p.parse_args(argv)
    if a.rate <= 0:
        p.error("--rate must be > 0")
    from protocol.runtime import install_stop_handlers

    setup = ReplaySetup(sequence=a.sequence, launch=a.launch, rate_hz=a.rate, declared=a.declared,
                        timeout_s=a.timeout_s, settle_s=a.settle_s, in_process=a.in_process, out=a.out,
                        perception=a.perception)
    try:
        check_perception(setup.perception)
        seq = load_checked(setup)
        run(setup, install_stop_handlers(), seq)
    except (SequenceError, ValueError, RuntimeError) as e:
        print(f"argus bench replay: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
