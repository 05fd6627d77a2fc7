"""Configuration of ``argus edge-camera`` (TOML file + command-line overrides)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, field_validator, model_validator

from edge_camera.sources import parse_source_config
from edge_camera.sources.base import SourceConfig
from protocol.session import ReconnectConfig
from protocol.tomlconfig import AgentConfig


class PublishConfig(BaseModel):
    """How frames go on the wire."""

    model_config = ConfigDict(extra="forbid")
    max_rate_hz: float = Field(default=5.0, gt=0, le=120, description="upper bound on frames sent per second")
    width: int | None = Field(
        default=None, gt=0, le=8192, description="resize frames to this width (none: source width)"
    )
    height: int | None = Field(
        default=None, gt=0, le=8192, description="resize frames to this height (none: keep the aspect ratio)"
    )
    jpeg_quality: int = Field(default=85, ge=1, le=100, description="JPEG quality 1..100")


class EdgeCameraConfig(AgentConfig):
    """One fixed camera: where it reads, how it publishes, where the router is."""

    id: str = Field(default="cam0", description="camera id (a single key chunk: letters, digits, _ . -)")
    source: SerializeAsAny[SourceConfig] = Field(
        description="[source] table: 'type' picks the backend (opencv, stream, video, folder, recorded, pattern, sim); "
        "the other fields belong to that backend (see --describe)"
    )
    publish: PublishConfig = Field(default_factory=PublishConfig, description="rate, size and JPEG quality")
    calibration: Path | None = Field(
        default=None, description="OpenCV YAML or JSON file with intrinsics and/or T_world_cam (see calibration.py)"
    )
    reconnect: ReconnectConfig = Field(default_factory=ReconnectConfig, description="back-off on faults")

    @field_validator("source", mode="before")
    @classmethod
    def _source(cls, v: Any) -> SourceConfig:
        return parse_source_config(v)

    @model_validator(mode="after")
    def _backoff(self) -> EdgeCameraConfig:
        if self.reconnect.max_s < self.reconnect.initial_s:
            raise ValueError("reconnect.max_s must be >= reconnect.initial_s")
        return self
