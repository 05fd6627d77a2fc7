"""Is a single-view placement hidden behind what the same view measured around it? (pure numpy + OpenCV)

A mask placed from where it seems to touch the floor (``mapper.geometry.singleview``) can be placed far
too deep: a monitor on a desk whose lowest pixels are read as floor contacts lands metres behind the wall.
The keyframe's own stereo depth says where the scene around the mask is: an object seen in front of the
wall cannot be behind it. ``behind_background`` compares the depth of the placed box along the mask's rays
with the confident depth of a ring of pixels around the mask; when the box lies farther than nearly all of
its surroundings (a high quantile, so that occluders in front do not count), the placement contradicts the
view and is refused. Without enough confident depth around the mask nothing is said (False).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from mapper.geometry.singleview import PlacedBox, layout_depth

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


def ring_depths(mask: np.ndarray, depth_m: F32, confidence: F32, min_confidence: float, ring_px: int) -> F32:
    """Confident depths (metres) of the pixels within ``ring_px`` of the mask, the mask itself left out."""
    k = 2 * int(ring_px) + 1
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    ring = grown & ~mask
    d, c = depth_m[ring], confidence[ring]
    return np.asarray(d[np.isfinite(d) & (d > 0) & (c >= min_confidence)], np.float32)


def behind_background(box: PlacedBox, mask: np.ndarray, depth_m: F32, confidence: F32, K: F64,
                      T_world_cam: F64, *, min_confidence: float, ring_px: int = 8, quantile: float = 0.9,
                      margin_m: float = 0.3, min_ring_px: int = 30) -> bool:
    """True when ``box`` (placed for ``mask``; mask and depth at the resolution of ``K``) lies, along the
    mask's rays (median), more than ``margin_m`` behind the ``quantile`` of the confident depth around the
    mask. False when fewer than ``min_ring_px`` ring pixels have confident depth."""
    around = ring_depths(mask, depth_m, confidence, min_confidence, ring_px)
    if len(around) < min_ring_px:
        return False
    placed, _ = layout_depth([mask], [box], K, T_world_cam)
    on_mask = placed[mask & (placed > 0)]
    if len(on_mask) == 0:
        return False
    return bool(np.median(on_mask) > np.quantile(around, quantile) + margin_m)
