"""``MapperCore``: the in-process mapping pipeline, with no Zenoh.

``ingest(view)`` runs keyframe selection, geometry on a window of views (the new keyframe plus its best
neighbour keyframes), 2D perception, 3D fusion and relation edges, and returns the resulting
:class:`GraphDelta` (or None when the view was not a keyframe or changed nothing). ``argus mapper``
(mapper/node.py) wraps it; benchmarks and the closed-loop explorer use it directly.

Thread safety: one thread calls ``ingest``; ``snapshot``, ``query``, ``point_map`` and ``state`` may be
called from other threads (they take the graph lock, which ``ingest`` holds only while committing).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import cv2
import numpy as np

from mapper.association import KeyframeView
from mapper.changemask import ChangeMask, Changes
from mapper.config import MapperCoreConfig
from mapper.consistency import downsample, verify_depth
from mapper.fusion import (
    LiftStats,
    Object3D,
    ObjectMap,
    UpdateResult,
    lift_detections,
    outside_fraction,
    resize_mask,
)
from mapper.geometry.background import behind_background
from mapper.geometry.contract import Reconstructor, View
from mapper.geometry.features import Features, LruCache, extract_features
from mapper.geometry.mvs import one_blas_thread
from mapper.geometry.posecheck import rotation_between
from mapper.geometry.singleview import PlacedBox, SeenView, depth_to_world, layout_depth, place_objects
from mapper.geometry.support import MappedTop, place_on_mapped_support, place_on_measured_support
from mapper.graph_store import GraphStore
from mapper.intake import view_problem
from mapper.keyframes import KeyframeSelector, KeyframeStore, intrinsics_of
from mapper.perception.base import Detection, Embedder, Mask2D, Segmenter, ViewGeometry
from mapper.perception.occluded import join_split_by_people
from mapper.pointmap import VoxelMap
from mapper.posegraph import Key, LoopCloser, node_move
from mapper.relations import EdgeCache, compute_edges, refine_with_points
from mapper.rooms import RoomLayer, RoomMapper, RoomParams, room_message
from mapper.work.compute import KeyframeProducts, compute_keyframe
from mapper.work.latency import StageTimes
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, NodeMove, PointMap, RetiredNode
from protocol.query import GraphQuery
from protocol.ratelog import RateLimitedLog
from protocol.rooms import RoomLayer as RoomLayerMessage

log = logging.getLogger(__name__)

STATE_FORMAT = 1


@dataclass
class KeyframeResult:
    """What the last keyframe did (for logs, Rerun and benchmarks)."""

    view: View
    T_world_cam: np.ndarray
    geometry: ViewGeometry
    n_detections: int
    lift: LiftStats
    timings_s: dict[str, float] = field(default_factory=dict)


def _room_mapper(cfg: MapperCoreConfig) -> RoomMapper:
    from protocol.prior import load_prior

    r = cfg.rooms
    params = RoomParams(**{f: getattr(r, f) for f in RoomParams.__dataclass_fields__})
    return RoomMapper(params, load_prior(r.prior), r.max_cameras)


def typical_depth(depth_m: np.ndarray, confidence: np.ndarray, min_pixels: int = 50) -> float | None:
    """Median confident depth of a view (None when too few pixels are confident): the scale that parallax
    thresholds and source selection are measured against."""
    ok = (confidence >= 0.5) & np.isfinite(depth_m) & (depth_m > 0)
    return float(np.median(depth_m[ok])) if int(ok.sum()) >= min_pixels else None


class MapperCore:
    """Keyframes -> geometry -> perception -> fusion -> edges -> versioned graph."""

    def __init__(
        self,
        config: MapperCoreConfig | None = None,
        reconstructor: Reconstructor | None = None,
        segmenter: Segmenter | None = None,
        embedder: Embedder | None = None,
    ) -> None:
        self.config = cfg = config or MapperCoreConfig()
        if reconstructor is None:
            from mapper.geometry.registry import make_reconstructor

            reconstructor = make_reconstructor(cfg.geometry.backend, cfg.geometry.options)
        if segmenter is None or embedder is None:
            from mapper.perception.registry import make_embedder, make_segmenter

            segmenter = segmenter or make_segmenter(cfg.perception.segmenter, cfg.perception.segmenter_options)
            embedder = embedder or make_embedder(cfg.perception.embedder, cfg.perception.embedder_options)
        self.reconstructor, self.segmenter, self.embedder = reconstructor, segmenter, embedder
        self.objects = ObjectMap(cfg.fusion)
        self.store = GraphStore(max_retired=cfg.max_retired, retired_keep_s=cfg.retired_keep_s)
        self.voxels = VoxelMap(cfg.point_map.voxel_m, cfg.point_map.max_voxels)
        self.rooms = _room_mapper(cfg) if cfg.rooms.enabled else None
        self._rooms_lock = threading.RLock()
        self._room_message: RoomLayerMessage | None = None
        self._rooms_built_at_keyframe = 0.0
        self.selector = KeyframeSelector(cfg.keyframes)
        self.keyframes = KeyframeStore(cfg.keyframes)
        self.lock = threading.RLock()
        self.counters: dict[str, float] = {}
        self.last: KeyframeResult | None = None
        self.update_times_s: list[float] = []
        # Called before every commit with the version it may create and the next node id number; the mapper
        # process persists a lease covering both there (mapper.persistence), before anyone can see them.
        self.reserve: Callable[[int, int], None] | None = None
        # Keyframes that had no neighbour to reconstruct with (a fixed camera's first frame before any robot
        # view): retried, one per later keyframe, once neighbours exist. Bounded.
        self._deferred: collections.deque[View] = collections.deque(maxlen=cfg.keyframes.max_deferred)
        # What each calibrated camera saw at its last single-view keyframe (free-space checks), oldest first.
        self._seen = LruCache(cfg.keyframes.max_keyframes)  # source id -> SeenView
        # Each calibrated camera's first keyframe's features: a later one that turned away flags the camera.
        self._pose_refs = LruCache(cfg.keyframes.max_keyframes)  # source id -> Features
        self._failed_key: tuple[str, int] | None = None  # the last view whose processing raised
        # Given the keyframe, its window and the target's index there, sends its heavy work elsewhere (a worker)
        # and returns True; :meth:`complete` then finishes it. None or False: the work is done here.
        self.offload: Callable[[View, list[View], int], bool] | None = None
        self._offloaded_key: tuple[str, int] | None = None  # the last view whose work was offloaded
        self._bad_input = RateLimitedLog(log)
        self._edges = EdgeCache()  # relations of node pairs whose boxes did not change are not recomputed
        # Loop closure of moving sources' odometry, and which of their keyframes each node was fused from (the
        # last few: a node follows them when a loop moves them).
        self.loops = LoopCloser(cfg.pose_graph) if cfg.pose_graph.enabled else None
        self._fused_from: dict[str, list[Key]] = {}
        self.stages = StageTimes()  # where keyframes' capture-to-graph time goes (status: kf_s.*)
        self._retried: collections.deque[tuple[str, int]] = collections.deque(maxlen=16)  # deferred, retried
        # Calibrated fixed cameras whose last keyframe saw a node's place empty: source -> that keyframe's stamp.
        # Their next frame absence_confirm_s later is a keyframe too (they keyframe only on image change).
        # Also when its measured keyframe made a node: seen once, a small one would be pruned as a stray.
        self._confirm: dict[str, tuple[int, str]] = {}  # source -> (stamp, "absence" or "new")
        # Each calibrated camera's view with people left out: what changed since (single_view.changed_only).
        kc = cfg.keyframes
        self._changes = ChangeMask(static_max_m=kc.static_max_m, static_max_deg=kc.static_max_deg)

    def views_to_keep(self) -> list[View]:
        """Every view a later window or retry may still use: the stored keyframes and recent frames, and the
        deferred keyframes (retried once they have neighbours, even after the store let them go). A worker
        job needs their JPEGs (``mapper.work.offload.Offloader.prune``)."""
        kept = self.keyframes.views()
        keys = {v.key for v in kept}
        return kept + [v for v in self._deferred if v.key not in keys]

    def _count(self, name: str, value: float = 1.0) -> None:
        self.counters[name] = self.counters.get(name, 0.0) + value

    # -- pipeline --------------------------------------------------------------------------------
    def ingest(self, view: View, force_keyframe: bool = False) -> GraphDelta | None:
        """Process one view; returns the graph delta it caused, if any. Bad views are counted, not raised.

        A physically impossible view (``config.limits``: absurd intrinsics, a camera outside the site's box,
        too many pixels) is refused first, counted under its reason and ``views_refused``."""
        self._count("views_in")
        problem = view_problem(view, self.config.limits)
        if problem is not None:
            reason, detail = problem
            self._count(reason)
            self._count("views_refused")
            self._failed_key = view.key
            self._bad_input.warning(reason, "refused a view from %s#%d: %s", view.source_id, view.seq, detail)
            return None
        if not (self.selector.consider(view) or force_keyframe or self._confirm_due(view)):
            self._count("views_not_keyframe")
            self.keyframes.note_frame(self._corrected(view))
            return None
        self._count("keyframes")
        self.stages.age("age_at_ingest", view.stamp_ns, time.time_ns())
        moved: set[str] = set()
        if self.loops is not None and self._drifts(view):
            view, moved = self._close_loops(view)
        results = [r for r in [self._timed(view)] if r is not None]
        if moved:
            results.append(UpdateResult(changed=moved))
        delta = self._finish(view, results)
        every = self.config.rooms.every_keyframes
        if self.rooms is not None and every and self.counters["keyframes"] - self._rooms_built_at_keyframe >= every:
            # Rooms follow the map as it grows (ids are carried over between builds, the closer the better);
            # a query between builds rebuilds them itself. A changed layer goes out in the graph: in this
            # keyframe's delta, or in a delta of its own.
            t = time.perf_counter()
            self.update_rooms()
            with self._rooms_lock:
                layer = self._room_message
            if layer is not None:
                with self.lock:
                    delta = self.store.commit_rooms(layer, layer.stamp_ns, delta)
            self.stages.add("rooms", time.perf_counter() - t)
        return delta

    def _confirm_due(self, view: View) -> bool:
        """Whether ``view`` confirms what its fixed camera's last keyframe saw empty, or saw anew
        (``absence_confirm_s``)."""
        since = self._confirm.get(view.source_id)
        wait_s = self.config.fusion.absence_confirm_s
        if since is None or wait_s <= 0 or view.stamp_ns - since[0] < wait_s * 1e9:
            return False
        del self._confirm[view.source_id]
        self._count(f"keyframes_confirming_{since[1]}")
        return True

    def _drifts(self, view: View) -> bool:
        """Whether ``view``'s pose is odometry that drifts: a prior, not a calibration, whose errors are not
        independent per frame (those are no chain to correct)."""
        r = view.prior_rel_rot_deg
        return view.T_world_cam is not None and not view.pose_trusted and (r is None or np.isfinite(r))

    def _corrected(self, view: View) -> View:
        """``view`` with its source's newest loop-closure correction applied to its pose prior."""
        if self.loops is None or not self._drifts(view) or view.source_id not in self.loops.graphs:
            return view
        assert view.T_world_cam is not None
        return dataclasses.replace(view, T_world_cam=self.loops.correction(view.source_id) @ view.T_world_cam)

    def _close_loops(self, view: View) -> tuple[View, set[str]]:
        """Add a moving source's keyframe to its pose graph (``mapper.posegraph``); when a loop closes, move the
        stored keyframes and the nodes fused from them. Returns the view with its corrected prior and the ids
        of the nodes moved."""
        assert self.loops is not None and view.T_world_cam is not None
        try:
            feats = extract_features(view.image, self.config.pose_graph.max_features)
            deltas = self.loops.keyframe(view.key, view.T_world_cam, feats, intrinsics_of(view).K(), view.image)
        except Exception as e:  # noqa: BLE001 - the keyframe goes on with its source's last correction
            self._count("pose_graph_errors")
            log.warning("pose graph: keyframe %s#%d failed: %s: %s", view.source_id, view.seq, type(e).__name__, e)
            return self._corrected(view), set()
        for key, delta in deltas.items():
            self.keyframes.move(key, delta)
            self.loops.move_memory(key, delta)
        moved = self._move_nodes(deltas) if deltas else set()
        self.counters.update(self.loops.counters)
        self._count("keyframes_moved_by_loops", len(deltas))
        self._count("nodes_moved_by_loops", len(moved))
        return self._corrected(view), moved

    def _move_nodes(self, deltas: dict[Key, np.ndarray]) -> set[str]:
        """Move each node fused from keyframes that ``deltas`` moved by their mean (its unmoved keyframes count
        as staying put)."""
        moved = set()
        for node_id, keys in list(self._fused_from.items()):
            node = self.objects.nodes.get(node_id)
            if node is None:
                del self._fused_from[node_id]
                continue
            if not any(k in deltas for k in keys):
                continue
            T = node_move(node.points.mean(0), [deltas.get(k, np.eye(4)) for k in keys])
            R, t = T[:3, :3], T[:3, 3]
            node.points = (node.points @ R.T.astype(np.float32) + t.astype(np.float32)).astype(node.points.dtype)
            node.rays = [(R @ o + t, R @ d) for o, d in node.rays]
            node.sight = [(R @ o + t, R @ d) for o, d in node.sight]
            node.touch()
            moved.add(node_id)
        return moved

    def _finish(self, view: View, results: list[UpdateResult]) -> GraphDelta | None:
        """Retry a deferred keyframe when ``view``'s processing changed something, and commit it all."""
        if results and self._deferred:
            # Retry the oldest deferred keyframe that now has neighbours (one per call bounds the time).
            for _ in range(len(self._deferred)):
                old = self._deferred.popleft()
                if self.keyframes.neighbours(old, self.selector.scene_depth(old.source_id)):
                    self.stages.age("deferred_wait", old.stamp_ns, time.time_ns())
                    self._retried.append(old.key)
                    # Checked for a moved camera when it came in; re-checking it now could only unflag the
                    # camera on an image taken before it moved.
                    extra = self._timed(old, check_pose=False)
                    if extra is not None:
                        results.append(extra)
                    break
                self._deferred.append(old)
        if not results:
            return None
        removed = set().union(*(r.removed for r in results))
        changed = set().union(*(r.changed for r in results)) - removed
        if changed or removed:
            retry = "_retry" if view.key in self._retried else ""
            self.stages.age(f"age_at_commit{retry}", view.stamp_ns, time.time_ns())
        stamp_ns = view.stamp_ns or time.time_ns()
        moves = [NodeMove(node_id=k, stamp_ns=n.last_moved_ns or stamp_ns, from_centroid=a, to_centroid=b,
                          moves=max(1, n.moves))
                 for r in results for k, (a, b) in sorted(r.moved.items())
                 if k in changed and (n := self.objects.nodes.get(k)) is not None]
        retired = {k: n.to_message(self.config.fusion.max_label_alternatives, self.config.node_embeddings)
                   for r in results for k, n in r.retired.items()}
        self._count("nodes_moved", len(moves))
        self._count("nodes_retired", len(retired))
        return self._commit(changed, removed, stamp_ns, {view.source_id: view.seq}, moves, retired)

    def complete(self, view: View, products: KeyframeProducts | None) -> GraphDelta | None:
        """Finish a keyframe whose heavy work was offloaded (:attr:`offload`) with its ``products`` (None: its
        reconstruction could not be placed in the world), as :meth:`ingest` would have; the graph delta, if any."""
        t0 = time.perf_counter()
        if self._offloaded_key == view.key:
            self._offloaded_key = None  # finished: mark_processed may now mark it
        res: UpdateResult | None = None
        if products is None:
            self._count("views_unposed_skipped")
        else:
            try:
                res = self.apply_products(view, products)
            except Exception as e:  # noqa: BLE001 - one bad keyframe must never stop the mapper
                self._count("keyframe_errors")
                log.warning("keyframe %s#%d failed: %s: %s", view.source_id, view.seq, type(e).__name__, e)
        if res is not None:
            self.update_times_s.append(time.perf_counter() - t0)
            del self.update_times_s[:-256]
        return self._finish(view, [res] if res is not None else [])

    def _timed(self, view: View, check_pose: bool = True) -> UpdateResult | None:
        t0 = time.perf_counter()
        try:
            res = self._process(view, check_pose)
        except Exception as e:  # noqa: BLE001 - one bad view must never stop the mapper
            self._count("keyframe_errors")
            self._failed_key = view.key
            log.warning("keyframe %s#%d failed: %s: %s", view.source_id, view.seq, type(e).__name__, e)
            return None
        if res is not None:
            dt = time.perf_counter() - t0
            self.update_times_s.append(dt)
            del self.update_times_s[:-256]
            self.counters["last_update_s"] = dt
        return res

    def mark_processed(self, view: View) -> GraphDelta | None:
        """A frames-only delta saying ``view`` was processed, when it changed nothing (and is newer than what the
        graph already covers): a planner waiting for a robot's arrival frame needs to know. A view whose
        processing failed is not marked (the graph stays exactly as it was)."""
        if self._failed_key == view.key or self._offloaded_key == view.key:
            return None
        self._reserve()
        with self.lock:
            return self.store.commit_frames({view.source_id: view.seq}, view.stamp_ns or time.time_ns())

    def _commit(self, changed: set[str], removed: set[str], stamp_ns: int,
                frames: dict[str, int] | None = None, moves: list[NodeMove] | None = None,
                retired: dict[str, GraphNode] | None = None) -> GraphDelta | None:
        with one_blas_thread():
            return self._commit_edges(changed, removed, stamp_ns, frames, moves, retired)

    def _commit_edges(self, changed: set[str], removed: set[str], stamp_ns: int, frames: dict[str, int] | None,
                      moves: list[NodeMove] | None, retired: dict[str, GraphNode] | None) -> GraphDelta | None:
        t = time.perf_counter()
        boxes = self.objects.boxes()
        edges = compute_edges(boxes, self.config.relations, self._edges)
        clouds = {i: n.points for i, n in self.objects.nodes.items()}
        edges = refine_with_points(edges, boxes, clouds, self.config.relations, self._edges)
        ups = self.objects.messages(sorted(changed), with_embedding=self.config.node_embeddings)
        self._reserve()
        with self.lock:
            delta = self.store.commit(ups, removed, edges, stamp_ns, frames, moves or (), retired)
        if self.last is not None:
            self.last.timings_s["edges"] = time.perf_counter() - t
        return delta

    def _reserve(self) -> None:
        if self.reserve is not None:
            self.reserve(self.store.version + 1, self.objects.next_id)

    def _window(self, view: View) -> tuple[list[View], int]:
        nbrs = self.keyframes.neighbours(view, self.selector.scene_depth(view.source_id))
        if view.T_world_cam is not None or self.config.geometry.backend == "oracle" or not nbrs:
            return [view, *nbrs], 0
        # An unposed view is registered against posed neighbours: put one first to anchor the window.
        return [*nbrs, view], len(nbrs)

    def _moved(self, view: View) -> bool:
        """Whether a calibrated camera's view no longer agrees with its pose (it turned since its first
        keyframe). Flags and unflags it in the counters: ``camera_moved_deg.<source>``."""
        pc = self.config.pose_check
        if not (pc.enabled and view.pose_trusted and view.T_world_cam is not None):
            return False
        feats = extract_features(view.image)
        ref = cast(Features | None, self._pose_refs.get(view.source_id))
        if ref is None:
            self._pose_refs.put(view.source_id, feats)
            return False
        check = rotation_between(ref, feats, intrinsics_of(view).K(), pc.min_inliers)
        key = f"camera_moved_deg.{view.source_id}"
        if check.rotation_deg is None:
            self._count("pose_checks_inconclusive")
            return key in self.counters
        if check.rotation_deg > pc.max_rotation_deg:
            if key not in self.counters:
                log.warning("camera %s turned %.1f deg since its first keyframe: its frames are not fused until it "
                            "is recalibrated", view.source_id, check.rotation_deg)
            self.counters[key] = round(check.rotation_deg, 2)
            self._count("keyframes_rejected_camera_moved")
            return True
        self.counters.pop(key, None)
        return False

    def _process(self, view: View, check_pose: bool = True) -> UpdateResult | None:
        if check_pose and self._moved(view):
            return None
        views, target = self._window(view)
        if len(views) == 1 and self.config.geometry.backend != "oracle":
            # Multi-view stereo needs a neighbour: keep the view for later windows and retry it later.
            self._count("keyframes_deferred")
            self.keyframes.add(view)
            self._deferred.append(view)
            sv = self.config.single_view
            if sv.enabled and view.T_world_cam is not None and (view.pose_trusted or sv.untrusted_poses):
                return self._single_view(view)
            return None
        if self.offload is not None and self.offload(view, views, target):
            self._count("keyframes_offloaded")
            self._offloaded_key = view.key
            return None
        products = compute_keyframe(self.reconstructor, self.segmenter, self.embedder, self.config, views, target)
        if products is None:
            self._count("views_unposed_skipped")
            return None
        return self.apply_products(view, products)

    def apply_products(self, view: View, products: KeyframeProducts) -> UpdateResult:
        """The mapper's part of a keyframe once its heavy work is done (here or by a worker): typical depth,
        the depth check, the keyframe store, then fusion."""
        with one_blas_thread():  # fusion and edges are many small products (see one_blas_thread)
            return self._apply_products(view, products)

    def _apply_products(self, view: View, products: KeyframeProducts) -> UpdateResult:
        times = dict(products.timings_s)
        vg, T_world_cam = products.geometry, products.T_world_cam
        depth_m = typical_depth(vg.depth_m, vg.confidence)
        if depth_m is not None:
            self.selector.observe_depth(view.source_id, depth_m)
        dc = self.config.depth_check
        K_out = products.K
        if dc.enabled and self.config.geometry.backend != "oracle" and depth_m is not None:
            # True depth needs no cross-check; estimated depth must agree with other keyframes before fusion.
            others = self.keyframes.depth_maps_overlapping(view, T_world_cam, depth_m, dc.max_views)
            conf, st = verify_depth(vg.depth_m, vg.confidence, K_out, T_world_cam, others, dc.min_views,
                                    dc.rel_tol, dc.reproj_px)
            self._count("depth_pixels_checked", st.checked)
            self._count("depth_pixels_rejected_inconsistent", st.rejected)
            vg = ViewGeometry(points_world=vg.points_world, depth_m=vg.depth_m, confidence=conf)
        # Only the depth check reads the stored maps: do not pay for them when it is off.
        depth_map = downsample(vg.depth_m, vg.confidence, K_out, T_world_cam, dc.map_width, 0.5) if dc.enabled else None
        self.keyframes.add(view, T_world_cam, depth_m, depth_map)
        if self.loops is not None:
            h, w = view.image.shape[:2]
            self.loops.remember(view.key, vg.depth_m, vg.confidence, K_out, intrinsics_of(view).K(), (w, h),
                                T_world_cam)
        # Measured depth: the detections are also matched to nodes in the image (confident depth only).
        sure = np.where(vg.confidence >= self.config.fusion.min_depth_confidence, vg.depth_m, 0.0)
        kv = KeyframeView(K_out, T_world_cam, sure)
        return self._fuse(view, vg, T_world_cam, times, dets=products.detections, kv=kv)

    def _single_view(self, view: View) -> UpdateResult | None:
        """Objects of a posed view with no stereo partner, placed from the floor plane (coarse, low confidence;
        the view stays deferred for multi-view stereo). Perception runs first: placement needs the masks, and the
        people among them (``_not_people``) are occluders, never supports (an object behind a passer-by is not set
        on the passer-by)."""
        assert view.T_world_cam is not None
        t = time.perf_counter()
        masks = self.segmenter.segment(view, None)
        if not masks:
            return UpdateResult()
        dets = self.embedder.embed(view, masks)
        times = {"perception": time.perf_counter() - t}
        t = time.perf_counter()
        things = self._not_people(dets, count=False)
        kept = {id(d) for d in things}
        shown = [d.mask for d in things]
        people = [d.mask for d in dets if id(d) not in kept]
        K = intrinsics_of(view).K()
        sv = self.config.single_view
        boxes = place_objects(shown, K, view.T_world_cam, sv.params(), view.image if sv.floor_colour_check else None,
                              occluders=people)
        floor_masks = [m for m, b in zip(shown, boxes, strict=True) if b is not None and b.support < 0]
        changed = self._learn_changes(view, people)
        skip: set[int] = set()
        if changed is not None and sv.changed_only:
            # What did not change this camera placed before from this very pose; a passer-by changes nothing.
            keep = [changed.touches(d.mask) for d in things]
            self._count("single_view_unchanged", keep.count(False))
            boxes = [b if k else None for b, k in zip(boxes, keep, strict=True)]
            skip = {id(d) for d, k in zip(things, keep, strict=True) if not k}
        self._count("keyframes_single_view")
        self._count("single_view_masks", len(masks))
        self._count("single_view_placed", sum(b is not None for b in boxes))
        if shown:
            depth, conf = layout_depth(shown, boxes, K, view.T_world_cam, sv.confidence)
        else:  # only people: nothing to place, but what they hide is still seen as not floor (SeenView)
            depth = np.zeros(masks[0].mask.shape, np.float32)
            conf = np.zeros_like(depth)
        vg = ViewGeometry(points_world=depth_to_world(depth, K, view.T_world_cam), depth_m=depth, confidence=conf)
        times["geometry"] = time.perf_counter() - t
        return self._fuse(view, vg, view.T_world_cam, times, floor_masks=floor_masks, dets=dets, skip=skip)

    def _fuse(self, view: View, vg: ViewGeometry, T_world_cam: np.ndarray, times: dict[str, float],
              masks: list[Mask2D] | None = None, floor_masks: list[np.ndarray] | None = None,
              dets: list[Detection] | None = None, kv: KeyframeView | None = None,
              skip: set[int] | None = None) -> UpdateResult:
        """2D perception (unless ``dets`` or ``masks`` are given), lifting and fusion of one keyframe's geometry.
        ``floor_masks`` (the masks it placed on the floor) marks a single-view keyframe; ``kv`` (a measured
        keyframe's camera and confident depth) lets fusion match detections to nodes in the image; ``skip``
        (``id()`` of detections) are seen but not fused (a fixed camera's unchanged objects)."""
        single_view = floor_masks is not None
        outside = outside_fraction(vg.points_world, vg.confidence, vg.depth_m, self.config.fusion)
        if outside > self.config.fusion.max_outside_fraction:
            # Depth that puts much of the view under the floor is wrong everywhere (scale or matching failure):
            # fusing it would place objects far from where they are. The pose may still serve later windows.
            self._count("keyframes_rejected_depth")
            log.debug("keyframe %s#%d: %.0f %% of its depth outside the room slab, not fused",
                      view.source_id, view.seq, 100 * outside)
            return UpdateResult()
        if dets is None:
            t = time.perf_counter()
            if masks is None:
                masks = self.segmenter.segment(view, vg)
            dets = self.embedder.embed(view, masks)
            times["perception"] = time.perf_counter() - t
        t = time.perf_counter()
        all_dets, dets = dets, self._not_people(dets)
        things = {id(d) for d in dets}
        people = [d.mask for d in all_dets if id(d) not in things]
        # their pixels at the depth's size, once: out of the point map, and occluders for evidence of absence
        people_px = np.zeros(vg.depth_m.shape, bool)
        for m in people:
            people_px |= resize_mask(m, *vg.depth_m.shape)
        fc = self.config.fusion
        people_known = bool(fc.people_labels) and not fc.fuse_people  # (a person's mask is then among people)
        dets = self._join_split_by_people(all_dets, dets)
        if skip:
            dets = [d for d in dets if id(d) not in skip]
        focal = intrinsics_of(view).K()[0, 0] * vg.depth_m.shape[1] / view.image.shape[1]
        objs, lift = lift_detections(dets, vg.points_world, vg.confidence, vg.depth_m, self.config.fusion, focal)
        self._count("detections", len(dets))
        self._count("detections_dropped_no_depth", lift.dropped_no_depth)
        self._count("detections_dropped_small", lift.dropped_small_mask)
        self._count("detections_dropped_noise", lift.dropped_noise)
        if not single_view and lift.no_depth and self.config.single_view.fill_depthless:
            coarse = self._place_depthless(view, T_world_cam, dets, lift.no_depth, vg)
            self._count("detections_placed_single_view", len(coarse))
            objs += coarse
        seen: SeenView | None = None
        seen_before = cast(SeenView | None, self._seen.get(view.source_id))
        if floor_masks is not None:  # a single-view keyframe
            objs = [dataclasses.replace(o, ray_origin=T_world_cam[:3, 3].copy()) for o in objs]
            if all_dets:  # people too: where one stands the camera did not see the floor
                seen = SeenView.build(
                    view.image, [d.mask for d in all_dets], [d.descriptor for d in all_dets], intrinsics_of(view).K(),
                    T_world_cam, floor_masks, self.config.single_view.floor_z_m,
                    people=[id(d) not in things for d in all_dets] if people_known else None)
                self._seen.put(view.source_id, seen)
        # every detection counts as seen, lifted to 3D or not (fusion.absence_*)
        detected = [(d.mask, d.descriptor) for d in dets] if kv is not None else None
        if kv is not None and people_known:
            # where people hide a node is no evidence of absence; other occluders hide less (mapper.absence)
            seen_people = people_px
            if seen_people.any():  # and the depth bleeding past its outline (stereo)
                seen_people = cv2.dilate(seen_people.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            kv = dataclasses.replace(kv, people=seen_people)
        res = self.objects.integrate(objs, view.source_id, view.stamp_ns or time.time_ns(), kv, detected,
                                     fixed=view.pose_trusted)
        if seen is not None and view.pose_trusted:  # where this camera saw each node: its misses ask there
            self.objects.remember_pixels(objs, res.targets, view.source_id, seen)
        if self.loops is not None:
            self._note_fused(view.key, res)
        if single_view:
            # Other cameras' placements of the same objects fix their depth, and what they saw as free space
            # refutes placements; cameras that never move make few keyframes, so this runs now, not every
            # ``merge_every_updates`` keyframes.
            self.objects.triangulate_coarse(res)
            if self.config.single_view.free_space_check:
                self._count("single_view_moved", self.objects.check_coarse(self._seen.values(), res))
                if seen is not None:  # what this camera placed before and now sees floor in place of: gone
                    self._count("single_view_gone", self.objects.forget_gone(seen, res))
            if seen is not None and view.pose_trusted:  # what it saw before and detects no more: a miss
                self._count("single_view_misses", len(self.objects.count_misses(
                    seen, seen_before, view.source_id, res)))
            self.objects.maintain(res)
        if view.pose_trusted and res.seen_gone:
            self._confirm[view.source_id] = (view.stamp_ns, "absence")
        elif view.pose_trusted and res.created and not single_view:
            self._confirm[view.source_id] = (view.stamp_ns, "new")
        else:
            self._confirm.pop(view.source_id, None)
        self._count("nodes_created", res.created)
        self._count("nodes_merged", res.merged_duplicates)
        self._count("nodes_pruned", res.pruned)
        self._add_points(view, vg, people_px)
        if self.rooms is not None:
            self.rooms.note_camera(T_world_cam[:3, 3])
        times["fusion"] = time.perf_counter() - t
        self.last = KeyframeResult(view, T_world_cam, vg, len(dets), lift, times)
        return res

    def _learn_changes(self, view: View, people: list[np.ndarray]) -> Changes | None:
        """What changed in a calibrated camera's view since its earlier single-view keyframes
        (``mapper.changemask``), ``people`` (their masks) left out, and the keyframe learnt as its background;
        None for other views, and when everything is new. Only single-view keyframes learn: a measured one may
        fuse an object it saw without making a node of it (no confident depth), and the next single-view keyframe
        must still see it as new."""
        if not view.pose_trusted or view.T_world_cam is None:
            return None
        return self._changes.update(view.source_id, view.T_world_cam, view.stamp_ns, view.image, people)

    def _not_people(self, dets: list[Detection], count: bool = True) -> list[Detection]:
        """``dets`` less the people (``fusion.people_labels``, unless ``fusion.fuse_people``): a person is not a
        furniture node, and one walking through would leave a trail of them. ``count``: add them to
        ``detections_people``."""
        fc = self.config.fusion
        if fc.fuse_people or not fc.people_labels:
            return dets
        people = {p.lower() for p in fc.people_labels}
        kept = [d for d in dets if d.label.lower() not in people]
        if count:
            self._count("detections_people", len(dets) - len(kept))
        return kept

    def _join_split_by_people(self, all_dets: list[Detection], dets: list[Detection]) -> list[Detection]:
        """``dets`` (people left out) with the pieces of one object a person of ``all_dets`` cut in two joined
        (``fusion.join_split_by_people``, ``mapper.perception.occluded``)."""
        fc = self.config.fusion
        if not fc.join_split_by_people or fc.fuse_people or len(dets) == len(all_dets):
            return dets
        people = {p.lower() for p in fc.people_labels}
        joined, n = join_split_by_people(dets, [d for d in all_dets if d.label.lower() in people],
                                         fc.merge_similarity)
        self._count("detections_joined_across_people", n)
        return joined

    def _note_fused(self, key: Key, res: UpdateResult, keep: int = 16) -> None:
        """Remember that keyframe ``key`` changed the nodes of ``res`` (its last ``keep`` keyframes per node; a
        moved node's earlier keyframes saw it elsewhere)."""
        for node_id in res.removed | set(res.moved):
            self._fused_from.pop(node_id, None)
        for node_id in res.changed - res.removed:
            keys = self._fused_from.setdefault(node_id, [])
            if key not in keys:
                keys.append(key)
                del keys[:-keep]

    def _place_depthless(self, view: View, T_world_cam: np.ndarray, dets: list[Detection],
                         which: list[int], vg: ViewGeometry) -> list[Object3D]:
        """Coarse 3D objects for the detections ``which`` that stereo gave no depth (textureless): placed from
        where their masks touch the floor (single-view geometry, every mask of the view taking part) or, with
        ``measured_support``, the level surface the keyframe's depth ``vg`` shows under them; marked with the
        camera centre as coarse."""
        sv = self.config.single_view
        K = intrinsics_of(view).K()
        h, w = view.image.shape[:2]
        shown = [resize_mask(d.mask, h, w) for d in dets]  # a worker's masks may come at the depth's size
        boxes = place_objects(shown, K, T_world_cam, sv.params(), view.image if sv.floor_colour_check else None)
        # Floor contacts; a guess stacked on another guess (a vase on a shelf) is too loose to keep.
        placed = {i: b for i in which if (b := boxes[i]) is not None and b.support < 0}
        if sv.measured_support and len(placed) < len(which):
            hd, wd = vg.depth_m.shape
            Kd = intrinsics_of(view).scaled(wd, hd).K()
            small = [resize_mask(d.mask, hd, wd) for d in dets]
            anything = np.any(small, axis=0)
            fc = self.config.fusion
            valid = (np.isfinite(vg.depth_m) & (vg.depth_m > 0) & (vg.confidence >= fc.min_depth_confidence)
                     & np.all(np.isfinite(vg.points_world), axis=-1))
            tops = self._mapped_tops() if sv.mapped_support else []
            for i in which:
                if i in placed:
                    continue
                others = anything & ~small[i]
                b = place_on_measured_support(small[i], others, vg.points_world, valid, Kd, T_world_cam, sv.params())
                if b is not None:
                    self._count("detections_placed_on_measured_support")
                elif sv.mapped_support:
                    b = place_on_mapped_support(small[i], others, tops, Kd, T_world_cam, sv.params())
                    if b is not None:
                        self._count("detections_placed_on_mapped_support")
                if b is not None:
                    placed[i] = b
        if sv.background_check and placed:
            placed = self._in_front_of_background(view, dets, placed, vg, T_world_cam)
        if not placed:
            return []
        pick = sorted(placed)
        depth, conf = layout_depth([shown[i] for i in pick], [placed[i] for i in pick], K, T_world_cam,
                                   sv.confidence)
        objs, _ = lift_detections([dets[i] for i in pick], depth_to_world(depth, K, T_world_cam), conf, depth,
                                  self.config.fusion)
        return [dataclasses.replace(o, ray_origin=T_world_cam[:3, 3].copy()) for o in objs]

    def _in_front_of_background(self, view: View, dets: list[Detection], placed: dict[int, PlacedBox],
                                vg: ViewGeometry, T_world_cam: np.ndarray) -> dict[int, PlacedBox]:
        """``placed`` without the boxes that lie behind the depth this keyframe measured around their masks."""
        hd, wd = vg.depth_m.shape
        Kd = intrinsics_of(view).scaled(wd, hd).K()
        kept = {}
        for i, b in placed.items():
            if behind_background(b, resize_mask(dets[i].mask, hd, wd), vg.depth_m, vg.confidence, Kd, T_world_cam,
                                 min_confidence=self.config.fusion.min_depth_confidence,
                                 margin_m=self.config.single_view.background_margin_m):
                self._count("placements_behind_background")
            else:
                kept[i] = b
        return kept

    def _mapped_tops(self, min_side_m: float = 0.2, z_range_m: tuple[float, float] = (0.2, 2.2)) -> list[MappedTop]:
        """Top faces of the measured nodes (not single-view guesses) big enough to stand things on."""
        tops = []
        for n in self.objects.nodes.values():
            if n.rays:
                continue
            b = n.box
            top = b.center[2] + 0.5 * b.extent[2]
            if min(b.extent[0], b.extent[1]) >= min_side_m and z_range_m[0] <= top <= z_range_m[1]:
                tops.append(MappedTop(np.asarray(b.center[:2], np.float64), 0.5 * np.asarray(b.extent[:2], np.float64),
                                      float(b.yaw_rad), float(top)))
        return tops

    def _add_points(self, view: View, vg: ViewGeometry, people_px: np.ndarray | None = None) -> None:
        """The keyframe's confident depth into the point map, less ``people_px`` (pixels of people, at the
        depth's size): a passer-by is no obstacle to plan around once gone, nor a wall for the room layer."""
        pm = self.config.point_map
        d = vg.depth_m
        ok = np.isfinite(d) & (d > 0) & (d <= pm.max_depth_m) & (vg.confidence >= pm.min_confidence)
        if people_px is not None:
            ok &= ~people_px
        if not ok.any():
            return
        h, w = d.shape
        # bilinear: cv2.INTER_AREA used to be passed where resize takes ``dst`` (positional), so it never applied
        img = view.image if view.image.shape[:2] == (h, w) else cv2.resize(view.image, (w, h))
        with self.lock:
            self.voxels.add(vg.points_world[ok], img[ok])

    # -- reads (any thread) ------------------------------------------------------------------------
    @property
    def version(self) -> int:
        return self.store.version

    @property
    def epoch(self) -> str:
        return self.store.epoch

    def snapshot(self) -> GraphSnapshot:
        with self.lock:
            return self.store.snapshot()

    def snapshot_key(self) -> tuple[str, int, int | None]:
        """(epoch, version, the room layer's version): the snapshot changes exactly when this does (a room layer can
        join the delta of the version it was built at after that version was committed)."""
        with self.lock:
            return self._snapshot_key()

    def keyed_snapshot(self) -> tuple[GraphSnapshot, tuple[str, int, int | None]]:
        """:meth:`snapshot` and its :meth:`snapshot_key`, taken together."""
        with self.lock:
            return self.store.snapshot(), self._snapshot_key()

    def _snapshot_key(self) -> tuple[str, int, int | None]:
        rooms = self.store.rooms
        return self.store.epoch, self.store.version, rooms.version if rooms is not None else None

    def nodes(self) -> list[GraphNode]:
        with self.lock:
            return [self.store.nodes[k] for k in sorted(self.store.nodes)]

    def query(self, q: GraphQuery) -> list[GraphNode]:
        """Nodes selected by ``q``; ``q.room`` selects by the room layer (built now if the graph changed)."""
        members: set[str] | None = None
        if q.room is not None:
            layer = self.room_layer()
            members = set(layer.members(q.room)) if layer is not None else set()
        with self.lock:
            out = self.store.query(q)
        return out if members is None else [n for n in out if n.node_id in members]

    def select_graph(self, q: GraphQuery) -> GraphSnapshot:
        """The nodes ``q`` selects, the edges among them and their last moves (and the retired nodes ``q`` asks
        for), without building the whole graph's snapshot."""
        nodes = self.query(q)
        ids = {n.node_id for n in nodes}
        retired = self.retired(q) if q.include_retired else []
        with self.lock:
            st = self.store
            edges = [st.edges[k] for k in sorted(st.edges)
                     if st.edges[k].subject_id in ids and st.edges[k].object_id in ids]
            return GraphSnapshot(epoch=st.epoch, version=st.version, stamp_ns=st.stamp_ns, nodes=nodes, edges=edges,
                                 moves=st.moves_of(ids), retired=retired)

    def retired(self, q: GraphQuery) -> list[RetiredNode]:
        """The retired nodes (seen gone, kept ``max_retired`` / ``retired_keep_s``) that ``q`` selects, newest
        first; none with ``q.room`` (rooms hold live nodes only)."""
        if q.room is not None:
            return []
        with self.lock:
            return self.store.retired_matching(q)

    def room_layer(self) -> RoomLayerMessage | None:
        """The room layer as its wire message, rebuilt when the graph version moved since the last build (None
        when rooms are off)."""
        if self.rooms is None:
            return None
        with self._rooms_lock:
            cached = self._room_message
            if cached is not None and cached.version == self.version and cached.epoch == self.epoch:
                return cached
        self.update_rooms()
        with self._rooms_lock:
            return self._room_message

    def update_rooms(self) -> RoomLayer | None:
        """Rebuild the room layer from the current map and nodes (room ids carried over from the last call);
        None when rooms are off. The map is copied under the graph lock; the rooms are built outside it."""
        if self.rooms is None:
            return None
        with self._rooms_lock:
            with self.lock:
                pts, counts = self.voxels.points(), self.voxels.counts.copy()
                nodes = [self.store.nodes[k] for k in sorted(self.store.nodes)]
                version, epoch = self.store.version, self.store.epoch
            layer = self.rooms.update(pts, nodes, counts)
            self._room_message = room_message(layer, self.rooms.in_room, version, epoch, time.time_ns())
            self._rooms_built_at_keyframe = self.counters.get("keyframes", 0.0)
            self.counters["rooms"] = float(len(layer.rooms))
            return layer

    def point_map(self, max_points: int | None = None) -> PointMap:
        with self.lock:
            return self.voxels.message(self.store.version, time.time_ns(), max_points)

    # -- persistence -----------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Everything a restart needs to resume the same graph (node ids, version, clouds)."""
        with self.lock:
            return {
                "format": STATE_FORMAT,
                "store": self.store.state(),
                "objects": self.objects.state(),
                "voxels": self.voxels.state(),
                **({"rooms": self.rooms.state()} if self.rooms is not None else {}),
            }

    def load_state(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`state` output; raises ``ValueError`` when it is unusable."""
        if state.get("format") != STATE_FORMAT:
            raise ValueError(f"state format {state.get('format')!r} is not {STATE_FORMAT}")
        with self.lock:
            try:
                self.store.load_state(state["store"])
                self.objects.load_state(state["objects"])
                self.voxels.load_state(state["voxels"])
                if self.rooms is not None and "rooms" in state:  # older states have none: rooms start afresh
                    self.rooms.load_state(state["rooms"])
            except (KeyError, TypeError) as e:
                raise ValueError(f"malformed state: {e!r}") from None

    def restart_at(self, epoch: str, version: int, next_id: int) -> None:
        """Go on as ``version`` of ``epoch`` with node ids from ``next_id`` on (a restarted mapper)."""
        with self.lock:
            self.store.restart_at(epoch, version)
            self.objects.next_id = max(self.objects.next_id, next_id)

    def switch_epoch(self, epoch: str) -> None:
        """Go on in another epoch from the current version (the old one's lease could not be extended)."""
        with self.lock:
            self.store.epoch = epoch
