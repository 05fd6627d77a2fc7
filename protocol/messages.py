"""Wire messages (pydantic v2). Every message crossing a process boundary is one of these.

Poses follow the conventions of :mod:`protocol.poses`: ``T_world_cam`` is a 4x4 rigid transform
mapping camera-frame points (OpenCV axes: x right, y down, z forward) into the world frame (metres,
z up). Times are integer nanoseconds since the Unix epoch (``time.time_ns()``).

Arrays travel as plain msgpack maps ``{"dtype", "shape", "data"}`` (:mod:`protocol.arrays`) through
:mod:`protocol.codec` and as nested lists in JSON; in Python they are numpy arrays. Messages compare
equal field by field, arrays included. docs/WIRE.md documents every message for non-Python readers
(its field tables and protocol/schema/*.json are generated from these classes by ``python -m protocol.wire``).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike
from pydantic import (
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from protocol import arrays


def _to_ndarray(v: Any) -> np.ndarray:
    if isinstance(v, np.ndarray):
        return v
    if arrays.is_wire_array(v):
        return arrays.from_wire(v)  # the msgpack map form; ArrayError is a ValueError
    if isinstance(v, (list, tuple)):
        return np.asarray(v)
    raise ValueError(f"expected an array, got {type(v).__name__}")


NDARRAY_JSON_SCHEMA: dict[str, Any] = {
    "description": "numpy array. msgpack: a map {dtype: numpy type string such as '<f4', shape: [int], "
    "data: bin, the raw little-endian C-order bytes}; JSON: nested lists of numbers",
    "anyOf": [
        {
            "type": "object",
            "properties": {
                "dtype": {"type": "string", "enum": sorted(arrays.ALLOWED_DTYPES)},
                "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}, "maxItems": arrays.MAX_DIMS},
                "data": {"description": "msgpack bin: prod(shape) * itemsize bytes"},
            },
            "required": ["dtype", "shape", "data"],
            "additionalProperties": False,
        },
        {"type": "array"},
    ],
}

NDArray = Annotated[
    np.ndarray,
    BeforeValidator(_to_ndarray),
    # JSON dumps (model_dump_json, the JSON view, --json outputs) get nested lists; msgpack keeps the ndarray.
    PlainSerializer(lambda a: a.tolist(), when_used="json"),
    WithJsonSchema(NDARRAY_JSON_SCHEMA),
]


def _to_mat(n: int, m: int) -> Any:
    def check(v: Any) -> list[list[float]]:
        a = np.asarray(v, dtype=np.float64)
        if a.shape != (n, m):
            raise ValueError(f"expected a {n}x{m} matrix, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("matrix entries must be finite")
        return a.tolist()

    return BeforeValidator(check)


def _mat_schema(n: int, m: int) -> WithJsonSchema:
    row = {"type": "array", "items": {"type": "number"}, "minItems": m, "maxItems": m}
    return WithJsonSchema({"type": "array", "items": row, "minItems": n, "maxItems": n,
                           "description": f"{n}x{m} matrix as {n} rows of {m} finite numbers"})


Mat4 = Annotated[list[list[float]], _to_mat(4, 4), _mat_schema(4, 4)]
"""A 4x4 pose (rows), see :mod:`protocol.poses`. ``np.asarray(msg.T_world_cam)`` gives the matrix;
``rows(T)`` gives the field value of an ndarray pose."""
Mat3 = Annotated[list[list[float]], _to_mat(3, 3), _mat_schema(3, 3)]
Mat6 = Annotated[list[list[float]], _to_mat(6, 6), _mat_schema(6, 6)]


def rows(matrix: ArrayLike) -> list[list[float]]:
    """A matrix (an ndarray pose or covariance) as the rows a ``Mat4`` / ``Mat3`` / ``Mat6`` field holds.
    Shape and finiteness are checked by the field."""
    out: list[list[float]] = np.asarray(matrix, dtype=np.float64).tolist()
    return out


def vec3(v: ArrayLike) -> tuple[float, float, float]:
    """A length-3 array (a point, an extent) as the ``(x, y, z)`` tuple a ``Vec3`` field holds."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"expected 3 numbers, got shape {a.shape}")
    return float(a[0]), float(a[1]), float(a[2])


Vec3 = Annotated[tuple[float, float, float], Field(description="x, y, z in metres")]


def _arrays_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
        )
    if isinstance(a, BaseModel) and isinstance(b, BaseModel):
        return type(a) is type(b) and all(
            _arrays_equal(getattr(a, k), getattr(b, k)) for k in type(a).model_fields
        )
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_arrays_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_arrays_equal(a[k], b[k]) for k in a)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


class Message(BaseModel):
    """Base of all wire messages: strict fields, arrays allowed, value equality."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True, frozen=False)
    KIND: ClassVar[str] = ""
    SCHEMA: ClassVar[tuple[int, int]] = (1, 0)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, BaseModel) and _arrays_equal(self, other)

    __hash__ = None  # type: ignore[assignment]


class Intrinsics(Message):
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height``.

    Every value must be finite (a NaN or infinite one fails validation, so such a frame header never
    decodes). Whether they describe a plausible camera (field of view, principal point) is the
    receiver's check: :func:`mapper.intake.intrinsics_problem`.
    """

    KIND: ClassVar[str] = "intrinsics"
    width: int = Field(gt=0, le=16384, description="image width in pixels")
    height: int = Field(gt=0, le=16384, description="image height in pixels")
    fx: float = Field(gt=0, allow_inf_nan=False, description="focal length along u, pixels (finite)")
    fy: float = Field(gt=0, allow_inf_nan=False, description="focal length along v, pixels (finite)")
    cx: float = Field(allow_inf_nan=False, description="principal point u, pixels (finite)")
    cy: float = Field(allow_inf_nan=False, description="principal point v, pixels (finite)")

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view ``hfov_deg``."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width=width, height=height, fx=f, fy=f, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0)

    def K(self) -> np.ndarray:
        """The 3x3 matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution."""
        return self._resampled(width, height, width / self.width, height / self.height)

    def reduced(self, reduction: int) -> Intrinsics:
        """The same camera decoded at 1/``reduction`` (JPEG DCT scaling, ``protocol.jpeg.decode_jpeg``): the image
        is ``ceil(width / reduction)`` x ``ceil(height / reduction)``, each pixel a ``reduction`` x ``reduction``
        block of the full image (a partial block at the right and bottom edges), so the scale is exactly
        1/``reduction`` even where the size does not divide."""
        if reduction < 1:
            raise ValueError(f"reduction must be >= 1, got {reduction}")
        s = 1.0 / reduction
        return self._resampled(-(-self.width // reduction), -(-self.height // reduction), s, s)

    def _resampled(self, width: int, height: int, sx: float, sy: float) -> Intrinsics:
        # Pixel centres: u' + 0.5 = (u + 0.5) * s.
        return Intrinsics(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )


SourceKind = Literal["fixed", "robot"]
Reduction = Literal[1, 2, 4, 8]
"""A JPEG decoded at 1/this of its size (libjpeg DCT scaling: ``protocol.jpeg.REDUCTIONS``)."""


class FrameHeader(Message):
    """Metadata of one camera frame; travels as the attachment of the JPEG sample."""

    KIND: ClassVar[str] = "frame_header"
    SCHEMA: ClassVar[tuple[int, int]] = (1, 1)
    source_id: str = Field(min_length=1, max_length=128, description="camera or robot id")
    source_kind: SourceKind = Field(description="fixed infrastructure camera or robot camera")
    seq: int = Field(ge=0, description="per-source sequence number, +1 per frame sent")
    stamp_ns: int = Field(ge=0, description="capture time, ns since the epoch")
    width: int = Field(gt=0, le=16384, description="JPEG width in pixels")
    height: int = Field(gt=0, le=16384, description="JPEG height in pixels")
    intrinsics: Intrinsics | None = Field(default=None, description="calibration, if known")
    T_world_cam: Mat4 | None = Field(default=None, description="camera pose, if known (odometry/calibration)")
    pose_covariance: Mat6 | None = Field(
        default=None,
        description="6x6 covariance of the pose's error (x y z roll pitch yaw; m^2, rad^2), if known: its "
        "smallest value per source is the per-frame accuracy, its growth between frames drift; null: "
        "undeclared (see 'Pose priors and their accuracy')"
    )
    pose_trusted: bool = Field(
        default=False,
        description="true when T_world_cam is a surveyed calibration, false when it is an odometry prior",
    )
    map_always: bool = Field(
        default=False,
        description="the sender needs this frame mapped (a robot's arrival view, on which its next goal is planned): "
        "an overloaded mapper never sheds its keyframe as stale or superseded, as it does video-rate frames "
        "(schema 1.1)",
    )


RobotStatus = Literal["idle", "moving", "arrived", "failed", "refused", "budget_exhausted"]


class RobotState(Message):
    """A robot's state, published on its state key."""

    KIND: ClassVar[str] = "robot_state"
    SCHEMA: ClassVar[tuple[int, int]] = (1, 1)
    robot_id: str = Field(min_length=1, max_length=128)
    stamp_ns: int = Field(ge=0)
    status: RobotStatus = Field(description="what the robot is doing; refused/failed/budget_exhausted come with reason")
    x: float = Field(description="base position x, metres (odometry)")
    y: float = Field(description="base position y, metres (odometry)")
    yaw_rad: float = Field(description="base heading, radians from world +x, counter-clockwise (odometry)")
    T_world_cam: Mat4 = Field(description="camera pose from odometry")
    goal_id: str | None = Field(default=None, description="the goal being pursued or last finished")
    reason: str | None = Field(default=None, description="why a goal was refused or failed")
    distance_m: float = Field(default=0.0, ge=0.0, description="distance travelled so far")
    steps: int = Field(default=0, ge=0, description="goals reached so far")
    viewpoint_id: int | None = Field(default=None, description="viewpoint the robot stands on, if any")
    travel_cost_m: NDArray | None = Field(
        default=None,
        description="geodesic distance from here to each viewpoint of the robot's ViewpointSet (inf: none)",
    )
    last_frame_seq: int | None = Field(
        default=None, ge=0,
        description="seq of the newest frame this robot published (once arrived: its arrival frame); a planner "
        "waits for a graph version whose ``frames`` cover it (schema 1.1)",
    )

    @field_validator("travel_cost_m")
    @classmethod
    def _one_dimensional(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None and (v.ndim != 1 or v.dtype.kind not in "fiu"):
            raise ValueError("travel_cost_m must be a 1-D numeric array")
        return v


class Viewpoint(Message):
    """One navigable viewpoint: a base pose whose camera pose follows from the set's mount."""

    KIND: ClassVar[str] = "viewpoint"
    vp_id: int = Field(ge=0, description="viewpoint id, unique within its ViewpointSet")
    x: float = Field(description="base position x, metres (world frame)")
    y: float = Field(description="base position y, metres (world frame)")
    yaw_rad: float = Field(description="base heading, radians from world +x, counter-clockwise")
    room: str | None = Field(default=None, description="room name, if known")


class ViewpointSet(Message):
    """Candidate viewpoints of one robot, published so a remote planner knows where it can go."""

    KIND: ClassVar[str] = "viewpoint_set"
    robot_id: str = Field(min_length=1, max_length=128)
    camera_height_m: float = Field(gt=0.0, description="camera height above the floor, metres")
    camera_pitch_deg: float = Field(default=0.0, description="camera tilt, degrees (negative: looking down)")
    intrinsics: Intrinsics = Field(description="the robot camera's calibration")
    max_range_m: float = Field(default=6.0, gt=0.0, description="useful sensing range")
    viewpoints: list[Viewpoint] = Field(description="where the robot can stand; camera pose follows from the mount")


class NbvGoal(Message):
    """A next-best-view goal for one robot."""

    KIND: ClassVar[str] = "nbv_goal"
    goal_id: str = Field(min_length=1, max_length=128, description="sender-chosen id, echoed in GoalStatus")
    robot_id: str = Field(min_length=1, max_length=128)
    stamp_ns: int = Field(ge=0)
    x: float = Field(description="goal base position x, metres (world frame)")
    y: float = Field(description="goal base position y, metres (world frame)")
    yaw_rad: float = Field(description="goal heading, radians from world +x, counter-clockwise")
    vp_id: int | None = Field(default=None, description="the viewpoint chosen, if from the robot's set")
    strategy: str = Field(default="", description="planner strategy (see, asp, ...)")
    expected_gain: float = Field(default=0.0, description="score of the goal (bits for asp)")
    reason: str = Field(default="", description="why this goal")
    graph_version: int = Field(default=0, ge=0, description="graph version the goal was planned on")


class OrientedBox(Message):
    """Gravity-aligned oriented box: rotated by ``yaw_rad`` about world z."""

    KIND: ClassVar[str] = "oriented_box"
    center: Vec3
    extent: Vec3 = Field(description="full side lengths along the box's x, y, z axes, metres")
    yaw_rad: float = Field(default=0.0, description="rotation about world z, radians")

    @field_validator("extent")
    @classmethod
    def _non_negative(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) < 0:
            raise ValueError("box extents must be >= 0")
        return v


class LabelScore(Message):
    KIND: ClassVar[str] = "label_score"
    label: str = Field(description="a candidate label")
    score: float = Field(description="its score (0..1 for the built-in labelers)")


class GraphNode(Message):
    """One object node of the scene graph."""

    KIND: ClassVar[str] = "graph_node"
    node_id: str = Field(min_length=1, max_length=64, description="stable id of the object (a single key chunk)")
    label: str = Field(description="best label, e.g. chair")
    label_confidence: float = Field(ge=0.0, le=1.0, description="confidence of the label, 0..1")
    label_alternatives: list[LabelScore] = Field(default_factory=list, description="runner-up labels")
    centroid: Vec3 = Field(description="centre of the object's points, x, y, z in metres (world frame)")
    box: OrientedBox = Field(description="bounding box (world frame, metres)")
    point_count: int = Field(ge=0, description="3D points fused into the object")
    observation_count: int = Field(ge=0, description="frames that observed it")
    sources: list[str] = Field(default_factory=list, description="source ids that observed it")
    first_seen_ns: int = Field(ge=0, description="capture time of the first observation, ns since the epoch")
    last_seen_ns: int = Field(ge=0, description="capture time of the latest observation, ns since the epoch")
    embedding: NDArray | None = Field(default=None, description="region descriptor (float32), optional")

    @field_validator("embedding")
    @classmethod
    def _descriptor(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None and (v.ndim != 1 or v.dtype.kind != "f"):
            raise ValueError("embedding must be a 1-D float array")
        return v


Predicate = Literal["on_top_of", "under", "over", "inside", "next_to"]
PREDICATES: tuple[str, ...] = ("on_top_of", "under", "over", "inside", "next_to")


class GraphEdge(Message):
    """A relation ``subject predicate object``, e.g. cup on_top_of table."""

    KIND: ClassVar[str] = "graph_edge"
    subject_id: str = Field(description="node id of the subject (e.g. the cup)")
    predicate: Predicate = Field(description="the spatial relation")
    object_id: str = Field(description="node id of the object (e.g. the table)")


class NodeMove(Message):
    """A node moved: the mapper saw its object at a new place while its old place was seen empty, and kept its id.
    ``stamp_ns`` is the node's last move time (``last_moved``)."""

    KIND: ClassVar[str] = "node_move"
    node_id: str = Field(min_length=1, max_length=64, description="the node that moved (same id before and after)")
    stamp_ns: int = Field(ge=0, description="capture time of the keyframe that saw it at its new place, ns since "
                          "the epoch (the node's last_moved time)")
    from_centroid: Vec3 = Field(description="its centroid before the move, x, y, z in metres (world frame)")
    to_centroid: Vec3 = Field(description="its centroid after the move, x, y, z in metres (world frame)")
    moves: int = Field(default=1, ge=1, description="how many times the node has moved, this move included")


RetireReason = Literal["absent"]


class RetiredNode(Message):
    """A node the mapper retired (removed from the graph) because keyframes saw its place empty; kept queryable
    for a while (``graph/nodes?include_retired=true``). Its id is never reused."""

    KIND: ClassVar[str] = "retired_node"
    node: GraphNode = Field(description="the node as it was when retired (its centroid is where it was last seen)")
    retired_ns: int = Field(ge=0, description="capture time of the keyframe that retired it, ns since the epoch")
    version: int = Field(ge=0, description="the graph version whose delta removed it")
    reason: RetireReason = Field(
        default="absent", description="why: absent = cameras saw its place empty (not merely hidden) often enough"
    )
    last_moved_ns: int = Field(default=0, ge=0, description="its last move time (0: never moved)")


EPOCH_DESCRIPTION = (
    "the mapper's version/id sequence this message belongs to (schema 1.2; '' from older mappers): within one "
    "epoch versions only grow, one version is one graph and one node id one object, across mapper restarts "
    "included; a new epoch (a mapper that started without its state, or lost its version lease) restarts "
    "both, and a consumer adopts its snapshot whatever the version (see protocol.graph.GraphFollower)"
)
MAX_EPOCH_CHARS = 64


# --- the room layer (served on graph/rooms; in snapshots and deltas since graph_snapshot / graph_delta 1.4) ---
RoomPredicate = Literal["in_room", "connects"]
ROOM_PREDICATES: tuple[str, ...] = ("in_room", "connects")


class RoomNode(Message):
    """One room of a floor."""

    KIND: ClassVar[str] = "room_node"
    room_id: str = Field(min_length=1, max_length=64, description="stable id of the room (a single key chunk), "
                         "e.g. room3; kept as the map grows into the room")
    label: str = Field(description="room kind from its objects, e.g. kitchen, bedroom, living_room; 'unknown' "
                       "until an object says something about it")
    label_confidence: float = Field(ge=0.0, le=1.0, description="posterior probability of the label (0 when unknown)")
    polygon: list[tuple[float, float]] = Field(
        description="outline, x, y in metres (world frame), counter-clockwise, not closed (last != first)")
    floor_z_m: float = Field(description="floor height, metres (world z)")
    area_m2: float = Field(ge=0.0, description="floor area, square metres")
    observed_fraction: float = Field(
        ge=0.0, le=1.0, description="share of the room's floor seen (observed floor, camera paths, object footprints)")
    centroid: tuple[float, float] = Field(description="centre of the room's floor, x, y metres (world frame)")


class RoomEdge(Message):
    """``object in_room room`` or ``room connects room`` (the latter with its doorway)."""

    KIND: ClassVar[str] = "room_edge"
    subject_id: str = Field(description="in_room: an object node id; connects: a room id")
    predicate: RoomPredicate = Field(description="in_room or connects")
    object_id: str = Field(description="a room id")
    position: tuple[float, float] | None = Field(
        default=None, description="connects: the doorway's middle, x, y metres (world frame); in_room: null")
    width_m: float | None = Field(default=None, ge=0.0, description="connects: the doorway's width; in_room: null")


class RoomLayer(Message):
    """All rooms and room edges at one graph version of one epoch."""

    KIND: ClassVar[str] = "room_layer"
    epoch: str = Field(default="", max_length=MAX_EPOCH_CHARS, description=EPOCH_DESCRIPTION)
    version: int = Field(ge=0, description="the graph version the layer was built at")
    stamp_ns: int = Field(ge=0, description="when it was built, ns since the epoch")
    rooms: list[RoomNode] = Field(default_factory=list)
    edges: list[RoomEdge] = Field(default_factory=list, description="in_room edges, then connects edges")

    def room_of(self, node_id: str) -> str | None:
        """The room id an object node is in (None: in none)."""
        return next((e.object_id for e in self.edges if e.predicate == "in_room" and e.subject_id == node_id), None)

    def members(self, room_id: str) -> list[str]:
        """Object node ids in ``room_id``."""
        return [e.subject_id for e in self.edges if e.predicate == "in_room" and e.object_id == room_id]



class GraphSnapshot(Message):
    """The whole graph at one version of one epoch."""

    KIND: ClassVar[str] = "graph_snapshot"
    SCHEMA: ClassVar[tuple[int, int]] = (1, 4)
    epoch: str = Field(default="", max_length=MAX_EPOCH_CHARS, description=EPOCH_DESCRIPTION)
    version: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    nodes: list[GraphNode] = Field(default_factory=list)
    edges: list[GraphEdge] = Field(default_factory=list)
    frames: dict[str, int] = Field(
        default_factory=dict,
        description="per source id, the newest frame seq the mapper had processed at this version (schema 1.1)",
    )
    moves: list[NodeMove] = Field(
        default_factory=list,
        description="the last move of each node of nodes that ever moved, by node_id: a node's last_moved time is "
        "its entry's stamp_ns (no entry: never moved; a retired node's is in its record) (schema 1.3)",
    )
    retired: list[RetiredNode] = Field(
        default_factory=list,
        description="retired nodes, newest first: only in answers to graph/nodes?include_retired=true (the "
        "selection's other parameters apply to them too); empty otherwise (schema 1.3)",
    )
    rooms: RoomLayer | None = Field(
        default=None,
        description="the room layer as the deltas up to this version carried it (rebuilt every rooms.every_keyframes "
        "keyframes; graph/rooms may answer a newer one); null: no rooms built yet, or rooms off (schema 1.4)",
    )


class GraphDelta(Message):
    """Changes from version ``version - 1`` to ``version`` of one epoch (versions increase by exactly one)."""

    KIND: ClassVar[str] = "graph_delta"
    SCHEMA: ClassVar[tuple[int, int]] = (1, 4)
    epoch: str = Field(default="", max_length=MAX_EPOCH_CHARS, description=EPOCH_DESCRIPTION)
    version: int = Field(ge=1)
    stamp_ns: int = Field(ge=0)
    upserted: list[GraphNode] = Field(default_factory=list)
    removed: list[str] = Field(default_factory=list)
    edges_added: list[GraphEdge] = Field(default_factory=list)
    edges_removed: list[GraphEdge] = Field(default_factory=list)
    frames: dict[str, int] = Field(
        default_factory=dict,
        description="sources whose newest processed frame seq advanced with this version, and that seq; a delta "
        "may carry only this (a robot's arrival frame that changed nothing) (schema 1.1)",
    )
    moves: list[NodeMove] = Field(
        default_factory=list,
        description="nodes of upserted that moved at this version (same id, new place) (schema 1.3)",
    )
    retired: list[RetiredNode] = Field(
        default_factory=list,
        description="nodes of removed that were retired because their place was seen empty (the others were "
        "merged into another node or pruned as noise) (schema 1.3)",
    )
    rooms: RoomLayer | None = Field(
        default=None,
        description="the whole room layer when it changed at this version (it replaces the consumer's); null: "
        "unchanged (schema 1.4)",
    )


class PointMap(Message):
    """Downsampled world point map for planners (and viewers)."""

    KIND: ClassVar[str] = "point_map"
    version: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    voxel_m: float = Field(gt=0.0, description="voxel size of the downsampling, metres")
    points: NDArray = Field(description="(N, 3) float32 world points")
    counts: NDArray | None = Field(default=None, description="(N,) observations per voxel")
    colors: NDArray | None = Field(default=None, description="(N, 3) uint8")

    @model_validator(mode="after")
    def _shapes_agree(self) -> PointMap:
        p = self.points
        if p.ndim != 2 or p.shape[1] != 3 or p.dtype.kind != "f":
            raise ValueError(f"points must be a float (N, 3) array, got {p.dtype} {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points must be finite")
        n = p.shape[0]
        if self.counts is not None and self.counts.shape != (n,):
            raise ValueError(f"counts must have shape ({n},), got {self.counts.shape}")
        if self.colors is not None and self.colors.shape != (n, 3):
            raise ValueError(f"colors must have shape ({n}, 3), got {self.colors.shape}")
        return self


class Status(Message):
    """Heartbeat and counters of one process, published at a low rate."""

    KIND: ClassVar[str] = "status"
    role: str = Field(description="process role: mapper, planner, robot-agent, edge-camera, ...")
    node_id: str = Field(description="process id within its role")
    stamp_ns: int = Field(ge=0)
    state: str = Field(default="ok", description="ok / degraded / error / starting / stopping / no_link")
    counters: dict[str, float] = Field(default_factory=dict, description="named counters and gauges")
    last_error: str | None = Field(default=None, description="the latest error, if any")


Heartbeat = Status


class OracleFrame(Message):
    """Simulator ground truth for one frame (ORACLE: only simulated sources publish it).

    Like Habitat's semantic and depth sensors: the ``sim`` segmenter (an oracle for 2D perception)
    and the ``oracle`` reconstructor (true geometry, the paper's "CG" baseline) read it; the default
    RGB-only pipeline never does. Matched to its frame by ``(source_id, seq)``.
    """

    KIND: ClassVar[str] = "oracle_frame"
    source_id: str = Field(min_length=1, max_length=128, description="the simulated camera or robot")
    seq: int = Field(ge=0, description="seq of the frame this ground truth belongs to")
    stamp_ns: int = Field(ge=0)
    T_world_cam_true: Mat4 = Field(description="true camera pose")
    ids_png: bytes | None = Field(
        default=None, description="16-bit PNG of instance ids: 0 = structure or nothing, k = object id"
    )
    depth_png: bytes | None = Field(default=None, description="16-bit PNG of z-depth in millimetres (0 = none)")
    labels: dict[str, str] = Field(default_factory=dict, description="str(object id) -> label")

class GoalStatus(Message):
    """A robot's answer to one goal message it received: accepted, or refused with the reason.

    Published on ``robot/<id>/goal/status`` (and as JSON on ``robot/<id>/goal/status/json``) for every
    goal payload, undecodable ones included (refusals are rate-limited; ``suppressed`` counts the ones
    not published since the last published status).
    """

    KIND: ClassVar[str] = "goal_status"
    robot_id: str = Field(min_length=1, max_length=128, description="the robot answering")
    stamp_ns: int = Field(ge=0, description="when the robot decided, ns since the epoch")
    goal_id: str | None = Field(
        default=None, description="the goal's id (assigned by the robot for plain goals without one); null when "
        "the payload was unreadable"
    )
    accepted: bool = Field(description="true: the robot is driving to the goal (or already pursues it)")
    reason: str = Field(default="", description="why the goal was refused (validation error, ...); empty if accepted")
    received: int = Field(ge=0, description="goal payloads this robot has received so far, this one included")
    suppressed: int = Field(default=0, ge=0, description="refusals not published (rate limit) since the last status")


class WorkFrame(Message):
    """One view of a keyframe job (mapper -> worker): everything of the frame but its pixels.

    The job's target travels with its JPEG; a source keyframe's JPEG is fetched by the worker from the
    mapper's keyframe store (``work/keyframe/<source_id>/<seq>``), identified by ``(source_id, seq)``.
    """

    KIND: ClassVar[str] = "work_frame"
    # 1.1: reduction (the size its JPEG is decoded at).
    SCHEMA: ClassVar[tuple[int, int]] = (1, 1)
    source_id: str = Field(min_length=1, max_length=128, description="camera or robot id")
    seq: int = Field(ge=0, description="the frame's sequence number within its source")
    stamp_ns: int = Field(default=0, ge=0, description="capture time, ns since the epoch")
    width: int = Field(gt=0, le=65535, description="image width, pixels: the JPEG decoded at 1/reduction")
    height: int = Field(gt=0, le=65535, description="image height, pixels: the JPEG decoded at 1/reduction")
    reduction: Reduction = Field(
        default=1,
        description="the mapper decoded the frame's JPEG at 1/reduction of its size (libjpeg DCT scaling; its "
        "limits.max_working_pixels) and so must the worker: width x height is then ceil(JPEG size / reduction) and "
        "the intrinsics are the reduced image's (schema 1.1)",
    )
    intrinsics: Intrinsics | None = Field(default=None, description="null: an uncalibrated camera")
    T_world_cam: Mat4 | None = Field(
        default=None, description="the pose the mapper holds for this view (prior or registered); null: unknown"
    )
    pose_trusted: bool = Field(default=False, description="a surveyed calibration reconstruction must not move")
    pose_covariance: Mat6 | None = Field(
        default=None, description="the pose covariance the frame's header declared (x y z roll pitch yaw; m^2, rad^2)"
    )
    prior_rel_trans_m: float | None = Field(
        default=None, ge=0, description="per-frame std-dev of the prior's position relative to the source's other "
        "frames, metres (null: judged from the images; +inf: independent per-frame errors)"
    )
    prior_rel_rot_deg: float | None = Field(
        default=None, ge=0, description="the same for the rotation, degrees"
    )


class WorkJob(Message):
    """A keyframe job: the mapper asks a worker (``argus worker``) for one keyframe's heavy products.

    Put on ``work/job/<worker_id>``; the worker answers ``work_ack`` at once and ``work_result`` when done.
    Results are idempotent by ``job_id`` (the keyframe id): the first valid one wins.
    """

    KIND: ClassVar[str] = "work_job"
    # 1.1: its frames carry the declared pose accuracy (pose_covariance, prior_rel_*).
    # 1.2: its frames carry the reduction their JPEGs are decoded at (a worker of 1.1 fails such a job: the image it
    # decodes is not the frame's size; the mapper then re-issues it and at last does it itself).
    SCHEMA: ClassVar[tuple[int, int]] = (1, 2)
    job_id: str = Field(min_length=1, max_length=300, description="the keyframe id: <source_id>#<seq>")
    attempt: int = Field(ge=1, description="1 for the first issue, +1 for each re-issue")
    window: list[WorkFrame] = Field(min_length=1, max_length=64, description="the views reconstructed together")
    target_index: int = Field(ge=0, description="the keyframe's position in window")
    jpeg: bytes = Field(description="the keyframe's JPEG bytes (as the camera sent them)")
    perception: bool = Field(description="also run 2D perception (segmenter and embedder) on the keyframe")
    core_config: dict[str, Any] = Field(
        description="the mapper's geometry, perception and fusion settings (a worker runs exactly these)"
    )
    config_digest: str = Field(max_length=128, description="digest of core_config (workers cache backends by it)")

    @model_validator(mode="after")
    def _target_in_window(self) -> WorkJob:
        if self.target_index >= len(self.window):
            raise ValueError(f"target_index {self.target_index} is outside the window of {len(self.window)}")
        return self


class WorkAck(Message):
    """A worker took a job (``work/ack/<worker_id>``)."""

    KIND: ClassVar[str] = "work_ack"
    job_id: str = Field(min_length=1, max_length=300, description="the job taken")
    attempt: int = Field(ge=1, description="the attempt taken")
    worker_id: str = Field(min_length=1, max_length=128, description="the worker")


class WorkDetection(Message):
    """One labelled 2D detection of a keyframe result."""

    KIND: ClassVar[str] = "work_detection"
    mask_png: bytes = Field(description="8-bit PNG at the image's size: nonzero = inside the mask")
    label: str = Field(max_length=256, description="class label")
    confidence: float = Field(description="label confidence in [0, 1]")
    descriptor: NDArray = Field(description="unit descriptor, 1-D float32 (float64 when the embedder makes those)")
    alternatives: list[tuple[str, float]] = Field(default_factory=list, description="other (label, score)")
    instance_key: int = Field(default=0, description="backend-specific instance id (logs)")


class WorkResult(Message):
    """A keyframe job's products (``work/result/<worker_id>``): depth, confidence, refined pose, detections.

    ``ok`` false: the worker could not do the job (``error`` says why; the mapper re-issues it).
    ``anchored`` false: the reconstruction could not place the keyframe in the world (a valid answer).
    """

    KIND: ClassVar[str] = "work_result"
    job_id: str = Field(min_length=1, max_length=300, description="the job answered")
    attempt: int = Field(ge=1, description="the attempt answered")
    worker_id: str = Field(min_length=1, max_length=128, description="the worker")
    ok: bool = Field(description="the job was done")
    error: str | None = Field(default=None, max_length=2000, description="why not, when ok is false")
    anchored: bool = Field(default=True, description="the reconstruction placed the keyframe in the world")
    T_world_cam: Mat4 | None = Field(default=None, description="refined pose of the keyframe")
    intrinsics: Intrinsics | None = Field(default=None, description="intrinsics at the depth map's resolution")
    depth_png: bytes | None = Field(
        default=None, description="16-bit PNG of z-depth in units of depth_unit_m (0 = none)"
    )
    depth_unit_m: float = Field(default=0.001, gt=0.0, description="metres per depth PNG unit")
    confidence_png: bytes | None = Field(default=None, description="16-bit PNG of depth confidence x 65535")
    detections: list[WorkDetection] | None = Field(
        default=None, description="2D detections; null when perception was not asked for or skipped"
    )
    timings_s: dict[str, float] = Field(default_factory=dict, description="seconds per stage on the worker")


class PlainGoal(BaseModel):
    """A goal as a plain JSON object or plain msgpack map (no envelope), for clients without Argus.

    The robot turns it into an :class:`NbvGoal` (``goal_id`` assigned when absent, ``stamp_ns`` = receipt).
    Not an envelope message: it has no kind and no version.
    """

    model_config = ConfigDict(extra="forbid")
    robot_id: str = Field(min_length=1, max_length=128, description="the robot that must drive")
    x: float = Field(description="goal base position x, metres (world frame)")
    y: float = Field(description="goal base position y, metres (world frame)")
    yaw_rad: float = Field(
        default=0.0, validation_alias=AliasChoices("yaw_rad", "yaw"),
        description="goal heading, radians from world +x, counter-clockwise (key 'yaw' or 'yaw_rad')",
    )
    goal_id: str | None = Field(default=None, min_length=1, max_length=128, description="optional id echoed back")
    vp_id: int | None = Field(default=None, ge=0, description="viewpoint id, if the goal is one of the robot's")


ALL_MESSAGES: tuple[type[Message], ...] = (
    Intrinsics,
    FrameHeader,
    RobotState,
    Viewpoint,
    ViewpointSet,
    NbvGoal,
    OrientedBox,
    LabelScore,
    GraphNode,
    GraphEdge,
    NodeMove,
    RetiredNode,
    GraphSnapshot,
    GraphDelta,
    PointMap,
    Status,
    OracleFrame,
    GoalStatus,
    WorkFrame,
    WorkJob,
    WorkAck,
    WorkDetection,
    WorkResult,
)
