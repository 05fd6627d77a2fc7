"""Configuration of ``argus robot-agent`` (TOML file + command-line overrides)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, field_validator

from protocol.tomlconfig import AgentConfig
from robot_agent.bodies import parse_body_config
from robot_agent.bodies.base import BodyConfig


class FramesConfig(BaseModel):
    """When and how the robot camera's frames are published."""

    model_config = ConfigDict(extra="forbid")
    moving_rate_hz: float = Field(
        default=2.0, ge=0, le=60, description="frames per second (wall clock) while moving; 0: none while moving"
    )
    idle_period_s: float = Field(
        default=0.0, ge=0, description="seconds between frames while standing still; 0: only on arrival/start"
    )
    on_start: bool = Field(default=True, description="publish one frame when the agent starts")
    jpeg_quality: int = Field(default=90, ge=1, le=100, description="JPEG quality 1..100")
    goal_capture_m: float = Field(
        default=0.3, ge=0, le=2.0,
        description="at each goal, first step this far to the left and to the right of it (where the floor is "
        "free) and publish a frame at each, then return: the stereo baseline RGB-only geometry needs at the "
        "goal view; the sidesteps count in distance_m and in the time to arrival; 0: off",
    )


class MotionConfig(BaseModel):
    """The control loop and the simulated clock."""

    model_config = ConfigDict(extra="forbid")
    tick_hz: float = Field(default=20.0, gt=0, le=1000, description="control loop rate (wall clock)")
    time_scale: float = Field(
        default=1.0, gt=0, description="robot seconds per wall second (fast simulation: e.g. 20)"
    )


class BudgetConfig(BaseModel):
    """Optional exploration budget; once used up the robot reports budget_exhausted and refuses goals."""

    model_config = ConfigDict(extra="forbid")
    max_distance_m: float | None = Field(default=None, gt=0, description="metres of driving allowed")
    max_steps: int | None = Field(default=None, gt=0, description="goals (arrivals) allowed")


class RobotAgentConfig(AgentConfig):
    """One robot: its body backend, what it publishes and where the router is."""

    id: str = Field(default="robot0", description="robot id (a single key chunk: letters, digits, _ . -)")
    body: SerializeAsAny[BodyConfig] = Field(
        description="[body] table: 'type' picks the backend (sim, kinematic); the other fields belong to it"
    )
    frames: FramesConfig = Field(default_factory=FramesConfig, description="frame publishing")
    motion: MotionConfig = Field(default_factory=MotionConfig, description="control loop and time scale")
    budget: BudgetConfig = Field(default_factory=BudgetConfig, description="exploration budget")
    state_period_s: float = Field(default=1.0, gt=0, description="seconds between RobotState messages when idle")
    viewpoints_period_s: float = Field(
        default=5.0, gt=0, description="seconds between ViewpointSet re-publications (also served on query)"
    )

    @field_validator("body", mode="before")
    @classmethod
    def _body(cls, v: Any) -> BodyConfig:
        return parse_body_config(v)
