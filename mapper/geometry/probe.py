"""``probe`` reconstructor: RGB-only ``mvs`` with ORACLE true depth put in at chosen pixels (sim only).

A diagnostic, never a product backend: it tells which of the RGB-only depth's failings costs the scene
graph its accuracy. It runs ``mvs`` as usual (poses, depth, confidence) and then, in the views that need
dense depth, replaces the depth of one class of pixels by the simulator's true depth (``View.oracle``):

- ``confident``: pixels ``mvs`` is confident about get their true depth (confidence kept): what would
  perfectly accurate depth on the same coverage give?
- ``unconfident``: pixels without confident depth get the true depth at full confidence: what would full
  coverage give, with ``mvs``'s errors kept where it measured?
- ``objects``: as ``unconfident``, on object pixels only (the ORACLE instance ids): is it the objects'
  coverage that matters or the room's?
- ``uncovered``: as ``unconfident``, on pixels that no other view of the window sees (true poses): what is
  lost to source views that do not overlap the keyframe's edges?

Everything after the reconstruction (depth check, lifting, fusion) is the RGB-only pipeline's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.consistency import DepthMap, coverage_count
from mapper.geometry.contract import FactoredReconstruction, View, pixel_rays, z_to_ray_depth
from mapper.geometry.mvs import MvsReconstructor
from mapper.geometry.oracle import resize_nearest
from protocol.messages import Intrinsics

TruthAt = Literal["confident", "unconfident", "objects", "uncovered"]


class ProbeConfig(BaseModel):
    """Options of the ``probe`` reconstructor (ORACLE diagnostics)."""

    model_config = ConfigDict(extra="forbid")
    truth_at: TruthAt = Field(default="unconfident", description="which pixels get their true depth (see module)")
    min_confidence: float = Field(
        default=0.3, ge=0.0, le=1.0, description="mvs confidence that counts as confident (the fusion's threshold)"
    )


def covered_by_others(depth_m: np.ndarray, K_out: np.ndarray, T_world_cam: np.ndarray,
                      others: Sequence[tuple[np.ndarray, np.ndarray, tuple[int, int]]]) -> np.ndarray:
    """(h, w) bool: the pixel's 3D point (z-depth ``depth_m``; 0 or non-finite: never covered) projects in
    front of and inside at least one of ``others`` (K (3, 3), T_world_cam (4, 4), (width, height)).

    The depth check's ``coverage_count`` against frames that have depth everywhere: inside a frame is covered."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    frames = [DepthMap(np.ones((oh, ow), np.float32), np.asarray(K, np.float64), np.asarray(T, np.float64))
              for K, T, (ow, oh) in others]
    d = np.where(valid, depth_m, 0.0).astype(np.float32)
    return (coverage_count(d, K_out, T_world_cam, frames) > 0) & valid


def truth_mask(truth_at: TruthAt, confident: np.ndarray, true_depth: np.ndarray, instance_id: np.ndarray | None,
               covered: np.ndarray | None) -> np.ndarray:
    """The pixels whose depth the probe replaces (only where the true depth exists)."""
    has_truth = np.isfinite(true_depth) & (true_depth > 0)
    if truth_at == "confident":
        return confident & has_truth
    sel = ~confident & has_truth
    if truth_at == "objects":
        if instance_id is None:
            raise ValueError("probe truth_at='objects' needs ORACLE instance ids")
        sel &= instance_id >= 1
    elif truth_at == "uncovered":
        if covered is None:
            raise ValueError("probe truth_at='uncovered' needs the coverage mask")
        sel &= ~covered
    return sel


class ProbeReconstructor:
    """``mvs`` with ORACLE true depth substituted at the pixels ``truth_at`` names (diagnostics only)."""

    name = "probe"

    def __init__(self, **opts: Any) -> None:
        self.config = ProbeConfig(**opts)
        self.mvs = MvsReconstructor()  # the default RGB-only reconstructor, whose losses the probe measures
        self.counters: dict[str, int] = {"probe_pixels_replaced": 0}

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        recon = self.mvs.reconstruct(views, targets)
        want = range(len(views)) if targets is None else targets
        depth = recon.depth_along_ray.copy()
        conf = recon.confidence.copy()
        for i in want:
            o = views[i].oracle
            if o is None:
                raise ValueError(f"view {i} ({views[i].source_id}) has no ORACLE data; the probe needs sim frames")
            k: Intrinsics = recon.intrinsics[i]
            rays = pixel_rays(k)
            true_z = resize_nearest(np.asarray(o.depth_m, dtype=np.float64), k.width, k.height)
            ids = None if o.instance_id is None else resize_nearest(o.instance_id, k.width, k.height)
            confident = conf[i] >= self.config.min_confidence
            covered = None
            if self.config.truth_at == "uncovered":
                others = []
                for j, (vj, kj) in enumerate(zip(views, recon.intrinsics, strict=True)):
                    if j != i and vj.oracle is not None:
                        others.append((kj.K(), np.asarray(vj.oracle.T_world_cam_true, dtype=np.float64),
                                       (kj.width, kj.height)))
                covered = covered_by_others(true_z, k.K(), np.asarray(o.T_world_cam_true, dtype=np.float64), others)
            sel = truth_mask(self.config.truth_at, confident, true_z, ids, covered)
            # depth_along_ray is in the reconstruction's units (metres / metric_scale)
            depth[i] = np.where(sel, z_to_ray_depth(true_z, rays) / recon.metric_scale, depth[i])
            if self.config.truth_at != "confident":
                conf[i] = np.where(sel, 1.0, conf[i])
            self.counters["probe_pixels_replaced"] += int(sel.sum())
        info = dict(recon.info, probe=self.config.truth_at)
        return replace(recon, depth_along_ray=depth.astype(np.float32), confidence=conf.astype(np.float32), info=info)
