"""Zenoh key expressions. Every Argus key is built and parsed here and nowhere else.

Layout (``prefix`` and ``site`` configurable)::

    <prefix>/<site>/cam/<camera_id>/frame          fixed-camera JPEG frames
    <prefix>/<site>/robot/<robot_id>/frame         robot-camera JPEG frames
    <prefix>/<site>/{cam,robot}/<id>/oracle        OracleFrame (simulated sources only: ground truth)
    <prefix>/<site>/robot/<robot_id>/state         RobotState
    <prefix>/<site>/robot/<robot_id>/goal          NbvGoal (or a plain JSON/msgpack goal, see docs/WIRE.md)
    <prefix>/<site>/robot/<robot_id>/goal/status   GoalStatus (the robot's answer to each goal payload)
    <prefix>/<site>/robot/<robot_id>/goal/status/json   the same GoalStatus as JSON
    <prefix>/<site>/robot/<robot_id>/viewpoints    ViewpointSet
    <prefix>/<site>/graph/snapshot                 GraphSnapshot (latest full graph)
    <prefix>/<site>/graph/delta                    GraphDelta
    <prefix>/<site>/graph/node/<node_id>           GraphNode (plain key/value, storable)
    <prefix>/<site>/graph/nodes                    query target: selected nodes (?label=..;near=..)
    <prefix>/<site>/graph/json/...                 JSON view (query only): json/snapshot, json/nodes, json/node/<id>
    <prefix>/<site>/map/points                     PointMap
    <prefix>/<site>/alive/<role>/<id>              liveliness tokens
    <prefix>/<site>/status/<role>/<id>             Status
    <prefix>/<site>/work/job/<worker_id>           WorkJob (mapper -> worker: a keyframe job)
    <prefix>/<site>/work/ack/<worker_id>           WorkAck (worker -> mapper: job taken)
    <prefix>/<site>/work/result/<worker_id>        WorkResult (worker -> mapper: the keyframe's products)
    <prefix>/<site>/work/keyframe/<source_id>/<seq>   query: a keyframe's JPEG (the mapper's keyframe store)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import AfterValidator

_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
_FORBIDDEN = set("/*$?#")

SourceKey = Literal["cam", "robot"]


def validate_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a safe single key chunk, else raise ``ValueError``.

    Refused: empty, longer than 128, or containing ``/ * $ ? #`` or anything outside
    letters, digits, ``_ . -``.
    """
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty string")
    if len(value) > 128:
        raise ValueError(f"{what} is longer than 128 characters")
    if _FORBIDDEN & set(value) or not _ID_RE.match(value) or value in {".", ".."}:
        raise ValueError(f"{what} {value!r} may only hold letters, digits, '_', '.', '-'")
    return value


SiteName = Annotated[str, AfterValidator(lambda v: validate_id(v, "site"))]
"""A site name in a pydantic config: validated as one key chunk."""


@dataclass(frozen=True)
class Keys:
    """Key expression builder for one site."""

    site: str = "default"
    prefix: str = "argus"

    def __post_init__(self) -> None:
        validate_id(self.site, "site")
        for chunk in self.prefix.split("/"):
            validate_id(chunk, "prefix chunk")

    @property
    def root(self) -> str:
        return f"{self.prefix}/{self.site}"

    # --- frames ---------------------------------------------------------------------------
    def cam_frame(self, camera_id: str) -> str:
        return f"{self.root}/cam/{validate_id(camera_id, 'camera id')}/frame"

    def robot_frame(self, robot_id: str) -> str:
        return f"{self.root}/robot/{validate_id(robot_id, 'robot id')}/frame"

    def frame(self, kind: Literal["fixed", "robot"], source_id: str) -> str:
        """Frame key for a source of the given FrameHeader kind."""
        return self.cam_frame(source_id) if kind == "fixed" else self.robot_frame(source_id)

    def oracle(self, kind: Literal["fixed", "robot"], source_id: str) -> str:
        """ORACLE ground-truth key paired with a simulated source's frame key (see OracleFrame)."""
        return self.frame(kind, source_id)[: -len("frame")] + "oracle"

    @property
    def all_oracle(self) -> str:
        return f"{self.root}/*/*/oracle"

    @property
    def all_frames(self) -> str:
        """Matches every camera and robot frame key of the site."""
        return f"{self.root}/*/*/frame"

    # --- robots ---------------------------------------------------------------------------
    def robot_state(self, robot_id: str) -> str:
        return f"{self.root}/robot/{validate_id(robot_id, 'robot id')}/state"

    def robot_goal(self, robot_id: str) -> str:
        return f"{self.root}/robot/{validate_id(robot_id, 'robot id')}/goal"

    def robot_goal_status(self, robot_id: str) -> str:
        """GoalStatus (msgpack envelope) of each goal payload the robot received."""
        return f"{self.robot_goal(robot_id)}/status"

    def robot_goal_status_json(self, robot_id: str) -> str:
        """The same GoalStatus as a JSON object."""
        return f"{self.robot_goal(robot_id)}/status/json"

    def robot_viewpoints(self, robot_id: str) -> str:
        return f"{self.root}/robot/{validate_id(robot_id, 'robot id')}/viewpoints"

    @property
    def all_robot_states(self) -> str:
        return f"{self.root}/robot/*/state"

    @property
    def all_robot_goals(self) -> str:
        return f"{self.root}/robot/*/goal"

    @property
    def all_robot_viewpoints(self) -> str:
        return f"{self.root}/robot/*/viewpoints"

    # --- graph ----------------------------------------------------------------------------
    @property
    def graph_snapshot(self) -> str:
        return f"{self.root}/graph/snapshot"

    @property
    def graph_delta(self) -> str:
        return f"{self.root}/graph/delta"

    def graph_node(self, node_id: str) -> str:
        return f"{self.root}/graph/node/{validate_id(node_id, 'node id')}"

    @property
    def graph_nodes(self) -> str:
        """Query target for node selections (parameters: label, near, radius, id, since_version, room)."""
        return f"{self.root}/graph/nodes"

    @property
    def graph_rooms(self) -> str:
        """Query target for the room layer (protocol.rooms.RoomLayer: rooms, in_room and connects edges)."""
        return f"{self.root}/graph/rooms"

    @property
    def graph_all(self) -> str:
        """Everything under graph/ (the mapper's queryable)."""
        return f"{self.root}/graph/**"

    @property
    def graph_json_all(self) -> str:
        """The JSON view: ``graph/json/<k>`` answers like ``graph/<k>``, as JSON (the mapper's second queryable)."""
        return f"{self.root}/graph/json/**"

    def graph_json(self, key: str) -> str:
        """The JSON-view twin of a graph key: ``graph/<k>`` -> ``graph/json/<k>``."""
        head = f"{self.root}/graph/"
        if not key.startswith(head) or key.startswith(head + "json/"):
            raise ValueError(f"{key!r} is not a graph key outside the JSON view")
        return head + "json/" + key[len(head) :]

    def from_graph_json(self, key: str) -> str:
        """The graph key a JSON-view key stands for: ``graph/json/<k>`` -> ``graph/<k>``."""
        head = f"{self.root}/graph/json/"
        if not key.startswith(head) or len(key) == len(head):
            raise ValueError(f"{key!r} is not a key of the JSON view")
        return f"{self.root}/graph/" + key[len(head) :]

    # --- map ------------------------------------------------------------------------------
    @property
    def map_points(self) -> str:
        return f"{self.root}/map/points"

    # --- presence and status --------------------------------------------------------------
    def alive(self, role: str, node_id: str) -> str:
        return f"{self.root}/alive/{validate_id(role, 'role')}/{validate_id(node_id, 'node id')}"

    def all_alive_of(self, role: str) -> str:
        """Liveliness tokens of every process of one role."""
        return f"{self.root}/alive/{validate_id(role, 'role')}/*"

    @property
    def all_alive(self) -> str:
        return f"{self.root}/alive/**"

    def status(self, role: str, node_id: str) -> str:
        return f"{self.root}/status/{validate_id(role, 'role')}/{validate_id(node_id, 'node id')}"

    @property
    def all_status(self) -> str:
        return f"{self.root}/status/**"

    # --- workers (argus worker) --------------------------------------------------------------
    def work_job(self, worker_id: str) -> str:
        """Keyframe jobs for one worker (the mapper puts, the worker subscribes)."""
        return f"{self.root}/work/job/{validate_id(worker_id, 'worker id')}"

    def work_ack(self, worker_id: str) -> str:
        return f"{self.root}/work/ack/{validate_id(worker_id, 'worker id')}"

    def work_result(self, worker_id: str) -> str:
        return f"{self.root}/work/result/{validate_id(worker_id, 'worker id')}"

    @property
    def all_work_acks(self) -> str:
        return f"{self.root}/work/ack/*"

    @property
    def all_work_results(self) -> str:
        return f"{self.root}/work/result/*"

    def work_keyframe(self, source_id: str, seq: int) -> str:
        """Query target: one keyframe's JPEG from the mapper's keyframe store."""
        if not isinstance(seq, int) or seq < 0:
            raise ValueError(f"seq must be a non-negative integer, got {seq!r}")
        return f"{self.root}/work/keyframe/{validate_id(source_id, 'source id')}/{seq}"

    @property
    def all_work_keyframes(self) -> str:
        """The mapper's keyframe-store queryable."""
        return f"{self.root}/work/keyframe/*/*"

    def parse_work_keyframe(self, key: str) -> tuple[str, int]:
        """``(source_id, seq)`` of a ``work/keyframe/<source_id>/<seq>`` key."""
        parts = self._rest(key)
        if len(parts) != 4 or parts[:2] != ["work", "keyframe"] or not parts[3].isdigit():
            raise ValueError(f"{key!r} is not a work keyframe key")
        return validate_id(parts[2]), int(parts[3])

    def parse_work(self, key: str) -> tuple[str, str]:
        """``(topic, worker_id)`` of a ``work/{job,ack,result}/<worker_id>`` key."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[0] != "work" or parts[1] not in ("job", "ack", "result"):
            raise ValueError(f"{key!r} is not a work key")
        return parts[1], validate_id(parts[2])

    # --- parsers --------------------------------------------------------------------------
    def _rest(self, key: str) -> list[str]:
        root = self.root + "/"
        if not key.startswith(root):
            raise ValueError(f"key {key!r} is not under {self.root!r}")
        return key[len(root) :].split("/")

    def parse_frame(self, key: str) -> tuple[Literal["fixed", "robot"], str]:
        """``(source_kind, source_id)`` of a frame (or oracle) key."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[2] not in ("frame", "oracle") or parts[0] not in ("cam", "robot"):
            raise ValueError(f"{key!r} is not a frame key")
        kind: Literal["fixed", "robot"] = "fixed" if parts[0] == "cam" else "robot"
        return kind, validate_id(parts[1])

    def parse_robot(self, key: str) -> tuple[str, str]:
        """``(robot_id, topic)`` of a robot key (topic: frame, state, goal, viewpoints)."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[0] != "robot" or parts[2] not in ("frame", "oracle", "state", "goal", "viewpoints"):
            raise ValueError(f"{key!r} is not a robot key")
        return validate_id(parts[1]), parts[2]

    def parse_node(self, key: str) -> str:
        """Node id of a ``graph/node/<id>`` key."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[:2] != ["graph", "node"]:
            raise ValueError(f"{key!r} is not a graph node key")
        return validate_id(parts[2])

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``(role, id)`` of a liveliness key."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[0] != "alive":
            raise ValueError(f"{key!r} is not a liveliness key")
        return validate_id(parts[1]), validate_id(parts[2])

    def parse_status(self, key: str) -> tuple[str, str]:
        """``(role, id)`` of a status key."""
        parts = self._rest(key)
        if len(parts) != 3 or parts[0] != "status":
            raise ValueError(f"{key!r} is not a status key")
        return validate_id(parts[1]), validate_id(parts[2])
