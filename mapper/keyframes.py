"""Keyframe selection and geometry windows (pure: no I/O).

A view becomes a keyframe when its camera moved or turned enough since its source's last keyframe, or,
for a camera without a pose (or a static one after ``refresh_s``), when its image changed enough.
Windows for the reconstructor are the new keyframe plus the nearest stored keyframes with a usable
baseline (poses known or registered), newest first when nothing is posed.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, replace

import cv2
import numpy as np

from mapper.config import KeyframeConfig
from mapper.geometry.contract import View
from protocol.poses import rotation_angle_deg


def thumbnail(image: np.ndarray) -> np.ndarray:
    """32x24 grey thumbnail in [0, 1] used for novelty."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (32, 24), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


@dataclass
class _Last:
    T_world_cam: np.ndarray | None
    stamp_ns: int
    thumb: np.ndarray


class KeyframeSelector:
    """Decides which views are keyframes, per source."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self._last: dict[str, _Last] = {}

    def consider(self, view: View) -> bool:
        """Whether ``view`` is a keyframe (and if so remember it as its source's last)."""
        cfg = self.cfg
        thumb = thumbnail(view.image)
        last = self._last.get(view.source_id)
        novelty = 1.0 if last is None or last.thumb.shape != thumb.shape else float(np.abs(thumb - last.thumb).mean())
        if last is None:
            new = True
        elif view.T_world_cam is not None and last.T_world_cam is not None:
            moved = float(np.linalg.norm(view.T_world_cam[:3, 3] - last.T_world_cam[:3, 3]))
            turned = rotation_angle_deg(view.T_world_cam, last.T_world_cam)
            stale = cfg.refresh_s > 0 and (view.stamp_ns - last.stamp_ns) >= cfg.refresh_s * 1e9
            new = moved >= cfg.min_translation_m or turned >= cfg.min_rotation_deg or (
                stale and novelty >= cfg.novelty_threshold
            )
        else:
            new = novelty >= cfg.novelty_threshold
        if new:
            self._last[view.source_id] = _Last(view.T_world_cam, view.stamp_ns, thumb)
        return new


class KeyframeStore:
    """The bounded set of past keyframes windows are drawn from."""

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self._frames: collections.deque[View] = collections.deque(maxlen=cfg.max_keyframes)

    def __len__(self) -> int:
        return len(self._frames)

    def add(self, view: View, T_world_cam: np.ndarray | None = None) -> None:
        """Keep ``view``, with its registered pose when it had none (so later windows can anchor on it)."""
        if view.T_world_cam is None and T_world_cam is not None:
            view = replace(view, T_world_cam=T_world_cam)
        self._frames.append(view)

    def neighbours(self, view: View) -> list[View]:
        """Up to ``window_neighbours`` keyframes to reconstruct ``view`` with, best first."""
        cfg = self.cfg
        if cfg.window_neighbours == 0:
            return []
        others = [f for f in self._frames if f.key != view.key]
        if view.T_world_cam is None:
            posed = [f for f in reversed(others) if f.T_world_cam is not None]
            return posed[: cfg.window_neighbours]
        scored: list[tuple[float, int, View]] = []
        for i, f in enumerate(others):
            if f.T_world_cam is None:
                continue
            dist = float(np.linalg.norm(f.T_world_cam[:3, 3] - view.T_world_cam[:3, 3]))
            z_a, z_b = f.T_world_cam[:3, 2], view.T_world_cam[:3, 2]
            angle = float(np.degrees(np.arccos(np.clip(z_a @ z_b, -1.0, 1.0))))
            if dist > cfg.neighbour_max_distance_m or angle > cfg.neighbour_max_angle_deg:
                continue
            if dist < cfg.neighbour_min_baseline_m and angle < 3.0:
                continue  # no parallax: useless for stereo
            scored.append((dist + angle / 45.0, -i, f))
        scored.sort(key=lambda s: (s[0], s[1]))
        return [f for _, _, f in scored[: cfg.window_neighbours]]
