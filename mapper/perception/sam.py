"""``sam`` segmenter: SAM / MobileSAM automatic masks from a LOCAL checkpoint (optional extra).

Needs ``segment-anything`` (``pip install 'argus-scenegraph[sam]'``) or ``mobile_sam``, and a
checkpoint file on disk; nothing is ever downloaded. The package is imported only when this backend is
built.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.perception.base import Mask2D, ViewGeometry

if TYPE_CHECKING:
    from mapper.geometry.contract import View


class BackendUnavailable(RuntimeError):
    """An optional perception backend cannot be built (package or weights missing)."""


class SamConfig(BaseModel):
    """Options of the ``sam`` segmenter."""

    model_config = ConfigDict(extra="forbid")
    package: Literal["segment_anything", "mobile_sam"] = Field(
        default="segment_anything", description="python package providing the SAM model registry"
    )
    model_type: str = Field(default="vit_b", description="registry key: vit_b, vit_l, vit_h, or vit_t (MobileSAM)")
    checkpoint: Path | None = Field(default=None, description="local checkpoint file (required)")
    random_init: bool = Field(
        default=False, description="TESTS ONLY: build the architecture with random weights, no checkpoint"
    )
    points_per_side: int = Field(default=16, ge=2, le=64, description="automatic mask generator grid")
    pred_iou_thresh: float = Field(default=0.86, ge=0.0, le=1.0, description="mask quality threshold")
    stability_score_thresh: float = Field(default=0.9, ge=0.0, le=1.0, description="mask stability threshold")
    min_mask_region_area: int = Field(default=50, ge=0, description="drop smaller regions (pixels)")
    device: str = Field(default="cpu", description="torch device")


def _import(package: str) -> Any:
    import importlib

    try:
        return importlib.import_module(package)
    except RuntimeError as e:  # e.g. a CUDA torchvision beside a CPU torch
        raise BackendUnavailable(
            f"the 'sam' segmenter's package {package!r} fails to import: {str(e).splitlines()[0][:200]} "
            "(install the torchvision build that matches your torch)"
        ) from None
    except ImportError as e:
        raise BackendUnavailable(
            f"the 'sam' segmenter needs the optional package {package!r} ({e}); install it with "
            "pip install 'argus-scenegraph[sam]' (segment-anything) and pass a local checkpoint with "
            "--set perception.segmenter_options.checkpoint=PATH, or use --segmenter classical"
        ) from None


def usable_device(device: str) -> str:
    """``device`` if torch can use it here, else ``BackendUnavailable`` (e.g. cuda without a GPU)."""
    from mapper.geometry.modelutil import ModelUnavailable, check_device

    try:
        return check_device(device)
    except ModelUnavailable as e:
        raise BackendUnavailable(str(e)) from None


class SamSegmenter:
    """SAM automatic mask generation on the full image."""

    name = "sam"
    description = "SAM / MobileSAM automatic masks (optional extra, local checkpoint)"

    def __init__(self, **opts: object) -> None:
        self.config = cfg = SamConfig.model_validate(opts)
        mod = _import(cfg.package)
        if cfg.checkpoint is None and not cfg.random_init:
            raise BackendUnavailable(
                "the 'sam' segmenter needs a local checkpoint: --set perception.segmenter_options.checkpoint=PATH "
                "(nothing is downloaded)"
            )
        if cfg.checkpoint is not None and not cfg.checkpoint.is_file():
            raise BackendUnavailable(f"SAM checkpoint {cfg.checkpoint} does not exist")
        if cfg.model_type not in mod.sam_model_registry:
            have = sorted(mod.sam_model_registry)
            raise BackendUnavailable(f"unknown SAM model type {cfg.model_type!r}; have {have}")
        usable_device(cfg.device)
        model = mod.sam_model_registry[cfg.model_type](checkpoint=None if cfg.random_init else str(cfg.checkpoint))
        model.to(cfg.device).eval()
        self._generator = mod.SamAutomaticMaskGenerator(
            model,
            points_per_side=cfg.points_per_side,
            pred_iou_thresh=cfg.pred_iou_thresh,
            stability_score_thresh=cfg.stability_score_thresh,
            min_mask_region_area=cfg.min_mask_region_area,
        )

    def segment(self, view: View, geometry: ViewGeometry | None = None) -> list[Mask2D]:
        import torch

        with torch.inference_mode():
            found = self._generator.generate(np.ascontiguousarray(view.image))
        found.sort(key=lambda r: -float(r.get("area", 0)))
        return [
            Mask2D(
                mask=np.asarray(r["segmentation"], dtype=bool), instance_key=i, score=float(r.get("predicted_iou", 1))
            )
            for i, r in enumerate(found)
        ]
