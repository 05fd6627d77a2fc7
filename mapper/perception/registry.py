"""Registries of 2D perception backends; heavy imports happen only inside the chosen backend.

Segmenters: ``sim`` (ORACLE: the simulator's semantic camera), ``classical`` (no weights), ``detector``
(bundled closed-set SSD, 24 classes, CPU), ``sam`` (optional extra). Embedders: ``sim`` (ORACLE labels),
``classical`` (appearance, label ``object``), ``detector`` (the detector segmenter's classes), ``clip``
(optional extra). Third parties add backends through the entry-point groups
``argus.segmenters`` and ``argus.embedders`` (name -> ``module:Class``).
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from mapper.perception.base import Embedder, Segmenter

SEGMENTERS: dict[str, str] = {
    "sim": "mapper.perception.sim:SimSegmenter",
    "classical": "mapper.perception.classical:ClassicalSegmenter",
    "sam": "mapper.perception.sam:SamSegmenter",
    "detector": "mapper.perception.detector:DetectorSegmenter",
}
EMBEDDERS: dict[str, str] = {
    "sim": "mapper.perception.sim:SimEmbedder",
    "classical": "mapper.perception.classical:AppearanceEmbedder",
    "clip": "mapper.perception.clip:ClipEmbedder",
    "detector": "mapper.perception.detector:DetectorEmbedder",
}
ORACLE_BACKENDS = frozenset({"sim"})
"""Backends that read simulator ground truth (ORACLE); the mapper subscribes to oracle keys for them."""


def _available(builtin: dict[str, str], group: str) -> dict[str, str]:
    found = dict(builtin)
    for ep in entry_points(group=group):
        found.setdefault(ep.name, ep.value)
    return found


def _build(kind: str, table: dict[str, str], name: str, opts: dict[str, Any]) -> Any:
    if name not in table:
        raise ValueError(f"unknown {kind} {name!r}; choose one of {sorted(table)}")
    module_name, _, attr = table[name].partition(":")
    return getattr(importlib.import_module(module_name), attr)(**opts)


def make_segmenter(name: str = "classical", **opts: Any) -> Segmenter:
    """Build the segmenter registered as ``name``."""
    return _build("segmenter", _available(SEGMENTERS, "argus.segmenters"), name, opts)  # type: ignore[no-any-return]


def make_embedder(name: str = "classical", **opts: Any) -> Embedder:
    """Build the embedder registered as ``name``."""
    return _build("embedder", _available(EMBEDDERS, "argus.embedders"), name, opts)  # type: ignore[no-any-return]
