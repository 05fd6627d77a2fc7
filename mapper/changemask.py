"""Where a fixed camera's view changed since its last keyframes, passers-by left out (pure: no I/O).

A calibrated camera that never moves keyframes on image change (``mapper.keyframes``), and a person walking
through changes its image as much as a chair moved or taken away. With no stereo partner the keyframe goes to
single-view placement, which used to place every object of the view again: the same objects, from the very
view that placed them before, now cut by a passer-by (measured on the changes eval, apartment seed 1, RGB-only,
two people: single-view keyframes 2 -> 24, their placements 38 -> 457, wrong nodes 23 -> 34).

:class:`ChangeMask` keeps, per camera, a background: the keyframe selector's 32x24 grey thumbnail in which the
cells a person covers (the ORACLE or learnt 2D perception's people, ``fusion.people_labels``) keep their value
from before the person came. A new keyframe's changed cells are those that differ from the background by
``change_threshold`` and that no person covers now; the mapper places from one view only the detections that
touch them (``single_view.changed_only``). The others it placed before from this very pose. A chair moved
behind a passer-by shows as changed at the camera's first keyframe after the person left.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mapper.keyframes import thumbnail
from protocol.poses import rotation_angle_deg

GRID = (24, 32)  # (rows, cols) of the thumbnail


@dataclass
class _Background:
    T_world_cam: np.ndarray
    stamp_ns: int  # the newest keyframe learnt
    thumb: np.ndarray  # (24, 32) grey in [0, 1]; NaN where no keyframe has seen the cell without a person yet


def cells(mask: np.ndarray) -> np.ndarray:
    """(24, 32) bool: the thumbnail cells a (H, W) mask touches (at any resolution)."""
    return cv2.resize(mask.astype(np.float32), (GRID[1], GRID[0]), interpolation=cv2.INTER_AREA) > 0


def touches(mask: np.ndarray, changed: np.ndarray) -> bool:
    """Whether a (H, W) mask covers any of the ``changed`` (24, 32) cells."""
    return bool(np.any(cells(mask) & changed))


class ChangeMask:
    """Per-camera backgrounds; :meth:`update` says which cells of a new keyframe changed and learns it."""

    def __init__(self, change_threshold: float = 0.1, static_max_m: float = 0.01, static_max_deg: float = 0.5,
                 person_margin_cells: int = 1, max_sources: int = 64) -> None:
        self.change_threshold = change_threshold
        self.static_max_m = static_max_m
        self.static_max_deg = static_max_deg
        self.person_margin_cells = person_margin_cells
        self.max_sources = max_sources
        self._bg: dict[str, _Background] = {}

    def update(self, source_id: str, T_world_cam: np.ndarray, stamp_ns: int, image: np.ndarray,
               people: list[np.ndarray]) -> np.ndarray | None:
        """The (24, 32) changed cells of ``image`` (RGB, taken at ``stamp_ns``) against ``source_id``'s
        background, people (their masks) left out; None when there is no background for this pose (the camera's
        first keyframe, or it moved: everything is new), or the image is older than the background (a deferred
        keyframe retried: it learns nothing either). Then the background takes the image's cells that no person
        covers."""
        thumb = thumbnail(image)
        covered = np.zeros(GRID, bool)
        for m in people:
            covered |= cells(m)
        if covered.any() and self.person_margin_cells > 0:
            k = 2 * self.person_margin_cells + 1
            covered = cv2.dilate(covered.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        bg = self._bg.get(source_id)
        if bg is not None and stamp_ns < bg.stamp_ns:
            return None
        if bg is not None and not self._same_pose(bg.T_world_cam, T_world_cam):
            bg = None
        if bg is None:
            changed = None
            bg = _Background(T_world_cam.copy(), stamp_ns, np.full(GRID, np.nan, np.float32))
        else:
            # never seen without a person: new, unless a person covers it now
            changed = ~(np.abs(thumb - bg.thumb) < self.change_threshold) & ~covered
        bg.thumb = np.where(covered, bg.thumb, thumb).astype(np.float32)
        bg.stamp_ns = stamp_ns
        self._bg.pop(source_id, None)
        self._bg[source_id] = bg  # newest last
        while len(self._bg) > self.max_sources:
            del self._bg[next(iter(self._bg))]
        return changed

    def _same_pose(self, a: np.ndarray, b: np.ndarray) -> bool:
        return (float(np.linalg.norm(a[:3, 3] - b[:3, 3])) <= self.static_max_m
                and rotation_angle_deg(a, b) <= self.static_max_deg)
