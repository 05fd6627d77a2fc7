"""Configuration models of the ``argus sim`` sub-commands."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

Family = Literal["apartment", "furnished_room", "apartment_large"]  # sim.world.FAMILIES (append only)
FAMILIES: tuple[Family, ...] = ("apartment", "furnished_room", "apartment_large")
RenderBackend = Literal["embree", "open3d"]
RENDER_BACKENDS: tuple[RenderBackend, ...] = ("embree", "open3d")


class SceneSource(BaseModel):
    """Which scene: generated from (family, seed), or loaded from a scene JSON."""

    model_config = ConfigDict(extra="forbid")
    family: Family = Field(default="apartment", description="scene family to generate")
    seed: int = Field(default=0, ge=0, description="generator seed")
    scene: str | None = Field(default=None, description="scene JSON to load instead of generating")


class CameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    width: int = Field(default=640, gt=0, le=4096, description="image width, pixels")
    height: int = Field(default=480, gt=0, le=4096, description="image height, pixels")
    hfov_deg: float = Field(default=90.0, gt=1.0, lt=179.0, description="horizontal field of view, degrees")


class ExportConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: SceneSource = Field(default_factory=SceneSource, description="scene to export")
    out_dir: str = Field(default="sim_out", description="output directory for <stem>.glb and <stem>.json")
    n_cameras: int = Field(default=3, ge=0, le=3, description="fixed cameras stored in the JSON")


class RenderConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: SceneSource = Field(default_factory=SceneSource, description="scene to render")
    out_dir: str = Field(default="sim_out", description="output directory for the PNGs")
    camera: CameraConfig = Field(default_factory=CameraConfig, description="camera model")
    n_fixed: int = Field(default=3, ge=0, le=3, description="fixed (overhead corner) camera views")
    robot_views: bool = Field(default=True, description="one robot-height view per room")
    backend: Literal["embree", "open3d"] = Field(default="embree", description="ray-casting backend")


class ViewConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: SceneSource = Field(default_factory=SceneSource, description="scene to log")
    out: str = Field(default="sim_out/scene.rrd", description="Rerun recording file to write (never served)")
    n_fixed: int = Field(default=2, ge=0, le=3, description="fixed cameras logged with their images")


class CheckConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    families: list[Family] = Field(default_factory=lambda: list(FAMILIES), description="families to check")
    seeds: list[int] = Field(default_factory=lambda: list(range(50)), description="seeds to check")
    full: bool = Field(default=False, description="also run the slower interpenetration check")
    out: str | None = Field(default=None, description="write the JSON report here")


class BenchConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: SceneSource = Field(default_factory=SceneSource, description="scene to render")
    camera: CameraConfig = Field(default_factory=CameraConfig, description="camera model")
    frames: int = Field(default=10, ge=1, le=1000, description="frames per backend")
    backends: list[RenderBackend] = Field(default_factory=lambda: list(RENDER_BACKENDS),
                                          description="backends to compare")
    out: str | None = Field(default=None, description="write the JSON result here")
