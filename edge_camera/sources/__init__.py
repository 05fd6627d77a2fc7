"""Camera source backends, one module each, picked by the ``type`` field of ``[source]``.

Each backend module defines ``Config`` (a :class:`~edge_camera.sources.base.SourceConfig` subclass
with its own fields) and ``create(config) -> FrameSource``. Backend modules import only light
packages at module level; the ``sim`` backend imports the simulator inside ``create``. Adding a
source type is one module plus one line here (or an entry point in the group
``argus.edge_camera.sources`` naming such a module), without touching the other backends.
"""

from __future__ import annotations

from typing import Any

from edge_camera.sources.base import FrameSource, SourceConfig, SourceConfigError
from protocol.plugins import BackendRegistry

SOURCES: dict[str, str] = {
    "opencv": "edge_camera.sources.opencv_device",
    "stream": "edge_camera.sources.stream",
    "video": "edge_camera.sources.video",
    "folder": "edge_camera.sources.folder",
    "recorded": "edge_camera.sources.recorded",
    "pattern": "edge_camera.sources.pattern",
    "sim": "edge_camera.sources.sim",
}
"""Source type name -> backend module."""

ENTRY_POINT_GROUP = "argus.edge_camera.sources"
REGISTRY = BackendRegistry("source type", "source", SOURCES, ENTRY_POINT_GROUP, SourceConfigError)
available = REGISTRY.available
backend_module = REGISTRY.module


def parse_source_config(data: Any) -> SourceConfig:
    """Validate a ``[source]`` table with its backend's ``Config`` (pydantic errors propagate)."""
    config: SourceConfig = REGISTRY.parse_config(data, SourceConfig)
    return config


def create_source(config: SourceConfig) -> FrameSource:
    """Build the backend object for a validated source config (not opened yet)."""
    source: FrameSource = REGISTRY.create(config)
    return source


__all__ = ["SOURCES", "available", "backend_module", "create_source", "parse_source_config", "FrameSource"]
