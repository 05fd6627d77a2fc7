"""What changed in a fixed camera's view since its last keyframes, passers-by left out (pure: no I/O).

A calibrated camera that never moves keyframes on image change (``mapper.keyframes``), and a person walking
through changes its image as much as a chair moved or taken away. With no stereo partner the keyframe goes to
single-view placement, which used to place every object of the view again: the same objects, from the very
view that placed them before, now cut by a passer-by (measured on the changes eval, apartment seed 1, RGB-only,
two people: single-view keyframes 2 -> 24, their placements 38 -> 457, wrong nodes 23 -> 34).

:class:`ChangeMask` keeps, per camera, a background: a small colour image (160 px wide) of its view in which the
pixels a person covers (2D perception's people, ``fusion.people_labels``) keep their value from before the
person came. A detection of a new keyframe has changed (:meth:`Changes.touches`) when at least ``min_share`` of
its pixels that no person covers differ from the background by ``threshold`` (in any colour channel, 0..1), or
most of them were never seen without a person. The mapper places from one view only the detections that
changed (``single_view.changed_only``): the others it placed before from this very pose. A chair moved behind
a passer-by shows as changed at the camera's first keyframe after the person left. A bag put down on a floor of
the same grey changes the grey thumbnail the keyframe selector watches by less than its threshold, but not its
colour. Only single-view keyframes learn the background (``MapperCore._learn_changes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from protocol.poses import rotation_angle_deg

WIDTH = 160  # background width, px


def small_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A (H, W) bool mask at the background's (h, w): the pixels it covers at least half of (any, for a mask
    smaller than one of them)."""
    if mask.shape == shape:
        return mask.astype(bool)
    share = cv2.resize(mask.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    out = share >= 0.5
    return out if out.any() else share > 0


@dataclass(frozen=True)
class Changes:
    """A keyframe against its camera's background: ``diff`` (h, w) the largest colour-channel difference per
    pixel (0..1; NaN where the background never saw it without a person), ``people`` (h, w) where people are
    now."""

    diff: np.ndarray
    people: np.ndarray
    threshold: float = 0.1
    min_share: float = 0.2

    def touches(self, mask: np.ndarray) -> bool:
        """Whether the object of ``mask`` (any size) changed: see the module docstring."""
        m = small_mask(mask, self.diff.shape) & ~self.people
        n = int(m.sum())
        if n == 0:
            return False  # all behind a person now: seen before or not, nothing to place from here
        d = self.diff[m]
        unknown = np.isnan(d)
        if int(unknown.sum()) > n // 2:
            return True
        return int((d[~unknown] >= self.threshold).sum()) >= self.min_share * n


@dataclass
class _Background:
    T_world_cam: np.ndarray
    stamp_ns: int  # the newest keyframe learnt
    image: np.ndarray  # (h, w, 3) float32 in 0..1; NaN where no keyframe saw it without a person yet


class ChangeMask:
    """Per-camera backgrounds; :meth:`update` says what changed in a new keyframe and learns it."""

    def __init__(self, threshold: float = 0.1, min_share: float = 0.2, static_max_m: float = 0.01,
                 static_max_deg: float = 0.5, person_margin_px: int = 2, max_sources: int = 64) -> None:
        self.threshold = threshold
        self.min_share = min_share
        self.static_max_m = static_max_m
        self.static_max_deg = static_max_deg
        self.person_margin_px = person_margin_px
        self.max_sources = max_sources
        self._bg: dict[str, _Background] = {}

    def update(self, source_id: str, T_world_cam: np.ndarray, stamp_ns: int, image: np.ndarray,
               people: list[np.ndarray]) -> Changes | None:
        """``image`` (RGB, taken at ``stamp_ns``) against ``source_id``'s background, people (their masks) left
        out; None when there is no background for this pose (the camera's first keyframe, or it moved:
        everything is new), or the image is older than the background (a deferred keyframe retried: it learns
        nothing either). Then the background takes the image's pixels that no person covers."""
        h, w = image.shape[:2]
        shape = (max(1, round(h * WIDTH / w)), WIDTH)
        now = cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        covered = np.zeros(shape, bool)
        for m in people:
            covered |= small_mask(m, shape)
        if covered.any() and self.person_margin_px > 0:
            k = 2 * self.person_margin_px + 1
            covered = cv2.dilate(covered.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        bg = self._bg.get(source_id)
        if bg is not None and stamp_ns < bg.stamp_ns:
            return None
        if bg is not None and (not self._same_pose(bg.T_world_cam, T_world_cam) or bg.image.shape[:2] != shape):
            bg = None
        changes = None
        if bg is None:
            bg = _Background(T_world_cam.copy(), stamp_ns, np.full((*shape, 3), np.nan, np.float32))
        else:
            changes = Changes(np.abs(now - bg.image).max(axis=2), covered, self.threshold, self.min_share)
        bg.image = np.where(covered[..., None], bg.image, now)
        bg.stamp_ns = stamp_ns
        self._bg.pop(source_id, None)
        self._bg[source_id] = bg  # newest last
        while len(self._bg) > self.max_sources:
            del self._bg[next(iter(self._bg))]
        return changes

    def _same_pose(self, a: np.ndarray, b: np.ndarray) -> bool:
        return (float(np.linalg.norm(a[:3, 3] - b[:3, 3])) <= self.static_max_m
                and rotation_angle_deg(a, b) <= self.static_max_deg)
