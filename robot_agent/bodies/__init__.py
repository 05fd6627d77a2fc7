"""Robot body backends, one module each, picked by the ``type`` field of ``[body]``.

Each backend module defines ``Config`` (a :class:`~robot_agent.bodies.base.BodyConfig` subclass)
and ``create(config) -> RobotBody``. Heavy imports (the simulator) happen inside ``create``. A real
base (e.g. a ROS 2 bridge) is one more module here, or a plug-in module named by an entry point in
the group ``argus.robot_agent.bodies``.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

from robot_agent.bodies.base import BodyConfig, BodyConfigError, RobotBody

BODIES: dict[str, str] = {
    "sim": "robot_agent.bodies.sim",
    "kinematic": "robot_agent.bodies.kinematic",
}
"""Body type name -> backend module."""

ENTRY_POINT_GROUP = "argus.robot_agent.bodies"


def available() -> dict[str, str]:
    """Built-in and plug-in body types (name -> module)."""
    out = dict(BODIES)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep.value)
    return out


def backend_module(name: str) -> ModuleType:
    types = available()
    if name not in types:
        raise BodyConfigError(f"unknown body type {name!r} (known: {', '.join(sorted(types))})")
    return importlib.import_module(types[name])


def parse_body_config(data: Any) -> BodyConfig:
    """Validate a ``[body]`` table with its backend's ``Config``."""
    if isinstance(data, BodyConfig):
        return data
    if not isinstance(data, dict) or not isinstance(data.get("type"), str):
        raise BodyConfigError("[body] needs a string field 'type'")
    cls: type[BodyConfig] = backend_module(data["type"]).Config
    return cls.model_validate(data)


def create_body(config: BodyConfig) -> RobotBody:
    body: RobotBody = backend_module(config.type).create(config)
    return body


__all__ = ["BODIES", "available", "backend_module", "create_body", "parse_body_config", "RobotBody"]
