"""A tiny recorded sequence folder (the ``recorded`` camera source's layout), written with OpenCV and numpy."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from protocol.poses import look_at

K = np.array([[50.0, 0.0, 15.5], [0.0, 52.0, 11.5], [0.0, 0.0, 1.0]])
"""The camera matrix written to camera-intrinsics.txt."""
SIZE = (32, 24)
"""Width x height of the written images."""


def pose_of(i: int) -> np.ndarray:
    """``T_world_cam`` of frame ``i``: the camera moves along world x, looking ahead and slightly down."""
    return look_at([float(i), 0.0, 1.5], [float(i), 3.0, 1.0])


def write_sequence(folder: Path, n: int = 3, meta: dict | None = None, ext: str = "png") -> Path:
    """``folder`` with ``n`` flat frames (grey level 10, 20, 30...), their poses, K and optionally meta.json."""
    frames = folder / "frames"
    frames.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(frames / f"frame-{i:06d}.color.{ext}"), np.full((SIZE[1], SIZE[0], 3), 10 * (i + 1), np.uint8))
        np.savetxt(frames / f"frame-{i:06d}.pose.txt", pose_of(i), fmt="%.9f")
    np.savetxt(folder / "camera-intrinsics.txt", K)
    if meta is not None:
        (folder / "meta.json").write_text(json.dumps(meta))
    return folder
