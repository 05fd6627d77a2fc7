"""``oracle`` reconstructor: true depth and poses from the simulator (the paper's "CG" baseline).

It reads only ``View.oracle`` (ORACLE ground truth that simulated sources publish beside their frames)
and returns it through the same factored contract as every other backend.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry.contract import FactoredReconstruction, View, factored_from_metric
from protocol.messages import Intrinsics


class OracleConfig(BaseModel):
    """Options of the ``oracle`` reconstructor."""

    model_config = ConfigDict(extra="forbid")
    width: int | None = Field(
        default=None, ge=2, description="output width in pixels (height keeps the aspect); None = full size"
    )


def resize_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-pixel resampling that never blends values across depth or id edges."""
    h, w = image.shape[:2]
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return image[rows[:, None], cols[None, :]]


class OracleReconstructor:
    """Depth and poses straight from the simulator's ORACLE truth."""

    name = "oracle"

    def __init__(self, **opts: Any) -> None:
        self.config = OracleConfig(**opts)

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        if not views:
            raise ValueError("reconstruct needs at least one view")
        want = set(range(len(views)) if targets is None else targets)
        depths, poses, confs, intr = [], [], [], []
        for i, v in enumerate(views):
            if v.oracle is None:
                raise ValueError(f"view {i} ({v.source_id}) has no ORACLE data; the oracle backend needs sim frames")
            h, w = v.image.shape[:2]
            k = v.intrinsics or _missing_intrinsics(v)
            ow = self.config.width or w
            oh = max(1, round(h * ow / w))
            d = v.oracle.depth_m.astype(np.float32)
            if (ow, oh) != (w, h):
                d = resize_nearest(d, ow, oh)
                k = k.scaled(ow, oh)
            valid = np.isfinite(d) & (d > 0)
            d = np.where(valid, d, 0.0).astype(np.float32)
            conf = valid.astype(np.float32) if i in want else np.zeros_like(d)
            depths.append(d)
            confs.append(conf)
            poses.append(np.asarray(v.oracle.T_world_cam_true, dtype=np.float64))
            intr.append(k)
        recon = factored_from_metric(depths, poses, confs, intr, info={"backend": self.name})
        recon.info["T_world_first"] = poses[0]
        recon.info["pose_ok"] = [True] * len(views)
        return recon


def _missing_intrinsics(v: View) -> Intrinsics:
    raise ValueError(f"view {v.source_id} has no intrinsics; the oracle backend needs them")
