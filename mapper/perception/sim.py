"""``sim`` 2D perception: the simulator's semantic camera. AN ORACLE for 2D masks and labels.

Like Habitat's semantic sensor, it reads the rendered instance ids and object labels that simulated
sources publish beside their frames (``View.oracle`` / ``OracleFrame``). Geometry does NOT come from
here: the chosen reconstructor still provides depth and poses. Use it to evaluate geometry and fusion
without perception errors, never on real cameras.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mapper.perception.base import Detection, Mask2D, ViewGeometry, label_descriptor

if TYPE_CHECKING:
    from mapper.geometry.contract import View


class OracleMissing(ValueError):
    """A view without ORACLE data reached the ``sim`` backend (it only works on simulated frames)."""


class SimSegmenterConfig(BaseModel):
    """Options of the ``sim`` (ORACLE) segmenter."""

    model_config = ConfigDict(extra="forbid")
    min_pixels: int = Field(default=30, ge=1, description="instances covering fewer pixels are ignored")


class SimSegmenter:
    """ORACLE instance masks from the simulator's rendered instance ids."""

    name = "sim"
    description = "ORACLE 2D perception: the simulator's instance-id render (simulated frames only)"

    def __init__(self, **opts: object) -> None:
        self.config = SimSegmenterConfig.model_validate(opts)

    def segment(self, view: View, geometry: ViewGeometry | None = None) -> list[Mask2D]:
        if view.oracle is None or view.oracle.instance_id is None:
            raise OracleMissing(f"view {view.source_id}#{view.seq} has no ORACLE instance ids")
        ids = np.asarray(view.oracle.instance_id)
        labels = view.oracle.labels
        uniq, counts = np.unique(ids[ids > 0], return_counts=True)
        return [
            Mask2D(mask=ids == k, instance_key=int(k), hint_label=labels.get(int(k), "object"))
            for k, c in zip(uniq.tolist(), counts.tolist(), strict=True)
            if c >= self.config.min_pixels
        ]


class SimEmbedderConfig(BaseModel):
    """Options of the ``sim`` (ORACLE) embedder."""

    model_config = ConfigDict(extra="forbid")
    descriptor_dim: int = Field(default=128, ge=8, le=4096, description="length of the label descriptor")


class SimEmbedder:
    """ORACLE labels: the mask's object label (its hint, or the majority instance id under it).

    The descriptor is a hashed embedding of the label text, so equal labels are similar.
    """

    name = "sim"
    description = "ORACLE 2D perception: object labels from the simulator (simulated frames only)"

    def __init__(self, **opts: object) -> None:
        self.config = SimEmbedderConfig.model_validate(opts)

    def _label_of(self, view: View, m: Mask2D) -> str | None:
        if m.hint_label is not None:
            return m.hint_label
        if view.oracle is None or view.oracle.instance_id is None:
            raise OracleMissing(f"view {view.source_id}#{view.seq} has no ORACLE instance ids")
        ids = np.asarray(view.oracle.instance_id)
        mask = m.mask
        if mask.shape != ids.shape:
            from mapper.fusion import resize_mask

            mask = resize_mask(mask, *ids.shape)
        under = ids[mask]
        under = under[under > 0]
        if len(under) == 0:
            return None  # structure: the oracle has no object here
        k = int(np.bincount(under).argmax())
        return view.oracle.labels.get(k, "object")

    def embed(self, view: View, masks: Sequence[Mask2D]) -> list[Detection]:
        out = []
        for m in masks:
            label = self._label_of(view, m)
            if label is None:
                continue
            out.append(
                Detection(
                    mask=m.mask,
                    label=label,
                    confidence=1.0,
                    descriptor=label_descriptor(label, self.config.descriptor_dim),
                    instance_key=m.instance_key,
                )
            )
        return out
