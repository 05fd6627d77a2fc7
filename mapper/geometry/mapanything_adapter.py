"""``mapanything`` reconstructor: an adapter around MapAnything (optional; never imported unless chosen).

MapAnything (``mapanything.models.MapAnything``) predicts, for N images in one forward pass, per-view ray
directions, depth along the rays, cam-to-world poses and a metric scaling factor: the factored form this
project's contract copies. The adapter passes known intrinsics and poses (OpenCV cam-to-world, metric)
when the views have them, and maps the outputs back. Weights come from a local directory or an already
populated Hugging Face cache: it never downloads (``local_files_only``).

What the real package does (checked against mapanything 1.1 with random weights, tests/mapper/test_models_real.py):
given poses are only conditioning, expressed in view 0's frame; the returned poses are the model's own
prediction in its reference-view frame, NOT the input world frame. The adapter therefore keeps the given
poses (metric, relative to view 0) as the result, anchors at the given view-0 pose, and records the model's
prediction in ``info["predicted_T_first_cam"]``. The image encoder is DINOv2 built through ``torch.hub``:
its code must be in the torch hub cache (fetched once), and the adapter turns off the hub's pretrained
DINOv2 download because the checkpoint's weights replace them anyway.

Install: ``pip install "mapanything @ git+https://github.com/facebookresearch/map-anything"`` and fetch
once: weights, e.g. ``huggingface-cli download facebook/map-anything-apache``, and DINOv2's hub code,
``python -c "import torch; torch.hub.load('facebookresearch/dinov2', 'dinov2_vits14', pretrained=False)"``.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.geometry.contract import FactoredReconstruction, View, pixel_rays, z_to_ray_depth
from mapper.geometry.modelutil import ModelUnavailable, check_device, import_or_explain, load_pretrained
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
    models = import_or_explain("mapanything.models", "mapanything", INSTALL_HINT)
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


def _encoder_overrides(checkpoint: str) -> dict[str, Any]:
    """``from_pretrained`` keyword overrides that stop the DINOv2 encoder from downloading its ImageNet
    weights through torch.hub while the model is built (the checkpoint's weights replace them)."""
    cfg_path = Path(checkpoint).expanduser() / "config.json"
    if not cfg_path.is_file():
        try:
            from huggingface_hub import hf_hub_download

            cfg_path = Path(hf_hub_download(checkpoint, "config.json", local_files_only=True))
        except Exception:  # noqa: BLE001 - not cached (the hub raises several types): load_pretrained reports it
            return {}
    try:
        import json

        enc = json.loads(cfg_path.read_text())["encoder_config"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    if not isinstance(enc, dict) or "torch_hub_pretrained" in enc or not enc.get("uses_torch_hub"):
        return {}
    return {"encoder_config": {**enc, "torch_hub_pretrained": False}}


def _check_dinov2_hub_cache(checkpoint: str) -> None:
    """MapAnything builds DINOv2 from torch.hub's cached code; without it torch.hub would reach GitHub."""
    if not _encoder_overrides(checkpoint) and not (Path(checkpoint).expanduser() / "config.json").is_file():
        return  # no readable config: load_pretrained reports the missing checkpoint
    import torch

    hub = Path(torch.hub.get_dir())
    if not any((hub / f"facebookresearch_dinov2_{ref}" / "hubconf.py").is_file() for ref in ("main", "master")):
        raise ModelUnavailable(
            f"MapAnything's DINOv2 encoder code is not in the torch hub cache ({hub}); nothing is downloaded at run "
            "time: fetch it once with python -c \"import torch; torch.hub.load('facebookresearch/dinov2', "
            "'dinov2_vits14', pretrained=False)\" (or set TORCH_HOME to a directory holding "
            "hub/facebookresearch_dinov2_main)"
        )


class MapAnythingReconstructor:
    """MapAnything behind the ``Reconstructor`` protocol (see module docstring)."""

    name = "mapanything"

    def __init__(self, **opts: Any) -> None:
        self.config = MapAnythingConfig(**opts)
        model_cls, self._preprocess = _import_mapanything()
        ckpt = self.config.checkpoint
        device = check_device(self.config.device)
        _check_dinov2_hub_cache(ckpt)
        self.model = load_pretrained(model_cls, ckpt, "MapAnything", **_encoder_overrides(ckpt))
        if hasattr(self.model, "to"):
            self.model = self.model.to(device)
        if hasattr(self.model, "eval"):
            self.model.eval()

    def _inputs(self, views: Sequence[View]) -> list[dict[str, Any]]:
        import torch

        # all or none: MapAnything needs view 0 posed, and a mix gives the adapter nothing to pin
        give_poses = self.config.use_known_poses and all(v.T_world_cam is not None for v in views)
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
        given = [np.asarray(v.T_world_cam, dtype=np.float64) for v in views] if all(
            "camera_poses" in d for d in inputs) else None
        if self._preprocess is not None:
            inputs = self._preprocess(inputs)  # resizes to the patch grid and rescales the intrinsics
        given_K = [_np(d["intrinsics"]).reshape(3, 3) if "intrinsics" in d else None for d in inputs]
        kwargs: dict[str, Any] = {"use_amp": self.config.use_amp, **self.config.infer_kwargs}
        try:
            preds = self.model.infer(inputs, **kwargs)
        except Exception as e:  # noqa: BLE001 - invalid input combinations are ValueErrors from inside the package
            raise RuntimeError(f"MapAnything failed on {len(views)} views: {type(e).__name__}: {e}") from None
        if len(preds) != len(views):
            raise RuntimeError(f"MapAnything returned {len(preds)} predictions for {len(views)} views")
        return factored_from_mapanything(preds, targets, self.config.outputs_already_scaled, given, given_K)


def _intrinsics(K: np.ndarray, w: int, h: int) -> Intrinsics:
    return Intrinsics(width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]))


def _valid_K(K: np.ndarray) -> bool:
    return bool(np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0)


def factored_from_mapanything(
    preds: Sequence[dict[str, Any]],
    targets: Sequence[int] | None = None,
    outputs_already_scaled: bool = True,
    given_poses: Sequence[np.ndarray] | None = None,
    given_intrinsics: Sequence[np.ndarray | None] | None = None,
) -> FactoredReconstruction:
    """Map MapAnything's per-view prediction dicts (batch size 1 each) into the contract.

    Uses ``ray_directions`` (1, H, W, 3), ``depth_along_ray`` (1, H, W, 1), ``cam_trans`` (1, 3) +
    ``cam_quats`` (1, 4, x y z w) cam-to-world, ``metric_scaling_factor`` (1,), ``conf`` (1, H, W) and
    ``intrinsics`` (1, 3, 3) when present. Poses are re-expressed in the first view's frame. When the model
    was given world poses (``given_poses``, camera-to-world, metres) those are the result: MapAnything
    returns its own prediction in its reference-view frame, kept as ``info["predicted_T_first_cam"]``.
    Likewise given intrinsics (at the model's input resolution) are kept, the rays are theirs and the depth is
    the model's ``depth_z`` along them; predicted intrinsics that are not a valid pinhole give that view
    confidence 0 (``info["intrinsics_ok"]``).
    """
    n = len(preds)
    want = set(range(n) if targets is None else targets)
    rays, depth, conf, T_w_c, intr = [], [], [], [], []
    k_ok: list[bool] = []
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
        K_given = given_intrinsics[i] if given_intrinsics is not None else None
        if K_given is not None:
            K = np.asarray(K_given, dtype=np.float64)
            r = pixel_rays(_intrinsics(K, w, h)).astype(np.float64)
            if "depth_z" in p:
                d = z_to_ray_depth(_np(p["depth_z"]).reshape(h, w) / div, r.astype(np.float32)).astype(np.float64)
        elif "intrinsics" in p:
            K = _np(p["intrinsics"]).reshape(3, 3)
        else:  # recover a pinhole from the rays of the centre row and column
            x, y = r[..., 0] / r[..., 2], r[..., 1] / r[..., 2]
            fx = (w - 1) / (x[h // 2, -1] - x[h // 2, 0])
            fy = (h - 1) / (y[-1, w // 2] - y[0, w // 2])
            K = np.array([[fx, 0, -x[h // 2, 0] * fx], [0, fy, -y[0, w // 2] * fy], [0, 0, 1]])
        k_ok.append(_valid_K(K))
        if not k_ok[-1]:  # a placeholder pinhole (60 deg wide); this view's depth is not used
            K = np.array([[0.866 * w, 0, w / 2], [0, 0.866 * w, h / 2], [0, 0, 1]])
            c = np.zeros_like(c)
        rays.append(r.astype(np.float32))
        depth.append(np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32))
        conf.append(c.astype(np.float32))
        T_w_c.append(T)
        intr.append(_intrinsics(K, w, h))
    T_first_world = np.linalg.inv(T_w_c[0])
    predicted = np.stack([T_first_world @ T for T in T_w_c])
    predicted[:, :3, 3] /= div
    info: dict[str, Any] = {"backend": "mapanything", "metric_scaling_factor": scale, "pose_ok": [True] * n,
                            "intrinsics_ok": k_ok}
    T_first = predicted
    if given_poses is not None:
        G = [np.asarray(T, dtype=np.float64) for T in given_poses]
        T_first = np.stack([np.linalg.inv(G[0]) @ T for T in G])
        T_first[:, :3, 3] /= scale  # metres -> the factored form's units (compose multiplies the scale back)
        info["T_world_first"] = G[0]
        info["predicted_T_first_cam"] = predicted
    return FactoredReconstruction(
        ray_dirs=np.stack(rays), depth_along_ray=np.stack(depth), T_first_cam=T_first, metric_scale=scale,
        confidence=np.stack(conf), intrinsics=intr, info=info,
    )
