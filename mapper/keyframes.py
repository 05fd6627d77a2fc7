"""Keyframe selection and geometry windows by parallax (pure: no I/O).

A posed view becomes a keyframe when it moved far enough from its source's last keyframe *relative to the
scene depth* (baseline / depth >= ``min_baseline_ratio``), or turned enough; at 30 fps most frames are
1-3 cm apart and add no depth a keyframe does not already give. A camera without a pose (or a static
one after ``refresh_s``) becomes a keyframe when its image changed enough (a static one also when a small part
of it changed much: an object moved or taken away).

The window for the reconstructor is the new keyframe plus the stored keyframes of ANY source (robots and
calibrated fixed cameras alike) that make the best stereo partners for it: triangulation angle at its
typical depth, overlap and viewing-angle change (``mapper.geometry.viewselect``), never simply the last
frames that arrived. The few moving-camera frames just before a keyframe that did not become keyframes
themselves are candidates too (``recent_sources``): at video rate they are the views that already see
most of what the new keyframe newly sees, with parallax enough to triangulate it.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, replace

import cv2
import numpy as np

from mapper.config import KeyframeConfig
from mapper.consistency import DepthMap
from mapper.geometry.contract import View
from mapper.geometry.viewselect import (
    Candidate,
    ViewSelectParams,
    overlap_fraction,
    sample_rays,
    select_sources,
    triangulation_deg,
)
from protocol.messages import Intrinsics
from protocol.poses import rotation_angle_deg


def thumbnail(image: np.ndarray) -> np.ndarray:
    """32x24 grey thumbnail in [0, 1] used for novelty."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def colour_thumbnail(image: np.ndarray) -> np.ndarray:
    """32x24 RGB thumbnail in [0, 1] for a static camera's changed cells: a bag put down on a floor of its own
    grey changes the grey thumbnail by less than ``change_threshold``, but not every colour channel."""
    return cv2.resize(image, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def intrinsics_of(view: View, hfov_deg: float = 70.0) -> Intrinsics:
    """The view's intrinsics, or a guess from a typical field of view for an uncalibrated camera."""
    if view.intrinsics is not None:
        return view.intrinsics
    h, w = view.image.shape[:2]
    return Intrinsics.from_fov(w, h, hfov_deg)


@dataclass
class _Last:
    T_world_cam: np.ndarray | None
    stamp_ns: int
    thumb: np.ndarray
    colour: np.ndarray  # (24, 32, 3)


class KeyframeSelector:
    """Decides which views are keyframes, per source."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self._last: dict[str, _Last] = {}
        self._depth: dict[str, collections.deque[float]] = {}

    def observe_depth(self, source_id: str, depth_m: float) -> None:
        """Tell the selector the typical scene depth a source sees (median of its last depth map)."""
        if np.isfinite(depth_m) and depth_m > 0:
            self._depth.setdefault(source_id, collections.deque(maxlen=5)).append(float(depth_m))

    def scene_depth(self, source_id: str) -> float:
        """The source's typical scene depth: median of its last 5 observed, else ``assumed_depth_m`` (one view
        close to a wall must not make every later baseline look huge)."""
        d = self._depth.get(source_id)
        return float(np.median(d)) if d else self.cfg.assumed_depth_m

    def consider(self, view: View) -> bool:
        """Whether ``view`` is a keyframe (and if so remember it as its source's last)."""
        cfg = self.cfg
        thumb, colour = thumbnail(view.image), colour_thumbnail(view.image)
        last = self._last.get(view.source_id)
        diff = None if last is None or last.thumb.shape != thumb.shape else np.abs(thumb - last.thumb)
        novelty = 1.0 if diff is None else float(diff.mean())
        changed = 1.0
        if diff is not None and last is not None:
            changed = float(np.mean(np.abs(colour - last.colour).max(axis=2) >= cfg.change_threshold))
        if last is None:
            new = True
        elif view.T_world_cam is not None and last.T_world_cam is not None:
            moved = float(np.linalg.norm(view.T_world_cam[:3, 3] - last.T_world_cam[:3, 3]))
            turned = rotation_angle_deg(view.T_world_cam, last.T_world_cam)
            static = moved <= cfg.static_max_m and turned <= cfg.static_max_deg
            refresh_s = cfg.refresh_s if static else cfg.moving_refresh_s
            stale = refresh_s > 0 and (view.stamp_ns - last.stamp_ns) >= refresh_s * 1e9
            enough_parallax = moved >= cfg.min_baseline_ratio * self.scene_depth(view.source_id)
            new = enough_parallax or moved >= cfg.min_translation_m or turned >= cfg.min_rotation_deg or (
                stale and (novelty >= cfg.novelty_threshold or (static and changed >= cfg.change_fraction))
            )
        else:
            new = novelty >= cfg.novelty_threshold
        if new:
            self._last[view.source_id] = _Last(view.T_world_cam, view.stamp_ns, thumb, colour)
        return new


@dataclass
class _Stored:
    view: View
    depth_m: float | None  # typical scene depth once reconstructed
    depth_map: DepthMap | None = None  # its confident depth, small, for consistency checks


class KeyframeStore:
    """The bounded set of past keyframes windows are drawn from."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self._frames: collections.deque[_Stored] = collections.deque(maxlen=cfg.max_keyframes)
        # Per moving source, its last few frames that were not keyframes (oldest source dropped first).
        self._recent: collections.OrderedDict[str, collections.deque[View]] = collections.OrderedDict()
        self.params = ViewSelectParams(
            min_triangulation_deg=cfg.source_min_triangulation_deg,
            min_overlap=cfg.source_min_overlap,
            max_rotation_deg=cfg.neighbour_max_angle_deg,
        )

    def __len__(self) -> int:
        return len(self._frames)

    def views(self) -> list[View]:
        """The stored keyframes, oldest first, then the recent frames that are source candidates too."""
        return [s.view for s in self._frames] + [v for ring in self._recent.values() for v in ring]

    def note_frame(self, view: View) -> None:
        """Remember a posed frame that is not a keyframe as a source candidate, when its camera moved
        ``recent_min_move_m`` from its source's last stored view (a static camera's frames add nothing)."""
        n = self.cfg.recent_sources
        if n == 0 or view.T_world_cam is None:
            return
        ring = self._recent.get(view.source_id)
        last = ring[-1] if ring else next((s.view for s in reversed(self._frames)
                                            if s.view.source_id == view.source_id), None)
        if last is not None and last.T_world_cam is not None and float(
                np.linalg.norm(view.T_world_cam[:3, 3] - last.T_world_cam[:3, 3])) < self.cfg.recent_min_move_m:
            return
        if ring is None:
            ring = self._recent[view.source_id] = collections.deque(maxlen=n)
        self._recent.move_to_end(view.source_id)
        ring.append(view)
        while len(self._recent) > self.cfg.max_keyframes:
            self._recent.popitem(last=False)

    def add(self, view: View, T_world_cam: np.ndarray | None = None, depth_m: float | None = None,
            depth_map: DepthMap | None = None) -> None:
        """Keep ``view``, with its registered pose when it had none (so later windows can anchor on it), its
        typical depth and its depth map when known. Storing a view again (same source and seq) replaces it."""
        if view.T_world_cam is None and T_world_cam is not None:
            view = replace(view, T_world_cam=T_world_cam)
        for i, s in enumerate(self._frames):
            if s.view.key == view.key:
                del self._frames[i]
                break
        self._frames.append(_Stored(view, depth_m, depth_map))
        # The source's frames before this keyframe are older views of what it sees: it replaces them.
        self._recent.pop(view.source_id, None)

    def move(self, key: tuple[str, int], delta: np.ndarray) -> bool:
        """A stored keyframe's pose was corrected by ``delta`` (4x4 world transform, left-multiplied): its
        prior and its depth map's pose follow. False when it is not stored."""
        for i, s in enumerate(self._frames):
            if s.view.key == key and s.view.T_world_cam is not None:
                dm = s.depth_map
                if dm is not None:
                    dm = DepthMap(dm.depth_m, dm.K, delta @ dm.T_world_cam)
                self._frames[i] = _Stored(replace(s.view, T_world_cam=delta @ s.view.T_world_cam), s.depth_m, dm)
                return True
        return False

    def depth_of(self, view: View, default: float) -> float:
        """Typical depth recorded for a stored view, else ``default``."""
        for s in self._frames:
            if s.view.key == view.key and s.depth_m is not None:
                return s.depth_m
        return default

    def depth_maps_overlapping(self, view: View, T_world_cam: np.ndarray, depth_m: float, k: int) -> list[DepthMap]:
        """Depth maps of up to ``k`` other stored keyframes that see most of what ``view`` sees at ``depth_m``."""
        rays = sample_rays(intrinsics_of(view))
        X = (rays * depth_m) @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
        scored = []
        for s in self._frames:
            if s.view.key == view.key or s.depth_map is None:
                continue
            ov = overlap_fraction(X, s.depth_map.T_world_cam, intrinsics_of(s.view))
            if ov > 0.1:
                scored.append((ov, s.depth_map))
        scored.sort(key=lambda t: -t[0])
        return [m for _, m in scored[:k]]

    def neighbours(self, view: View, depth_m: float | None = None) -> list[View]:
        """Up to ``window_neighbours`` stored keyframes to reconstruct ``view`` with, best stereo partners
        first. ``depth_m``: the view's typical scene depth (default: ``assumed_depth_m``)."""
        cfg = self.cfg
        if cfg.window_neighbours == 0:
            return []
        others = [v for v in self.views() if v.key != view.key]
        if view.T_world_cam is None:
            posed = [f for f in reversed(others) if f.T_world_cam is not None]
            return posed[: cfg.window_neighbours]
        T = view.T_world_cam
        cands = [
            Candidate(i, f.T_world_cam, intrinsics_of(f))
            for i, f in enumerate(others)
            if f.T_world_cam is not None
            and float(np.linalg.norm(f.T_world_cam[:3, 3] - T[:3, 3])) <= cfg.neighbour_max_distance_m
        ]
        depth = depth_m if depth_m is not None else self.depth_of(view, cfg.assumed_depth_m)
        chosen = [s.index for s in select_sources(T, intrinsics_of(view), depth, cands, cfg.window_neighbours,
                                                    self.params)]
        if len(chosen) < cfg.window_neighbours:
            # Too few ideal partners: fill with the nearest views that still have parallax and whose optical axes
            # are within 10 deg more than the cap (measured on the static sim eval: more views make the pose
            # refinement sturdier, F1 0.75 -> 0.82 on one held-out room).
            near = []
            for c in cands:
                base = float(np.linalg.norm(c.T_world_cam[:3, 3] - T[:3, 3]))
                axis = float(np.degrees(np.arccos(np.clip(c.T_world_cam[:3, 2] @ T[:3, 2], -1.0, 1.0))))
                if c.index in chosen or axis > cfg.neighbour_max_angle_deg + 10.0:
                    continue
                if triangulation_deg(base, depth) < cfg.source_min_triangulation_deg and axis < 3.0:
                    continue
                near.append((base + axis / 45.0, c.index))
            chosen += [i for _, i in sorted(near)[: cfg.window_neighbours - len(chosen)]]
        return [others[i] for i in chosen]
