"""Registries of 2D perception backends: each name has a factory and a pydantic options model.

Segmenters: ``sim`` (ORACLE: the simulator's semantic camera), ``classical`` (no weights), ``detector``
(bundled closed-set SSD, 24 classes, CPU), ``sam`` (optional extra). Embedders: ``sim`` (ORACLE labels),
``classical`` (appearance, label ``object``), ``detector`` (the detector segmenter's classes), ``clip``
(optional extra). ``perception.segmenter_options`` / ``embedder_options`` of the mapper config are
validated against the chosen backend's model when the config loads; heavy imports (segment_anything,
open_clip) happen only inside the chosen backend. Third parties add backends through the entry-point
groups ``argus.segmenters`` and ``argus.embedders`` (name -> ``module:Class``).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from mapper.perception.base import Embedder, Segmenter
from protocol.plugins import FactoryRegistry

SEGMENTERS = FactoryRegistry("segmenter", {
    "sim": ("mapper.perception.sim:SimSegmenter", "mapper.perception.sim:SimSegmenterConfig"),
    "classical": ("mapper.perception.classical:ClassicalSegmenter",
                  "mapper.perception.classical:ClassicalSegmenterConfig"),
    "sam": ("mapper.perception.sam:SamSegmenter", "mapper.perception.sam:SamConfig"),
    "detector": ("mapper.perception.detector:DetectorSegmenter", "mapper.perception.detector:DetectorConfig"),
}, "argus.segmenters")
EMBEDDERS = FactoryRegistry("embedder", {
    "sim": ("mapper.perception.sim:SimEmbedder", "mapper.perception.sim:SimEmbedderConfig"),
    "classical": ("mapper.perception.classical:AppearanceEmbedder",
                  "mapper.perception.classical:AppearanceEmbedderConfig"),
    "clip": ("mapper.perception.clip:ClipEmbedder", "mapper.perception.clip:ClipConfig"),
    "detector": ("mapper.perception.detector:DetectorEmbedder", "mapper.perception.detector:DetectorEmbedderConfig"),
}, "argus.embedders")
ORACLE_BACKENDS = frozenset({"sim"})
"""Backends that read simulator ground truth (ORACLE); the mapper subscribes to oracle keys for them."""


def make_segmenter(name: str = "classical", options: BaseModel | None = None, **opts: Any) -> Segmenter:
    """Build the segmenter registered as ``name`` (options: a validated model or keywords)."""
    seg: Segmenter = SEGMENTERS.create(name, options if options is not None else opts)
    return seg


def make_embedder(name: str = "classical", options: BaseModel | None = None, **opts: Any) -> Embedder:
    """Build the embedder registered as ``name`` (options: a validated model or keywords)."""
    emb: Embedder = EMBEDDERS.create(name, options if options is not None else opts)
    return emb
