"""``da3`` reconstructor: Depth Anything 3 (optional extra ``da3``; never imported unless chosen).

``depth_anything_3.api.DepthAnything3.inference(images, extrinsics, intrinsics)`` predicts per view a
z-depth map, a confidence and world-to-camera extrinsics (OpenCV axes) at its processing resolution
(longest side ``process_res``, a multiple of the 14-pixel patch: any input size is resized by the
package). Given the views' pose priors (as world-to-camera) and intrinsics, DA3 conditions on them, keeps
the given poses and rescales its depth to their units (metres): the result is metric. With fewer than 3
posed views DA3's own Umeyama alignment is degenerate, so the adapter runs unposed and scales the depth
by the ratio of the prior baseline to the predicted one (2 views), or leaves it unscaled (1 view).
Without priors the poses are DA3's own, relative to view 0, up to an unknown scale (``info["metric"]``
False).

Weights (Apache-2.0 sizes: DA3-SMALL, DA3-BASE; the LARGE/GIANT ones are CC BY-NC) come from a local
directory or an already populated Hugging Face cache; nothing is downloaded at run time.
Install: ``pip install -e '.[da3]'`` then ``huggingface-cli download depth-anything/DA3-BASE``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry.contract import FactoredReconstruction, View, factored_from_metric
from mapper.geometry.modelutil import ModelUnavailable, check_device, import_or_explain, load_pretrained
from protocol.messages import Intrinsics

INSTALL = "pip install 'argus-scenegraph[da3]' (Depth Anything 3), or choose the `mvs` reconstructor"


class Da3Config(BaseModel):
    """Options of the ``da3`` reconstructor."""

    model_config = ConfigDict(extra="forbid")
    checkpoint: str = Field(
        default="depth-anything/DA3-BASE",
        description="local checkpoint directory (save_pretrained layout), or a Hugging Face id already in the cache",
    )
    device: str = Field(default="cpu", description="torch device, e.g. cpu or cuda")
    process_res: int = Field(default=504, ge=56, le=2016, description="longest side DA3 works at (pixels)")
    use_known_poses: bool = Field(default=True, description="condition on View.T_world_cam priors")
    use_known_intrinsics: bool = Field(default=True, description="condition on View.intrinsics")
    min_posed_views: int = Field(
        default=3, ge=3, description="posed views needed to hand poses to DA3 (its scale alignment needs 3)"
    )


def _conf01(c: np.ndarray) -> np.ndarray:
    """DA3's confidence is >= 1 and unbounded: squash it into [0, 1) like MapAnything's."""
    c = np.nan_to_num(np.asarray(c, dtype=np.float64), nan=0.0)
    return np.where(c > 1.0, 1.0 - 1.0 / np.maximum(c, 1.0), np.clip(c, 0.0, 1.0))


def _w2c_to_T(ext: np.ndarray) -> np.ndarray:
    """(N, 3|4, 4) world-to-camera -> (N, 4, 4) camera-to-world."""
    ext = np.asarray(ext, dtype=np.float64)
    T = np.tile(np.eye(4), (len(ext), 1, 1))
    T[:, :3, :] = ext[:, :3, :]
    return np.linalg.inv(T)


class Da3Reconstructor:
    """Depth Anything 3 behind the ``Reconstructor`` protocol (see module docstring)."""

    name = "da3"

    def __init__(self, **opts: Any) -> None:
        self.config = cfg = Da3Config(**opts)
        torch = import_or_explain("torch", "da3", INSTALL)
        api = import_or_explain("depth_anything_3.api", "da3", INSTALL)
        device = check_device(cfg.device)
        self.model = load_pretrained(api.DepthAnything3, cfg.checkpoint, "Depth Anything 3").to(device).eval()
        self._torch = torch

    def _priors(self, views: Sequence[View]) -> tuple[np.ndarray | None, np.ndarray | None]:
        cfg = self.config
        K = None
        if cfg.use_known_intrinsics and all(v.intrinsics is not None for v in views):
            K = np.stack([v.intrinsics.K() for v in views if v.intrinsics is not None]).astype(np.float64)
        ext = None
        if cfg.use_known_poses and K is not None and all(v.T_world_cam is not None for v in views):
            ext = np.stack([np.linalg.inv(np.asarray(v.T_world_cam)) for v in views])
        return K, ext

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        if not views:
            raise ValueError("reconstruct needs at least one view")
        K, ext = self._priors(views)
        posed = ext is not None and len(views) >= self.config.min_posed_views
        images = [np.ascontiguousarray(v.image) for v in views]
        kwargs: dict[str, Any] = {"process_res": self.config.process_res, "ref_view_strategy": "first"}
        with self._torch.inference_mode():
            try:
                pred = self.model.inference(
                    images, extrinsics=ext if posed else None, intrinsics=K if posed else None, **kwargs
                )
            except Exception as e:  # noqa: BLE001 - a degenerate pose alignment inside the package, a shape it rejects, ...
                raise RuntimeError(f"Depth Anything 3 failed on {len(views)} views: {type(e).__name__}: {e}") from None
        depth = np.asarray(pred.depth, dtype=np.float64)
        n, h, w = depth.shape
        if n != len(views):
            raise RuntimeError(f"Depth Anything 3 returned {n} depth maps for {len(views)} views")
        T_w_c = _w2c_to_T(pred.extrinsics)
        intr = [Intrinsics(width=w, height=h, fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]),
                           cy=float(k[1, 2])) for k in np.asarray(pred.intrinsics, dtype=np.float64)]
        metric = posed
        if not posed and ext is not None:  # 1-2 posed views: keep the priors, scale by the baseline
            T_prior = _w2c_to_T(ext)
            scale = _baseline_ratio(T_prior, T_w_c)
            if scale is not None:
                depth = depth * scale
                metric = True
            T_w_c = T_prior
        conf = _conf01(pred.conf)
        ok = np.isfinite(depth) & (depth > 0)
        conf = np.where(ok, conf, 0.0)
        want = set(range(n) if targets is None else targets)
        for i in range(n):
            if i not in want:
                conf[i] = 0.0
        info: dict[str, Any] = {"backend": "da3", "metric": metric, "posed_input": posed, "pose_ok": [True] * n}
        if ext is not None:
            info["T_world_first"] = T_w_c[0]
        return factored_from_metric(
            list(np.where(ok, depth, 0.0)), list(T_w_c), list(conf), intr, info
        )


def _baseline_ratio(T_prior: np.ndarray, T_pred: np.ndarray) -> float | None:
    """Metres per predicted unit from the baseline between view 0 and the farthest view (None: one view or
    a degenerate prediction)."""
    if len(T_prior) < 2:
        return None
    d_prior = np.linalg.norm(T_prior[1:, :3, 3] - T_prior[0, :3, 3], axis=1)
    j = int(np.argmax(d_prior))
    d_pred = float(np.linalg.norm(T_pred[j + 1, :3, 3] - T_pred[0, :3, 3]))
    if d_prior[j] < 1e-6 or not np.isfinite(d_pred) or d_pred < 1e-9:
        return None
    return float(d_prior[j] / d_pred)


__all__ = ["Da3Config", "Da3Reconstructor", "ModelUnavailable"]
