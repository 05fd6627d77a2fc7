"""Robot body backends, one module each, picked by the ``type`` field of ``[body]``.

Each backend module defines ``Config`` (a :class:`~robot_agent.bodies.base.BodyConfig` subclass)
and ``create(config) -> RobotBody``. Heavy imports (the simulator) happen inside ``create``. A real
base (e.g. a ROS 2 bridge) is one more module here, or a plug-in module named by an entry point in
the group ``argus.robot_agent.bodies``.
"""

from __future__ import annotations

from typing import Any

from protocol.plugins import BackendRegistry
from robot_agent.bodies.base import BodyConfig, BodyConfigError, RobotBody

BODIES: dict[str, str] = {
    "sim": "robot_agent.bodies.sim",
    "kinematic": "robot_agent.bodies.kinematic",
}
"""Body type name -> backend module."""

ENTRY_POINT_GROUP = "argus.robot_agent.bodies"
REGISTRY = BackendRegistry("body type", "body", BODIES, ENTRY_POINT_GROUP, BodyConfigError)
available = REGISTRY.available
backend_module = REGISTRY.module


def parse_body_config(data: Any) -> BodyConfig:
    """Validate a ``[body]`` table with its backend's ``Config``."""
    config: BodyConfig = REGISTRY.parse_config(data, BodyConfig)
    return config


def create_body(config: BodyConfig) -> RobotBody:
    """Build the backend object for a validated body config."""
    body: RobotBody = REGISTRY.create(config)
    return body


__all__ = ["BODIES", "available", "backend_module", "create_body", "parse_body_config", "RobotBody"]
