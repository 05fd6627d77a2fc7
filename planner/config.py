"""Configuration of the planner (pure core) and of the `argus planner` process."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from protocol.keys import SiteName
from protocol.session import ZenohSettings, default_site

Strategy = Literal["see", "asp"]
"""Planner strategies: see (geometric frontier gain) or asp (semantic gain over sampled completions)."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class VisibilityConfig(_Model):
    """How the planner predicts what a camera at a candidate pose would see."""

    near_m: float = Field(default=0.2, gt=0.0, description="closest useful depth, metres")
    cube_face_bins: int = Field(
        default=48, ge=8, le=512, description="panoramic z-buffer: bins per cube-map face side (6 faces)"
    )
    occluder_voxel_m: float = Field(
        default=0.1, ge=0.0, description="map points are thinned to one per voxel of this size for occlusion"
    )
    occlusion_tol_m: float = Field(
        default=0.15, ge=0.0, description="a target counts as unoccluded up to this far behind the z-buffer"
    )
    occlusion_tol_rel: float = Field(
        default=0.06, ge=0.0, description="relative occlusion tolerance (fraction of the target's range)"
    )
    max_occluder_points: int = Field(
        default=60000, ge=100, description="map points used for occlusion (deterministic subsample above)"
    )
    panorama_batch_pairs: int = Field(
        default=250_000,
        ge=1,
        description="(camera position, occluder) pairs binned at once while building panoramas: bounds the "
        "planner's transient memory (about 110 bytes per pair: 4M pairs peaked at ~450 MiB per decision, "
        "250k at ~55 MiB, no slower); the z-buffers do not depend on it",
    )
    threads: int = Field(
        default=2,
        ge=1,
        le=64,
        description="worker threads of a decision: panorama builds, frustum tests, occlusion look-ups and the "
        "frontier classification are split across them (numpy frees the interpreter in its array loops); the "
        "results are the same for any value, and the panoramas' transient memory stays within "
        "panorama_batch_pairs in total",
    )
    image_margin_frac: float = Field(
        default=0.03,
        ge=0.0,
        lt=0.5,
        description="image border (fraction of size) that does not count as seen",
    )


class SeeConfig(_Model):
    """Geometric baseline after Surface Edge Explorer: frontier points from measurement density."""

    min_neighbors: int = Field(
        default=6, ge=1, le=26, description="occupied 26-neighbours below which a voxel is a surface edge"
    )
    min_density: float = Field(
        default=3.0,
        ge=0.0,
        description="summed observation counts (voxel + neighbours) below which it is sparse",
    )
    max_attempts: int = Field(
        default=2, ge=1, description="past views that had a frontier point well in view before it is given up"
    )
    attempt_range_frac: float = Field(
        default=0.6,
        gt=0.0,
        le=1.0,
        description="a past view counts as an attempt within this fraction of range",
    )
    tie_tolerance: float = Field(
        default=0.1,
        ge=0.0,
        lt=1.0,
        description="candidates within this fraction of the best score tie; nearest wins",
    )


class AspConfig(_Model):
    """Semantic strategy: expected information gain over sampled scene completions."""

    n_completions: int = Field(default=8, ge=1, le=64, description="completions K drawn from the sampler")
    n_jitter: int = Field(default=4, ge=1, le=32, description="position-jitter draws J per completion")
    jitter_m: float = Field(default=0.25, ge=0.0, description="std of hypothesis position jitter, metres")
    observation: Literal["joint", "factored"] = Field(
        default="factored",
        description="joint: Y is the whole label multiset; factored: sum of per-label count informations",
    )
    min_pixels: float = Field(
        default=22.0, ge=1.0, description="projected size (pixels) an object needs to be detected"
    )
    travel_weight_per_m: float = Field(
        default=0.05,
        ge=0.0,
        description="utility = gain - this * best gain * travel metres (fraction of the best gain per metre)",
    )
    cross_room_visibility: bool = Field(
        default=False, description="allow seeing hypotheses of another room (when rooms are known)"
    )
    proposals_per_object: int = Field(
        default=10, ge=1, le=64, description="placements tried per hypothesised object before it is dropped"
    )
    detect_reject: float = Field(
        default=0.9,
        ge=0.0,
        le=1.0,
        description="probability a past view that would have seen it rules it out",
    )
    min_gain_bits: float = Field(
        default=0.05, ge=0.0, description="below this best gain the geometric frontier score takes over"
    )
    max_attempts: int = Field(
        default=0,
        ge=0,
        description="a hypothesis that this many past views had well in view (frustum, see.attempt_range_frac of "
        "range, big enough; occlusion not asked) is ruled out as seen, as see gives up a frontier point: stray "
        "points of estimated depth hide places the robot has looked at again and again (the demo's robot spent its "
        "last 8 goals in one bedroom). 0 disables; off: with 3, RGB-only ASP on the tuning apartments (seeds 1-2, "
        "2 starts each) reached recall@30 0.772 against 0.795 (better in 2 of 4 episodes)",
    )


class LlmConfig(_Model):
    """An OpenAI-compatible chat-completions endpoint used as the completion sampler."""

    base_url: str = Field(default="http://127.0.0.1:8000/v1", description="endpoint base URL (…/v1)")
    model: str = Field(default="local-model", description="model name sent in the request")
    api_key_env: str = Field(
        default="ARGUS_LLM_API_KEY", description="env var holding the API key (may be unset)"
    )
    timeout_s: float = Field(default=20.0, gt=0.0, description="per-request timeout, seconds")
    retries: int = Field(
        default=1, ge=0, le=5, description="extra attempts after a failed request or bad reply"
    )
    temperature: float = Field(default=0.8, ge=0.0, le=2.0, description="sampling temperature")
    max_tokens: int = Field(default=2048, ge=64, description="reply token cap")
    json_mode: bool = Field(
        default=True, description="send response_format json_object (if the server supports it)"
    )
    max_nodes_in_prompt: int = Field(
        default=150, ge=1, description="graph nodes listed in the prompt at most"
    )


class SamplerConfig(_Model):
    """Which completion sampler the asp strategy uses."""

    kind: Literal["prior", "llm"] = Field(
        default="prior", description="prior (embedded) or llm (chat endpoint)"
    )
    prior_path: Path | None = Field(default=None, description="indoor prior JSON (default: the packaged one)")
    llm: LlmConfig = Field(default_factory=LlmConfig, description="llm sampler settings")


class PlannerConfig(_Model):
    """The pure planner."""

    strategy: Strategy = Field(default="asp", description="see (geometric) or asp (semantic)")
    seed: int = Field(default=0, description="random seed of the samplers")
    visibility: VisibilityConfig = Field(default_factory=VisibilityConfig, description="view prediction")
    see: SeeConfig = Field(default_factory=SeeConfig, description="geometric strategy")
    asp: AspConfig = Field(default_factory=AspConfig, description="semantic strategy")
    sampler: SamplerConfig = Field(default_factory=SamplerConfig, description="completion sampler")
    rooms: Literal["auto", "map", "viewpoints"] = Field(
        default="auto",
        description="where asp's rooms come from: map (the mapper's room layer, built from its own map; viewpoints "
        "in no room form one 'unexplored' region), viewpoints (the room names the robots publish with their "
        "viewpoints; none: one region), auto (map when the planner has a room layer with rooms, else viewpoints). "
        "The demo with auto: F1 0.769, every decision asp; with viewpoints 0.732 (one run each, RGB-only)",
    )
    focus_room: str | None = Field(
        default=None,
        description="look around one room: only viewpoints inside it are candidates (a room id such as room3, or a "
        "room label such as kitchen: the most confident room with it); none inside, or no such room: no focus",
    )
    revisit_xy_m: float = Field(default=0.15, ge=0.0, description="a candidate this close to a past view…")
    revisit_yaw_deg: float = Field(default=20.0, ge=0.0, description="…and this aligned is not taken again")
    claim_radius_m: float = Field(
        default=1.0, ge=0.0, description="robots' goals keep at least this far apart (multi-robot)"
    )
    max_history: int = Field(default=400, ge=1, description="past camera views remembered")


class PlannerNodeConfig(_Model):
    """The `argus planner` process."""

    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how to join the Zenoh network")
    site: SiteName = Field(
        default_factory=default_site,
        validate_default=True,
        description="Argus site name (key prefix argus/<site>/...; default $ARGUS_SITE or default)",
    )
    prefix: str = Field(default="argus", description="key prefix")
    node_id: str = Field(default="planner", description="id of this planner (liveliness, status)")
    planner: PlannerConfig = Field(default_factory=PlannerConfig, description="the planner itself")
    replan_new_nodes: int = Field(
        default=15,
        ge=1,
        description="nodes added since a goal was planned that count as a large graph change",
    )
    resend_s: float = Field(
        default=5.0, gt=0.0, description="re-plan an idle robot that ignored its goal after this"
    )
    fusion_wait_s: float = Field(
        default=5.0, ge=0.0,
        description="after a robot arrives, wait at least up to this long for a graph version that covers its arrival "
        "frame (RobotState.last_frame_seq against the graph's frames) before planning its next goal; 0: do not wait",
    )
    fusion_wait_max_s: float = Field(
        default=30.0, ge=0.0,
        description="... and at most this long: the wait follows the mapper's measured pace (fusion_wait_factor x "
        "the 90th percentile of the last 16 arrival-to-graph delays), so a loaded mapper's late keyframes are waited "
        "for; status fusion_wait_limit_s says the wait now",
    )
    fusion_wait_factor: float = Field(
        default=1.5, gt=0.0, description="the wait in units of the measured arrival-to-graph delay (its p90)"
    )
    unannounced_expire_s: float = Field(
        default=30.0, gt=0.0,
        description="a robot with no liveliness token (status robots_unannounced) is forgotten once it has sent no "
        "state for this long (counter robots_expired): an id that put a state once gets no goals for ever; robots "
        "with a token are forgotten when it goes away",
    )
    status_period_s: float = Field(default=1.0, gt=0.0, description="status publication period")
    release_heap_after_plan: bool = Field(
        default=True,
        description="after each decision, give the C heap's freed memory back to the system (glibc malloc_trim; "
        "a few ms): without it the resting RSS creeps up in plateaus after decisions' large temporary arrays",
    )
    query_timeout_s: float = Field(default=2.0, gt=0.0, description="start-up query timeout")
    rooms_period_s: float = Field(
        default=2.0, ge=0.0,
        description="ask the mapper for its room layer (graph/rooms) at most this often, when the graph changed: "
        "asp's rooms, the rooms of frontiers and goals, planner.focus_room (0: never; rooms then come from the "
        "viewpoints' names)",
    )
    log_level: str = Field(default="INFO", description="logging level")
