"""Configuration of the mapper: the in-process core (geometry, perception, fusion, relations) and the
``argus mapper`` process around it (Zenoh, publishing, persistence, Rerun)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SerializeAsAny, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from mapper.fusion import FusionConfig
from mapper.geometry.registry import RECONSTRUCTORS
from mapper.intake import InputLimits
from mapper.perception.registry import EMBEDDERS, SEGMENTERS
from mapper.posegraph import PoseGraphConfig
from mapper.relations import RelationConfig
from mapper.work.config import OffloadConfig
from protocol.keys import SiteName
from protocol.plugins import FactoryRegistry, FreeOptions
from protocol.session import ZenohSettings, default_site

if TYPE_CHECKING:
    from mapper.geometry.singleview import SingleViewParams


def _backend_name(registry: FactoryRegistry, name: str) -> str:
    """``name`` if ``registry`` has it, else one error listing the known names."""
    try:
        registry.factory_target(name)
    except ValueError as e:
        raise PydanticCustomError("unknown_backend", "{reason}", {"reason": str(e)}) from None
    return name


def _backend_options(registry: FactoryRegistry, name: Any, value: Any) -> BaseModel:
    """``value`` validated as the options of backend ``name``: one error naming the backend and each bad
    option. A name that failed its own check leaves the options unchecked (its error says why)."""
    if not isinstance(name, str):
        return FreeOptions()
    try:
        return registry.parse_options(name, value)
    except ValueError as e:
        raise PydanticCustomError("backend_options", "{reason}", {"reason": str(e)}) from None


class GeometryConfig(BaseModel):
    """Which reconstructor turns views into metric geometry; ``options`` are validated against the chosen
    backend's options model when the config loads (``argus mapper --describe`` lists each backend's)."""

    model_config = ConfigDict(extra="forbid")
    backend: str = Field(default="mvs", description="reconstructor: mvs (RGB only), oracle (sim), mapanything, da3")
    options: SerializeAsAny[BaseModel] = Field(
        default_factory=dict, validate_default=True,
        description="the backend's options (its own table: see the per-backend lists below)",
    )

    @field_validator("backend")
    @classmethod
    def _known(cls, v: str) -> str:
        return _backend_name(RECONSTRUCTORS, v)

    @field_validator("options", mode="before")
    @classmethod
    def _options(cls, v: Any, info: ValidationInfo) -> BaseModel:
        return _backend_options(RECONSTRUCTORS, info.data.get("backend"), v)


class PerceptionConfig(BaseModel):
    """Which 2D perception backends find, describe and label objects; each one's options are validated
    against its options model when the config loads."""

    model_config = ConfigDict(extra="forbid")
    segmenter: str = Field(
        default="classical", description="masks: classical (no weights), detector (24 classes, CPU), sim (ORACLE), sam"
    )
    segmenter_options: SerializeAsAny[BaseModel] = Field(
        default_factory=dict, validate_default=True, description="the segmenter's options (see the per-backend lists)"
    )
    embedder: str = Field(
        default="classical", description="labels: classical (appearance), detector, sim (ORACLE labels), clip"
    )
    embedder_options: SerializeAsAny[BaseModel] = Field(
        default_factory=dict, validate_default=True, description="the embedder's options (see the per-backend lists)"
    )

    @field_validator("segmenter")
    @classmethod
    def _known_segmenter(cls, v: str) -> str:
        return _backend_name(SEGMENTERS, v)

    @field_validator("embedder")
    @classmethod
    def _known_embedder(cls, v: str) -> str:
        return _backend_name(EMBEDDERS, v)

    @field_validator("segmenter_options", mode="before")
    @classmethod
    def _segmenter_options(cls, v: Any, info: ValidationInfo) -> BaseModel:
        return _backend_options(SEGMENTERS, info.data.get("segmenter"), v)

    @field_validator("embedder_options", mode="before")
    @classmethod
    def _embedder_options(cls, v: Any, info: ValidationInfo) -> BaseModel:
        return _backend_options(EMBEDDERS, info.data.get("embedder"), v)


class KeyframeConfig(BaseModel):
    """Keyframe selection (parallax / rotation / novelty) and the source views handed to geometry."""

    model_config = ConfigDict(extra="forbid")
    min_baseline_ratio: float = Field(
        default=0.08, ge=0.0,
        description="a posed view is a keyframe once its baseline to its source's last keyframe reaches this "
        "fraction of the scene depth (parallax, not arrival order: video-rate frames 1-3 cm apart are not)",
    )
    min_translation_m: float = Field(
        default=0.3, ge=0.0, description="camera motion that makes a keyframe whatever the depth (far scenes)"
    )
    min_rotation_deg: float = Field(default=20.0, ge=0.0, description="camera rotation that makes a new keyframe")
    assumed_depth_m: float = Field(
        default=1.0, gt=0.0,
        description="typical scene depth assumed before a source's first depth map (short: a keyframe too many early "
        "costs less than a source without parallax)"
    )
    novelty_threshold: float = Field(
        default=0.08, ge=0.0, description="mean abs. change of a 32x24 grey thumbnail (0..1) that counts as new"
    )
    refresh_s: float = Field(
        default=2.0, ge=0.0,
        description="a static camera is reconsidered after this long (if its image changed): a fixed camera sees an "
        "object moved or taken away at its next keyframe (30 s before the graph followed changes)",
    )
    static_max_m: float = Field(
        default=0.01, ge=0.0,
        description="a posed camera that moved less than this (and turned less than static_max_deg) since its last "
        "keyframe is static: refresh_s and the changed-cells rule apply to it",
    )
    static_max_deg: float = Field(default=0.5, ge=0.0, description="... and turned less than this")
    moving_refresh_s: float = Field(
        default=30.0, ge=0.0,
        description="a moving camera whose motion stays under the parallax and rotation thresholds is reconsidered "
        "(novelty) after this long: every refresh_s would give a slowly moving camera's windows no parallax (a "
        "recording replayed at 0.5 Hz made each frame a keyframe)",
    )
    change_threshold: float = Field(
        default=0.1, gt=0.0, le=1.0,
        description="a static posed camera's thumbnail cell (32x24, 0..1) that changed by this much in a colour "
        "channel changed ...",
    )
    change_fraction: float = Field(
        default=0.002, gt=0.0, le=1.0,
        description="... and this fraction of changed cells makes its next frame after refresh_s a keyframe, "
        "whatever the mean change: a chair moved or taken away in a corner camera's view changes a few cells "
        "(at 160x120 px, 5 to 10 of 768), far below novelty_threshold on average; at most one keyframe per "
        "refresh_s",
    )
    max_keyframes: int = Field(default=32, ge=2, description="keyframes kept as source candidates (oldest dropped)")
    max_deferred: int = Field(default=8, ge=0, description="keyframes without usable sources kept for a retry")
    window_neighbours: int = Field(default=3, ge=0, description="source keyframes per geometry window")
    recent_sources: int = Field(
        default=2, ge=0, le=8,
        description="a moving camera's last frames that did not become keyframes are source candidates too "
        "(video rate: they see most of what the next keyframe newly sees; hololens-dvmvs coverage 0.45 -> 0.63)",
    )
    recent_min_move_m: float = Field(
        default=0.005, ge=0.0, description="a frame is kept as a recent source only if its camera moved this far"
    )
    neighbour_max_distance_m: float = Field(default=3.0, gt=0.0, description="farthest source camera")
    neighbour_max_angle_deg: float = Field(default=60.0, gt=0.0, description="largest viewing-direction change")
    source_min_triangulation_deg: float = Field(
        default=1.5, ge=0.0,
        description="a source needs at least this triangulation angle at the target's typical depth (parallax)",
    )
    source_min_overlap: float = Field(
        default=0.3, ge=0.0, le=1.0, description="fraction of the target's view a source must also see"
    )


class DepthCheckConfig(BaseModel):
    """Multi-view consistency of a keyframe's depth against other keyframes before it is fused."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(
        default=False,
        description="check estimated depth against other keyframes (not oracle). Off by default: on the static "
        "sim eval it cut confident coverage ~3x and cost recall without removing the duplicate nodes",
    )
    min_views: int = Field(default=2, ge=1, description="agreeing views a pixel needs (fewer if fewer cover it)")
    max_views: int = Field(default=4, ge=1, description="other keyframes checked against, most overlapping first")
    rel_tol: float = Field(default=0.05, gt=0.0, description="relative depth tolerance of agreement")
    reproj_px: float = Field(default=2.0, gt=0.0, description="forward-backward reprojection tolerance, pixels")
    map_width: int = Field(default=160, ge=16, description="width of the stored keyframe depth maps, pixels")


class PoseCheckConfig(BaseModel):
    """Whether a calibrated fixed camera still looks where its pose says (``mapper.geometry.posecheck``)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(
        default=True,
        description="compare each keyframe of a calibrated (trusted-pose) camera with its first one; a camera that "
        "turned is flagged in the status and its frames are not fused until it looks the same again or is recalibrated",
    )
    max_rotation_deg: float = Field(
        default=1.0, gt=0.0, description="rotation since the reference keyframe that flags the camera as moved"
    )
    min_inliers: int = Field(
        default=40, ge=8, description="matches the check needs to decide (fewer: inconclusive, frames still fused)"
    )


class SingleViewConfig(BaseModel):
    """Single-view geometry for posed views that have no stereo partner yet (``mapper.geometry.singleview``):
    objects placed from where their masks touch the floor or a placed object, under an upright-box assumption."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(
        default=True,
        description="place objects of a calibrated view with no stereo partner (a lone fixed camera) from the floor "
        "plane; the view is still retried with multi-view stereo once partners exist",
    )
    untrusted_poses: bool = Field(
        default=False,
        description="also for views whose pose is only a prior (a robot's odometry). Off by default: on the static "
        "sim walks the first frames' placements duplicated later stereo nodes (F1 0.687 -> 0.664); on, the RGB-only "
        "active loop's ASP recall@30 rose from 0.21 to 0.44 (docs/benchmarks.md)",
    )
    fill_depthless: bool = Field(
        default=True,
        description="detections of a multi-view keyframe with no confident stereo depth (textureless objects) are "
        "placed by single-view geometry from the keyframe's pose, as coarse nodes that measured depth or other "
        "views' rays refine later",
    )
    measured_support: bool = Field(
        default=True,
        description="... and such a detection that does not touch the floor is placed on the level surface this "
        "keyframe's confident depth shows just under its mask (a frame on a dresser, a bowl on a table). On since "
        "fusion keeps told-apart nodes and limits growth: RGB-only ASP on the tuning apartments (seeds 1-2, 2 starts "
        "each) recall@30 0.795 -> 0.853 (better in 3 of 4 episodes), static replay of tuning rooms 0-9 F1 0.885 -> "
        "0.888 (nodes 24.5 -> 24.8, true 23.8). Before those (off then): static tuning seeds 0-4 F1 0.807 -> 0.813, "
        "nodes 24.6 -> 26.2; held-out 0.823 -> 0.806",
    )
    mapped_support: bool = Field(
        default=False,
        description="... or, where that surface has no confident depth either, a small one (no side over 0.45 m) "
        "is placed on the top face of the mapped node its lowest pixels' rays meet first, when the pixels just "
        "under it belong to another object's mask (with measured_support). Off: on the same seeds recall 0.845 -> "
        "0.894 but precision 0.797 -> 0.755 and nodes 26.6 -> 29.6 (F1 0.815 either way); one RGB-only ASP run "
        "(apartment 1): recall@30 0.713 -> 0.693",
    )
    floor_z_m: float = Field(default=0.0, description="height of the floor in the world frame, metres")
    max_range_m: float = Field(default=12.0, gt=0.0, description="floor contacts farther from the camera are ignored")
    max_extent_m: float = Field(
        default=3.5, gt=0.0, description="a footprint longer than this is taken as a wrong placement and dropped"
    )
    confidence: float = Field(
        default=0.4, ge=0.0, le=1.0,
        description="depth confidence of placed objects (stereo depth is 0.5-1): coarse, refined by other views",
    )
    floor_colour_check: bool = Field(
        default=True,
        description="floor contacts must look like the floor under the view's other objects (an object seen "
        "against a wall is not pushed through it)",
    )
    floor_colour_sigma: float = Field(
        default=3.0, gt=0.0,
        description="how far (robust standard deviations, Lab) the colour under a floor contact may be from the "
        "floor's colour models (learnt under the view's other objects)",
    )
    floor_cluster_share: float = Field(
        default=0.3, gt=0.0,
        description="each of the two colour clusters of the floor sample holding this share of it is a floor of "
        "its own (an apartment camera sees other rooms' floors through doorways); above 0.5: one floor model",
    )
    other_floor: bool = Field(
        default=True,
        description="an object whose floor contacts all fail the floor-colour test is still placed from them when "
        "the colour under them is unlike the background just above the object (another room's floor seen "
        "through a doorway, not a wall going on above and below a wall-mounted object)",
    )
    free_space_check: bool = Field(
        default=True,
        description="a placement that another calibrated camera saw as free space (its floor, learnt from under "
        "the objects it placed) is moved along its ray to where that camera saw a similar object; one that its own "
        "camera now sees floor in place of is removed (taken away)",
    )

    changed_only: bool = Field(
        default=True,
        description="a calibrated camera that has not moved places from one view only the detections that touch "
        "cells of its view that changed since its earlier keyframes, the cells people cover left out "
        "(``mapper.changemask``): a passer-by made it place every object of the view again, cut by the person",
    )
    background_check: bool = Field(
        default=True,
        description="a placement whose surface lies, along its mask's rays, behind nearly all the confident depth "
        "the same keyframe measured around the mask (a monitor on a desk read as standing on the floor metres "
        "behind the wall) is refused (``mapper.geometry.background``); views with no confident depth around the "
        "mask are not checked",
    )
    background_margin_m: float = Field(
        default=0.3, ge=0.0,
        description="how far (metres) behind the 90th percentile of the depth around the mask a placement may lie",
    )

    def params(self) -> SingleViewParams:
        from mapper.geometry.singleview import SingleViewParams

        return SingleViewParams(floor_z_m=self.floor_z_m, max_range_m=self.max_range_m,
                                max_extent_m=self.max_extent_m, confidence=self.confidence,
                                floor_colour_sigma=self.floor_colour_sigma,
                                floor_cluster_share=self.floor_cluster_share, other_floor=self.other_floor)


class PointMapConfig(BaseModel):
    """The global voxel map published for planners."""

    model_config = ConfigDict(extra="forbid")
    voxel_m: float = Field(default=0.08, gt=0.0, description="voxel size, metres")
    max_voxels: int = Field(default=300_000, ge=1, description="memory bound (least observed dropped)")
    min_confidence: float = Field(default=0.3, ge=0.0, le=1.0, description="depth confidence needed")
    max_depth_m: float = Field(default=8.0, gt=0.0, description="farther points are not mapped")


class RoomsConfig(BaseModel):
    """The room layer: rooms split from the map's floor grid, doorways, objects in rooms (mapper.rooms)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=True, description="build the room layer (rooms, in_room and connects edges)")
    cell_m: float = Field(default=0.1, gt=0.0, le=1.0, description="floor grid cell, metres")
    floor_band_m: float = Field(default=0.1, gt=0.0, description="points within this of the floor height are floor")
    wall_band_m: tuple[float, float] = Field(
        default=(1.2, 2.0),
        description="heights above the floor whose points make walls (below a doorway's lintel, above most furniture)",
    )
    min_observations: int = Field(
        default=2, ge=1,
        description="map voxels observed by fewer keyframes are left out (RGB-only depth scatters one-view outliers)",
    )
    wall_min_points: int = Field(default=6, ge=1, description="voxels in the wall band that make a cell a wall")
    camera_free_m: float = Field(default=0.3, ge=0.0, description="known-free radius around each camera position")
    camera_max_height_m: float = Field(
        default=1.8, gt=0.0, description="cameras higher than this above the floor (wall-mounted) free no space"
    )
    sight_cameras: int = Field(
        default=16, ge=0,
        description="observed floor and object footprints count as free space only in sight of one of this many "
        "nearest camera positions (no wall between: RGB-only depth and stretched boxes put some behind walls); 0: off",
    )
    grow_m: float = Field(
        default=1.5, ge=0.0, description="rooms take unseen cells inside their walls up to this far from known space"
    )
    close_m: float = Field(default=0.3, ge=0.0, description="gaps in observed floor up to this wide are filled")
    marker_h_m: float = Field(
        default=0.3, gt=0.0, description="a room's middle stands this far above the saddle to its neighbour (h-maxima)"
    )
    marker_min_m: float = Field(default=0.45, ge=0.0, description="a room's middle is at least this far from walls")
    min_room_m2: float = Field(default=1.5, ge=0.0, description="smaller regions join their neighbour")
    door_min_m: float = Field(default=0.4, ge=0.0, description="rooms touching along this much are connected")
    merge_open_m: float = Field(
        default=1.5, gt=0.0, description="two tracked rooms merge only across an opening this wide, seen open"
    )
    merge_floor_fraction: float = Field(
        default=0.7, ge=0.0, le=1.0, description="... with observed floor along this fraction of it"
    )
    merge_free_fraction: float = Field(
        default=0.4, ge=0.0, le=1.0,
        description="... or, with no wall cell in it, with observed floor or a camera's passage along this fraction "
        "of it: RGB-only sees floor in patches (0: observed floor only)",
    )
    assign_max_m: float = Field(
        default=0.6, ge=0.0, description="an object outside every room joins the nearest one within this distance"
    )
    wall_share_m: float = Field(
        default=0.3, ge=0.0,
        description="a wall cell up to this deep in a thick wall band (RGB-only depth scatters walls) joins the room "
        "nearest to it, so the band splits down its middle (0: rooms take only the ring of wall cells next to them)",
    )
    wall_bridge_m: float = Field(
        default=2.5, ge=0.0,
        description="a gap up to this long in a straight wall line, between two stretches of wall, that no camera "
        "passed through is wall the map did not see (RGB-only misses parts of walls); a doorway the robot has not "
        "used yet stays closed until it does (0: off)",
    )
    wall_run_m: float = Field(
        default=1.0, gt=0.0, description="... between two stretches at least this long (shorter ones: furniture)"
    )
    door_max_m: float = Field(
        default=2.4, ge=0.0,
        description="two regions joined by free space at least this wide (wider than any doorway) are one room: the "
        "distance transform's saddle between them stands at half this (0: h-maxima alone decide)",
    )
    max_cameras: int = Field(default=20_000, ge=1, description="camera positions kept as known-free space (bound)")
    every_keyframes: int = Field(
        default=5, ge=0,
        description="rebuild the rooms every this many keyframes, so ids follow the growing map (0: only when "
        "asked; a query for rooms rebuilds them whenever the graph changed)",
    )
    prior: Path | None = Field(
        default=None, description="indoor prior JSON for room labels (default: the embedded protocol/data one)"
    )


class MapperCoreConfig(BaseModel):
    """The in-process mapping pipeline (no I/O)."""

    model_config = ConfigDict(extra="forbid")
    geometry: GeometryConfig = Field(default_factory=GeometryConfig, description="reconstructor")
    perception: PerceptionConfig = Field(default_factory=PerceptionConfig, description="2D perception")
    fusion: FusionConfig = Field(default_factory=FusionConfig, description="3D fusion of detections")
    relations: RelationConfig = Field(default_factory=RelationConfig, description="relation edge thresholds")
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig, description="keyframes and windows")
    point_map: PointMapConfig = Field(default_factory=PointMapConfig, description="global point map")
    depth_check: DepthCheckConfig = Field(
        default_factory=DepthCheckConfig, description="multi-view depth consistency before fusion"
    )
    pose_check: PoseCheckConfig = Field(
        default_factory=PoseCheckConfig, description="flag calibrated fixed cameras that were bumped"
    )
    single_view: SingleViewConfig = Field(
        default_factory=SingleViewConfig, description="single-view floor geometry for views without stereo partners"
    )
    pose_graph: PoseGraphConfig = Field(
        default_factory=PoseGraphConfig,
        description="loop closure of moving sources' odometry: a planar pose graph over their keyframes with "
        "odometry and verified loop factors; corrects their later frames and moves what earlier ones fused",
    )
    limits: InputLimits = Field(
        default_factory=InputLimits,
        description="what peers may send: frame bytes and pixels, JPEG plausibility, decode budget, intrinsics, "
        "the site's box",
    )
    rooms: RoomsConfig = Field(default_factory=RoomsConfig, description="the room layer over the objects")
    node_embeddings: bool = Field(default=True, description="publish each node's descriptor")
    max_retired: int = Field(
        default=256, ge=0,
        description="retired nodes (seen gone) kept queryable (graph/nodes?include_retired=true), the newest",
    )
    retired_keep_s: float = Field(
        default=3600.0, ge=0.0, description="... for at most this long after retirement (capture time), seconds"
    )
    torch_threads: int = Field(default=2, ge=1, le=64, description="torch CPU threads")


class PublishConfig(BaseModel):
    """Publishing rates of the process."""

    model_config = ConfigDict(extra="forbid")
    snapshot_period_s: float = Field(default=2.0, ge=0.0, description="at most one snapshot per period (0: each)")
    point_map_period_s: float = Field(default=2.0, ge=0.0, description="at most one point map per period")
    point_map_max_points: int = Field(default=100_000, ge=1, description="points per published map")


class RerunConfig(BaseModel):
    """Optional Rerun output (points, labelled boxes, edges, camera frusta with images)."""

    model_config = ConfigDict(extra="forbid")
    file: Path | None = Field(default=None, description="write a .rrd recording here")
    serve: bool = Field(default=False, description="serve a live viewer on 127.0.0.1 only (rerun CLI subprocess)")
    port: int = Field(default=9876, ge=1, le=65535, description="gRPC port of the served stream (127.0.0.1)")
    web_port: int | None = Field(
        default=None, ge=1, le=65535,
        description="with serve: also host the web viewer on http://127.0.0.1:<web_port> (headless servers)",
    )
    server_memory_limit: str = Field(
        default="512MB", description="with serve: the server keeps at most this much for late viewers (oldest dropped)"
    )
    image_width: int = Field(default=160, ge=16, description="logged images are downscaled to this width")
    jpeg_quality: int = Field(default=75, ge=1, le=100, description="logged images are JPEG-compressed")
    point_parts: int = Field(
        default=16, ge=1,
        description="new voxels are logged as parts; beyond this many parts the whole map is logged once afresh",
    )


class MapperConfig(MapperCoreConfig):
    """``argus mapper``: the core plus Zenoh I/O, persistence and logging."""

    id: str = Field(default="mapper", description="process id (liveliness and status keys)")
    site: SiteName = Field(
        default_factory=default_site,
        validate_default=True,
        description="Argus site name (key prefix argus/<site>/...; default $ARGUS_SITE or default)",
    )
    key_prefix: str = Field(default="argus", description="key expression prefix")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how to join Zenoh")
    publish: PublishConfig = Field(default_factory=PublishConfig, description="publishing rates")
    state_dir: Path | None = Field(
        default=None,
        description="persist the graph and the version lease here; a restart resumes it and never reuses a "
        "version or node id (docs/consumers.md: graph versions, epochs and mapper restarts)",
    )
    save_period_s: float = Field(default=5.0, ge=0.0, description="at most one save per period (0: each update)")
    ring_depth: int = Field(default=2, ge=1, le=64, description="frames buffered per source (newest kept)")
    max_sources: int = Field(default=64, ge=1, description="sources accepted (memory bound)")
    oracle_wait_s: float = Field(
        default=1.0, ge=0.0, description="how long a frame waits for its ORACLE sample (sim backends only)"
    )
    max_oracle_cache: int = Field(default=64, ge=1, description="ORACLE samples buffered (memory bound)")
    status_period_s: float = Field(default=1.0, gt=0.0, description="status publishing period")
    release_heap_period_s: float = Field(
        default=5.0, ge=0.0,
        description="give the C heap's freed memory back to the system at most once per this many seconds (glibc "
        "malloc_trim, a few ms; counter heap_releases): keyframes' large temporary arrays otherwise leave the "
        "resting RSS creeping up in plateaus (0: never)",
    )
    rerun: RerunConfig = Field(default_factory=RerunConfig, description="Rerun output")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(default="INFO", description="log level")
    workers: OffloadConfig = Field(
        default_factory=OffloadConfig,
        description="keyframe jobs for argus worker processes (used only while one is alive; not with ORACLE backends)",
    )
