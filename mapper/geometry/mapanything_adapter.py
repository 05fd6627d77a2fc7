"""``mapanything`` reconstructor: an adapter around MapAnything (optional; never imported unless chosen).

MapAnything (``mapanything.models.MapAnything``) predicts, for N images in one forward pass, per-view ray
directions, depth along the rays, cam-to-world poses and a metric scaling factor: the factored form this
project's contract copies. The adapter passes known intrinsics and poses (OpenCV cam-to-world, metric)
when the views have them, and maps the outputs back. Weights come from a local directory or an already
populated Hugging Face cache: it never downloads (``local_files_only``).

Install: ``pip install "mapanything @ git+https://github.com/facebookresearch/map-anything"`` and fetch
weights once, e.g. ``huggingface-cli download facebook/map-anything-apache``.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry.contract import FactoredReconstruction, View
from protocol.messages import Intrinsics

INSTALL_HINT = (
    'install it with: pip install "mapanything @ git+https://github.com/facebookresearch/map-anything" '
    "(and torch); or choose the `mvs` reconstructor, which needs no weights"
)


class MapAnythingConfig(BaseModel):
    """Options of the ``mapanything`` reconstructor."""

    model_config = ConfigDict(extra="forbid")
    checkpoint: str = Field(
        default="facebook/map-anything-apache",
        description="local checkpoint directory, or a Hugging Face model id already in the local cache",
    )
    device: str = Field(default="cpu", description="torch device, e.g. cpu or cuda")
    use_known_intrinsics: bool = Field(default=True, description="pass View.intrinsics to the model")
    use_known_poses: bool = Field(default=True, description="pass View.T_world_cam priors to the model")
    use_amp: bool = Field(default=False, description="mixed precision inference (GPU)")
    outputs_already_scaled: bool = Field(
        default=True,
        description="MapAnything's depth and translations already include metric_scaling_factor; divide it "
        "out so the factored form is up to scale like the contract says",
    )
    infer_kwargs: dict[str, Any] = Field(default_factory=dict, description="extra keyword arguments for infer()")


def _import_mapanything() -> tuple[Any, Any | None]:
    try:
        models = importlib.import_module("mapanything.models")
    except ImportError as e:
        raise RuntimeError(f"the mapanything reconstructor needs the `mapanything` package: {INSTALL_HINT}") from e
    try:
        preprocess = importlib.import_module("mapanything.utils.image").preprocess_inputs
    except (ImportError, AttributeError):
        preprocess = None
    return models.MapAnything, preprocess


def _np(x: Any) -> np.ndarray:
    """Tensor or array to a float64 numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().float().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def quat_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) ordered x, y, z, w (scalar last)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


class MapAnythingReconstructor:
    """MapAnything behind the ``Reconstructor`` protocol (see module docstring)."""

    name = "mapanything"

    def __init__(self, **opts: Any) -> None:
        self.config = MapAnythingConfig(**opts)
        model_cls, self._preprocess = _import_mapanything()
        ckpt = self.config.checkpoint
        try:
            if Path(ckpt).exists():
                model = model_cls.from_pretrained(ckpt)
            else:
                model = model_cls.from_pretrained(ckpt, local_files_only=True)
        except Exception as e:  # the hub raises several types for a missing cache entry
            raise RuntimeError(
                f"MapAnything checkpoint {ckpt!r} is not available locally (no download is attempted): give a "
                f"local directory as `checkpoint`, or fetch it once with `huggingface-cli download {ckpt}`"
            ) from e
        self.model = model.to(self.config.device) if hasattr(model, "to") else model
        if hasattr(self.model, "eval"):
            self.model.eval()

    def _inputs(self, views: Sequence[View]) -> list[dict[str, Any]]:
        import torch

        give_poses = self.config.use_known_poses and views[0].T_world_cam is not None
        out = []
        for v in views:
            d: dict[str, Any] = {"img": torch.from_numpy(np.ascontiguousarray(v.image)).float()}
            if self.config.use_known_intrinsics and v.intrinsics is not None:
                d["intrinsics"] = torch.from_numpy(v.intrinsics.K()).float()
            if give_poses and v.T_world_cam is not None:
                d["camera_poses"] = torch.from_numpy(np.asarray(v.T_world_cam)).float()
                d["is_metric_scale"] = torch.tensor([True])
            out.append(d)
        return out

    def reconstruct(self, views: Sequence[View], targets: Sequence[int] | None = None) -> FactoredReconstruction:
        if not views:
            raise ValueError("reconstruct needs at least one view")
        inputs = self._inputs(views)
        poses_given = any("camera_poses" in d for d in inputs)
        if self._preprocess is not None:
            inputs = self._preprocess(inputs)
        kwargs: dict[str, Any] = {"use_amp": self.config.use_amp, **self.config.infer_kwargs}
        preds = self.model.infer(inputs, **kwargs)
        if len(preds) != len(views):
            raise RuntimeError(f"MapAnything returned {len(preds)} predictions for {len(views)} views")
        return factored_from_mapanything(preds, targets, self.config.outputs_already_scaled, poses_given)


def factored_from_mapanything(
    preds: Sequence[dict[str, Any]],
    targets: Sequence[int] | None = None,
    outputs_already_scaled: bool = True,
    poses_given: bool = False,
) -> FactoredReconstruction:
    """Map MapAnything's per-view prediction dicts (batch size 1 each) into the contract.

    Uses ``ray_directions`` (1, H, W, 3), ``depth_along_ray`` (1, H, W, 1), ``cam_trans`` (1, 3) +
    ``cam_quats`` (1, 4, x y z w) cam-to-world, ``metric_scaling_factor`` (1,), ``conf`` (1, H, W) and
    ``intrinsics`` (1, 3, 3) when present. Poses are re-expressed in the first view's frame. When the model
    was given world poses (``poses_given``), its world is ours and the first view's output pose is the anchor.
    """
    n = len(preds)
    want = set(range(n) if targets is None else targets)
    rays, depth, conf, T_w_c, intr = [], [], [], [], []
    scale = float(_np(preds[0].get("metric_scaling_factor", 1.0)).reshape(-1)[0])
    if not np.isfinite(scale) or scale <= 0:
        raise RuntimeError(f"MapAnything returned a bad metric scaling factor {scale}")
    div = scale if outputs_already_scaled else 1.0
    for i, p in enumerate(preds):
        r = _np(p["ray_directions"]).reshape(_np(p["ray_directions"]).shape[-3:])
        r = r / np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-12)
        h, w = r.shape[:2]
        d = _np(p["depth_along_ray"]).reshape(h, w) / div
        c = _np(p["conf"]).reshape(h, w) if "conf" in p else np.ones((h, w))
        # MapAnything's confidence is unbounded (>= 1); squash it into [0, 1).
        c = 1.0 - 1.0 / np.maximum(c, 1.0) if c.max() > 1.0 else np.clip(c, 0.0, 1.0)
        if "mask" in p:
            c = c * (_np(p["mask"]).reshape(h, w) > 0.5)
        if i not in want:
            c = np.zeros_like(c)
        if "camera_poses" in p:
            T = _np(p["camera_poses"]).reshape(4, 4)
        else:
            T = np.eye(4)
            T[:3, :3] = quat_xyzw_to_matrix(_np(p["cam_quats"]).reshape(4))
            T[:3, 3] = _np(p["cam_trans"]).reshape(3)
        if "intrinsics" in p:
            K = _np(p["intrinsics"]).reshape(3, 3)
        else:  # recover a pinhole from the rays of the centre row and column
            x, y = r[..., 0] / r[..., 2], r[..., 1] / r[..., 2]
            fx = (w - 1) / (x[h // 2, -1] - x[h // 2, 0])
            fy = (h - 1) / (y[-1, w // 2] - y[0, w // 2])
            K = np.array([[fx, 0, -x[h // 2, 0] * fx], [0, fy, -y[0, w // 2] * fy], [0, 0, 1]])
        rays.append(r.astype(np.float32))
        depth.append(np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32))
        conf.append(c.astype(np.float32))
        T_w_c.append(T)
        intr.append(Intrinsics(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                               cy=float(K[1, 2])))
    T_first_world = np.linalg.inv(T_w_c[0])
    T_first = np.stack([T_first_world @ T for T in T_w_c])
    T_first[:, :3, 3] /= div
    info: dict[str, Any] = {"backend": "mapanything", "metric_scaling_factor": scale, "pose_ok": [True] * n}
    if poses_given:
        info["T_world_first"] = T_w_c[0]
    return FactoredReconstruction(
        ray_dirs=np.stack(rays), depth_along_ray=np.stack(depth), T_first_cam=T_first, metric_scale=scale,
        confidence=np.stack(conf), intrinsics=intr, info=info,
    )
