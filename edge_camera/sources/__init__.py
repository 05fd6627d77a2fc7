"""Camera source backends, one module each, picked by the ``type`` field of ``[source]``.

Each backend module defines ``Config`` (a :class:`~edge_camera.sources.base.SourceConfig` subclass
with its own fields) and ``create(config) -> FrameSource``. Backend modules import only light
packages at module level; the ``sim`` backend imports the simulator inside ``create``. Adding a
source type is one module plus one line here (or an entry point in the group
``argus.edge_camera.sources`` naming such a module), without touching the other backends.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

from edge_camera.sources.base import FrameSource, SourceConfig, SourceConfigError

SOURCES: dict[str, str] = {
    "opencv": "edge_camera.sources.opencv_device",
    "stream": "edge_camera.sources.stream",
    "video": "edge_camera.sources.video",
    "folder": "edge_camera.sources.folder",
    "pattern": "edge_camera.sources.pattern",
    "sim": "edge_camera.sources.sim",
}
"""Source type name -> backend module."""

ENTRY_POINT_GROUP = "argus.edge_camera.sources"


def available() -> dict[str, str]:
    """Built-in and plug-in source types (name -> module)."""
    out = dict(SOURCES)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep.value)
    return out


def backend_module(name: str) -> ModuleType:
    """The module of source type ``name``; :class:`SourceConfigError` for an unknown type."""
    types = available()
    if name not in types:
        raise SourceConfigError(f"unknown source type {name!r} (known: {', '.join(sorted(types))})")
    return importlib.import_module(types[name])


def parse_source_config(data: Any) -> SourceConfig:
    """Validate a ``[source]`` table with its backend's ``Config`` (pydantic errors propagate)."""
    if isinstance(data, SourceConfig):
        return data
    if not isinstance(data, dict) or not isinstance(data.get("type"), str):
        raise SourceConfigError("[source] needs a string field 'type'")
    cls: type[SourceConfig] = backend_module(data["type"]).Config
    return cls.model_validate(data)


def create_source(config: SourceConfig) -> FrameSource:
    """Build the backend object for a validated source config (not opened yet)."""
    source: FrameSource = backend_module(config.type).create(config)
    return source


__all__ = ["SOURCES", "available", "backend_module", "create_source", "parse_source_config", "FrameSource"]
