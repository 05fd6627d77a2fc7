"""The wire contract (docs/WIRE.md) in the fast tier: generated docs and schemas match the models, arrays
are plain msgpack maps, encodings name schemas, the JSON view, goal payload parsing, goal answers and
their rate limit, and ``argus goal`` against a real robot agent."""

from __future__ import annotations

import json
import re
import time
from typing import Any

import jsonschema
import msgpack
import numpy as np
import pytest

from protocol import arrays, wire
from protocol.codec import DecodeError, content_type, decode, encode
from protocol.keys import Keys
from protocol.messages import (
    ALL_MESSAGES,
    GoalStatus,
    GraphEdge,
    GraphNode,
    GraphSnapshot,
    NbvGoal,
    OrientedBox,
    PlainGoal,
    PointMap,
    RobotState,
    Status,
)
from protocol.query import GraphQuery
from protocol.rooms import RoomEdge, RoomLayer, RoomNode
from robot_agent.goals import GoalRefused, RefusalLimiter, parse_goal
from tests.support.procs import Proc, wait_for


def node(node_id: str = "n1", label: str = "chair", emb: bool = True) -> GraphNode:
    return GraphNode(
        node_id=node_id, label=label, label_confidence=0.8, centroid=(1.0, 2.0, 0.5),
        box=OrientedBox(center=(1.0, 2.0, 0.5), extent=(0.5, 0.5, 0.9)), point_count=10, observation_count=2,
        sources=["cam0"], first_seen_ns=1, last_seen_ns=2,
        embedding=np.arange(4, dtype=np.float32) / 4 if emb else None,
    )


def legacy_encode(msg: Any) -> bytes:
    """An envelope as Argus builds before the wire contract made it: arrays in msgpack ext type 1."""

    def default(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            a = np.ascontiguousarray(obj)
            return msgpack.ExtType(1, msgpack.packb([a.dtype.str, list(a.shape), a.tobytes()], use_bin_type=True))
        if isinstance(obj, tuple):
            return list(obj)
        raise TypeError(type(obj))

    major, minor = type(msg).SCHEMA
    return msgpack.packb(["ARG1", type(msg).KIND, major, minor, msg.model_dump(mode="python")], default=default,
                         use_bin_type=True)


# --- generated contract --------------------------------------------------------------------------
def test_wire_md_and_schema_files_match_the_models() -> None:
    assert wire.drift() == [], "run: python -m protocol.wire --write"


def test_drift_is_detected(tmp_path) -> None:  # noqa: ANN001
    (tmp_path / "schema").mkdir()
    for name, text in wire.schema_files().items():
        (tmp_path / "schema" / name).write_text(text)
    md = wire.WIRE_MD.read_text()
    (tmp_path / "WIRE.md").write_text(md)
    assert wire.drift(tmp_path / "schema", tmp_path / "WIRE.md") == []
    stale = md.replace("| `goal_id` | string or null |", "| `goal_id` | int |", 1)
    assert stale != md
    (tmp_path / "WIRE.md").write_text(stale)
    (tmp_path / "schema" / "gone_kind.json").write_text("{}")
    (tmp_path / "schema" / "status.json").write_text("{}")
    found = wire.drift(tmp_path / "schema", tmp_path / "WIRE.md")
    assert len(found) == 3 and any("gone_kind" in f for f in found) and any("WIRE.md" in f for f in found)


def test_every_message_has_a_schema_file_and_a_documented_field_table() -> None:
    md = wire.WIRE_MD.read_text()
    files = wire.schema_files()
    for cls in ALL_MESSAGES:
        schema = json.loads(files[f"{cls.KIND}.json"])
        assert schema["$id"] == f"argus/{cls.KIND}/{cls.SCHEMA[0]}.{cls.SCHEMA[1]}"
        assert set(schema["properties"]) == set(cls.model_fields)
        assert f"### `{cls.KIND}` ({cls.__name__}" in md
        for name, prop in schema["properties"].items():
            assert prop.get("description"), f"{cls.__name__}.{name} has no description (meaning, units)"


def test_schema_files_ship_as_package_data() -> None:
    import tomllib

    pyproject = tomllib.loads((wire.WIRE_MD.parents[1] / "pyproject.toml").read_text())
    data = pyproject["tool"]["setuptools"]["package-data"]
    assert "schema/*.json" in data.get("protocol", [])
    assert (wire.SCHEMA_DIR / "graph_delta.json").is_file()


def _json_view(msg: Any) -> Any:
    return json.loads(msg.model_dump_json())


@pytest.mark.parametrize("msg", [
    GraphSnapshot(version=3, stamp_ns=5, nodes=[node()], edges=[GraphEdge(subject_id="n1", predicate="next_to",
                                                                          object_id="n1")], frames={"cam0": 4}),
    node(),
    GoalStatus(robot_id="r", stamp_ns=1, goal_id=None, accepted=False, reason="bad", received=3),
    PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.ones((2, 3), np.float32)),
], ids=lambda m: type(m).__name__)
def test_json_dumps_validate_against_the_shipped_schemas(msg: Any) -> None:
    schema = json.loads(wire.schema_files()[f"{type(msg).KIND}.json"])
    jsonschema.validate(_json_view(msg), schema)
    bad = {**_json_view(msg), "stamp_ns": -1}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


def test_plain_goal_schema_accepts_the_documented_goal() -> None:
    schema = json.loads(wire.schema_files()["plain_goal.json"])
    jsonschema.validate({"robot_id": "r", "x": 1.0, "y": 2.0, "yaw_rad": 0.5}, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"robot_id": "r", "x": 1.0}, schema)


# --- arrays ----------------------------------------------------------------------------------------
def test_a_plain_msgpack_reader_gets_arrays_as_dtype_shape_data_maps() -> None:
    pm = PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.arange(6, dtype=np.float32).reshape(2, 3),
                  counts=np.array([3, 4], np.uint16))
    magic, kind, major, minor, body = msgpack.unpackb(encode(pm), raw=False)  # no ext_hook: plain msgpack
    assert (magic, kind) == ("ARG1", "point_map")
    assert body["points"]["dtype"] == "<f4" and body["points"]["shape"] == [2, 3]
    assert np.array_equal(np.frombuffer(body["points"]["data"], "<f4").reshape(2, 3), pm.points)
    assert body["counts"] == {"dtype": "<u2", "shape": [2], "data": np.array([3, 4], "<u2").tobytes()}


def test_big_endian_arrays_go_out_little_endian() -> None:
    pm = PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.arange(6, dtype=">f4").reshape(2, 3))
    body = msgpack.unpackb(encode(pm), raw=False)[4]
    assert body["points"]["dtype"] == "<f4"
    assert np.array_equal(decode(encode(pm), PointMap).points, np.arange(6, dtype=np.float32).reshape(2, 3))


@pytest.mark.parametrize("msg", [
    PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.ones((5, 3), np.float32),
             colors=np.zeros((5, 3), np.uint8)),
    GraphSnapshot(version=1, stamp_ns=1, nodes=[node("a"), node("b", emb=False)]),
], ids=lambda m: type(m).__name__)
def test_legacy_ext_arrays_still_decode(msg: Any) -> None:
    assert decode(legacy_encode(msg), type(msg)) == msg


def test_array_map_form_costs_at_most_16_bytes_per_array_over_the_legacy_form() -> None:
    rng = np.random.default_rng(0)
    n = 100_000
    pm = PointMap(version=1, stamp_ns=1, voxel_m=0.05, points=rng.random((n, 3), dtype=np.float32),
                  counts=rng.integers(0, 100, n).astype(np.uint16),
                  colors=rng.integers(0, 255, (n, 3)).astype(np.uint8))
    assert 0 <= len(encode(pm)) - len(legacy_encode(pm)) <= 3 * 16
    snap = GraphSnapshot(version=1, stamp_ns=1, nodes=[node(f"n{i}") for i in range(100)])
    assert 0 <= len(encode(snap)) - len(legacy_encode(snap)) <= 100 * 16


def _point_map_body(points: Any) -> bytes:
    return msgpack.packb(["ARG1", "point_map", 1, 0, {"version": 1, "stamp_ns": 1, "voxel_m": 0.1, "points": points}],
                         use_bin_type=True)


@pytest.mark.parametrize(("points", "match"), [
    ({"dtype": "<f4", "shape": [10, 3], "data": b"\x00" * 8}, "byte length"),
    ({"dtype": "|O", "shape": [1], "data": b"\x00" * 8}, "dtype"),
    ({"dtype": "<f8", "shape": [2**40, 2**20], "data": b""}, "cap"),
    ({"dtype": "<f4", "shape": [True, 3], "data": b"\x00" * 12}, "shape"),
    ({"dtype": "<f4", "shape": [1] * 9, "data": b"\x00" * 4}, "shape"),
    ({"dtype": "<f4", "shape": [1, 3], "data": "not bytes"}, "byte length"),
    ({"dtype": "<f4", "shape": "3", "data": b"\x00" * 12}, "shape"),
])
def test_hostile_array_maps_are_refused(points: Any, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        decode(_point_map_body(points), PointMap)


def test_array_cap_applies_to_the_map_form(monkeypatch: pytest.MonkeyPatch) -> None:
    data = encode(PointMap(version=1, stamp_ns=1, voxel_m=0.1, points=np.zeros((100, 3), np.float32)))
    monkeypatch.setattr(arrays, "MAX_ARRAY_ELEMENTS", 299)
    with pytest.raises(DecodeError, match="cap"):
        decode(data)


def test_a_dict_field_that_looks_like_an_array_is_not_one() -> None:
    s = Status(role="r", node_id="n", stamp_ns=1, counters={"dtype": 1.0, "shape": 2.0, "data": 3.0})
    assert decode(encode(s), Status).counters == {"dtype": 1.0, "shape": 2.0, "data": 3.0}


# --- encodings and keys ----------------------------------------------------------------------------
def test_encodings_name_the_schema() -> None:
    from protocol.transport import message_encoding

    assert content_type(RobotState) == "application/msgpack;argus/robot_state/1.1"
    assert str(message_encoding(GoalStatus, "application/json")) == "application/json;argus/goal_status/1.0"
    assert str(message_encoding()) == "application/msgpack"


def test_json_view_keys() -> None:
    k = Keys("s")
    assert k.graph_json(k.graph_snapshot) == "argus/s/graph/json/snapshot"
    assert k.from_graph_json("argus/s/graph/json/node/n1") == k.graph_node("n1")
    assert k.from_graph_json(k.graph_json_all) == k.graph_all
    for bad in ("argus/s/graph/json/", "argus/s/graph/snapshot", "argus/t/graph/json/snapshot"):
        with pytest.raises(ValueError):
            k.from_graph_json(bad)
    with pytest.raises(ValueError):
        k.graph_json("argus/s/graph/json/snapshot")
    assert k.robot_goal_status("r1") == "argus/s/robot/r1/goal/status"
    assert k.robot_goal_status_json("r1") == "argus/s/robot/r1/goal/status/json"


# --- the mapper's JSON view (fake core and queries, no Zenoh session) --------------------------------
class FakeCore:
    def __init__(self) -> None:
        self.snap = GraphSnapshot(version=7, stamp_ns=9, nodes=[node("n1", "chair"), node("n2", "table")],
                                  edges=[GraphEdge(subject_id="n1", predicate="next_to", object_id="n2")])
        self.version = 7

    @property
    def epoch(self) -> str:
        return self.snap.epoch

    def restart_at(self, epoch: str, version: int, next_id: int) -> None:  # what MapperNode's keeper calls
        self.snap = self.snap.model_copy(update={"epoch": epoch})

    def snapshot(self) -> GraphSnapshot:
        return self.snap

    def snapshot_key(self) -> tuple[str, int, int | None]:
        return self.snap.epoch, self.snap.version, None

    def keyed_snapshot(self) -> tuple[GraphSnapshot, tuple[str, int, int | None]]:
        return self.snap, self.snapshot_key()

    def nodes(self) -> list[GraphNode]:
        return list(self.snap.nodes)

    def query(self, q: Any) -> list[GraphNode]:
        members = None if q.room is None else set(self.rooms.members(q.room))
        return [n for n in self.snap.nodes if q.matches(n) and (members is None or n.node_id in members)]

    def select_graph(self, q: Any) -> GraphSnapshot:
        nodes = self.query(q)
        ids = {n.node_id for n in nodes}
        return self.snap.model_copy(update={"nodes": nodes, "edges": [
            e for e in self.snap.edges if e.subject_id in ids and e.object_id in ids]})

    rooms = RoomLayer(version=7, stamp_ns=9, rooms=[RoomNode(
        room_id="room1", label="kitchen", label_confidence=0.8, polygon=[(0.0, 0.0), (4.0, 0.0), (4.0, 3.0)],
        floor_z_m=0.0, area_m2=12.0, observed_fraction=0.9, centroid=(2.0, 1.5))],
        edges=[RoomEdge(subject_id="n1", predicate="in_room", object_id="room1")])

    def room_layer(self) -> RoomLayer:
        return self.rooms


class FakeQuery:
    def __init__(self, key: str, parameters: str = "") -> None:
        self.key_expr, self.parameters = key, parameters
        self.replies: list[tuple[str, Any, str]] = []
        self.errors: list[str] = []

    def reply(self, key: str, payload: Any, encoding: Any = None) -> None:
        self.replies.append((key, payload, str(encoding)))

    def reply_err(self, payload: str, encoding: Any = None) -> None:
        self.errors.append(payload)


@pytest.fixture
def mapper_node():
    from mapper.config import MapperConfig
    from mapper.node import MapperNode

    return MapperNode(MapperConfig(site="s"), core=FakeCore())  # type: ignore[arg-type]


def test_json_view_answers_like_the_msgpack_keys(mapper_node) -> None:  # noqa: ANN001
    k = mapper_node.keys
    q = FakeQuery(k.graph_json(k.graph_snapshot))
    mapper_node.queries.on_json_query(q)
    ((key, payload, enc),) = q.replies
    major, minor = GraphSnapshot.SCHEMA
    assert key == "argus/s/graph/json/snapshot" and enc == f"application/json;argus/graph_snapshot/{major}.{minor}"
    snap = json.loads(payload)
    assert snap["version"] == 7 and [n["node_id"] for n in snap["nodes"]] == ["n1", "n2"]
    assert snap["nodes"][0]["embedding"] == [0.0, 0.25, 0.5, 0.75]  # arrays are lists in JSON
    assert snap == json.loads(mapper_node.core.snap.model_dump_json())
    assert GraphSnapshot.model_validate_json(payload).nodes[1].label == "table"  # JSON validates back too

    q = FakeQuery(k.graph_json(k.graph_nodes), "label=chair")
    mapper_node.queries.on_json_query(q)
    assert [n["node_id"] for n in json.loads(q.replies[0][1])["nodes"]] == ["n1"]

    q = FakeQuery(k.graph_json(k.graph_node("n2")))
    mapper_node.queries.on_json_query(q)
    assert json.loads(q.replies[0][1])["label"] == "table" and q.replies[0][2].startswith("application/json;")

    q = FakeQuery(k.graph_json_all)
    mapper_node.queries.on_json_query(q)
    assert sorted(r[0] for r in q.replies) == ["argus/s/graph/json/node/n1", "argus/s/graph/json/node/n2",
                                               "argus/s/graph/json/rooms", "argus/s/graph/json/snapshot"]


def test_rooms_are_answered_in_both_views_and_select_nodes(mapper_node) -> None:  # noqa: ANN001
    k = mapper_node.keys
    q = FakeQuery(k.graph_rooms)
    mapper_node.queries.on_query(q)
    ((key, payload, enc),) = q.replies
    assert key == "argus/s/graph/rooms" and enc == "application/msgpack;argus/room_layer/1.0"
    layer = decode(payload, RoomLayer)
    assert layer.rooms[0].label == "kitchen" and layer.members("room1") == ["n1"] and layer.room_of("n2") is None
    q = FakeQuery(k.graph_json(k.graph_rooms))
    mapper_node.queries.on_json_query(q)
    assert json.loads(q.replies[0][1])["rooms"][0]["polygon"][1] == [4.0, 0.0]
    q = FakeQuery(k.graph_json(k.graph_nodes), "room=room1")
    mapper_node.queries.on_json_query(q)
    assert [n["node_id"] for n in json.loads(q.replies[0][1])["nodes"]] == ["n1"]
    assert GraphQuery.from_parameters("room=room1;label=cup") == GraphQuery(room="room1", label="cup")
    assert GraphQuery(room="room2").to_parameters() == "room=room2"


def test_json_view_refuses_bad_selectors_and_never_answers_msgpack_wildcards(mapper_node) -> None:  # noqa: ANN001
    k = mapper_node.keys
    q = FakeQuery(k.graph_json(k.graph_nodes), "colour=red")
    mapper_node.queries.on_json_query(q)
    assert q.replies == [] and "colour" in q.errors[0]
    q = FakeQuery(k.graph_all)  # graph/** reaches both queryables; only the msgpack one answers it
    mapper_node.queries.on_json_query(q)
    assert q.replies == [] and q.errors == []
    mapper_node.queries.on_query(q)
    assert {r[2] for r in q.replies} == {"application/msgpack;argus/graph_snapshot/1.4",
                                        "application/msgpack;argus/graph_node/1.0",
                                        "application/msgpack;argus/room_layer/1.0"}
    assert decode(q.replies[0][1], GraphSnapshot).version == 7


def test_a_missing_node_is_a_not_found_error_reply_and_a_bad_value_a_bad_query_one(mapper_node) -> None:  # noqa: ANN001
    """docs/WIRE.md, "Error replies": one line ``<code>: <detail>``; a node selection that selects nothing is an
    empty snapshot, not an error."""
    k = mapper_node.keys
    for key in (k.graph_node("n999999"), k.graph_json(k.graph_node("n999999"))):
        q = FakeQuery(key)
        (mapper_node.queries.on_json_query if "/json/" in key else mapper_node.queries.on_query)(q)
        assert q.replies == [] and len(q.errors) == 1, key
        assert q.errors[0].startswith("not_found: node n999999 is not in the graph (version 7"), q.errors
    q = FakeQuery(k.graph_nodes, "near=1,2,0;radius=-1")
    mapper_node.queries.on_query(q)
    assert q.replies == [] and q.errors == ["bad_query: radius: Input should be greater than 0"]
    q = FakeQuery(k.graph_nodes, "id=n999999")
    mapper_node.queries.on_query(q)
    assert q.errors == [] and decode(q.replies[0][1], GraphSnapshot).nodes == []


# --- goal payloads ---------------------------------------------------------------------------------
def test_parse_goal_envelope_json_and_msgpack() -> None:
    env = NbvGoal(goal_id="g1", robot_id="r", stamp_ns=5, x=1.0, y=2.0, yaw_rad=0.5)
    assert parse_goal(encode(env), "dflt", 9) == (env, "envelope")
    goal, form = parse_goal(b' {"robot_id": "r", "x": 1, "y": 2, "yaw": 0.5}', "r-goal-3", 9)
    assert form == "json" and (goal.goal_id, goal.x, goal.y, goal.yaw_rad, goal.stamp_ns) == ("r-goal-3", 1, 2, 0.5, 9)
    goal, form = parse_goal(msgpack.packb({"robot_id": "r", "x": 1.5, "y": 2, "yaw_rad": 1, "goal_id": "mine"}),
                            "d", 9)
    assert form == "msgpack" and goal.goal_id == "mine" and goal.yaw_rad == 1.0
    goal, _ = parse_goal(b'{"robot_id": "r", "x": 0, "y": 0}', "d", 9)
    assert goal.yaw_rad == 0.0


@pytest.mark.parametrize(("payload", "match", "goal_id"), [
    (b'{"robot_id": "r", "x": 1, "goal_id": "g7"}', "y: Field required", "g7"),
    (b'{"robot_id": "r", "x": 1, "y": 2, "yaw_deg": 90}', "yaw_deg: Extra inputs are not permitted", None),
    (b'{"robot_id": "r", "x": "far", "y": 2}', "x: Input should be a valid number", None),
    (b'{"robot_id": "r", "x": 1,', "not a JSON object", None),
    (b"[1, 2]", "must be an object", None),
    (b"junk", "neither JSON nor msgpack", None),
    (b"", "neither JSON nor msgpack", None),
    (b"{" + b" " * 70_000 + b"}", "exceeds", None),
    (msgpack.packb(["ARG1", "nbv_goal", 1, 0, {"goal_id": "g8", "robot_id": "r"}]), "nbv_goal failed validation", "g8"),
    (encode(Status(role="x", node_id="y", stamp_ns=0)), "expected 'nbv_goal'", None),
    (msgpack.packb(["ARG1", "nbv_goal", 2, 0, {}]), "major 2", None),
])
def test_parse_goal_refuses_with_a_reason(payload: bytes, match: str, goal_id: str | None) -> None:
    with pytest.raises(GoalRefused, match=match) as e:
        parse_goal(payload, "d", 1)
    assert e.value.goal_id == goal_id


def test_plain_goal_model_documents_yaw_alias() -> None:
    assert PlainGoal.model_validate({"robot_id": "r", "x": 0, "y": 0, "yaw": 1}).yaw_rad == 1.0


def test_refusal_limiter_bounds_bursts_and_refills() -> None:
    lim = RefusalLimiter(rate_per_s=10.0, burst=5)
    assert [lim.allow(0.0) for _ in range(7)] == [True] * 5 + [False] * 2
    assert lim.take_suppressed() == 2 and lim.take_suppressed() == 0
    assert lim.allow(0.05) is False  # half a token
    assert lim.allow(0.11) is True
    assert sum(lim.allow(100.0) for _ in range(50)) == 5  # a long pause refills only up to the burst
    assert lim.suppressed_total == 3 + 45
    with pytest.raises(ValueError):
        RefusalLimiter(rate_per_s=0)


# --- goal answers from the robot agent (fake publishers) -------------------------------------------
class CapturePub:
    def __init__(self) -> None:
        self.puts: list[Any] = []

    def put(self, payload: Any, attachment: Any = None) -> None:
        self.puts.append(payload)


def robot_with_fakes():  # noqa: ANN201
    from tests.support.robot import agent_with_fakes

    agent = agent_with_fakes()
    agent._ack_pubs = [(CapturePub(), False), (CapturePub(), True)]
    return agent


def answers(agent: Any) -> list[GoalStatus]:
    (msgpack_pub, _), (json_pub, _) = agent._ack_pubs
    out = [decode(p, GoalStatus) for p in msgpack_pub.puts]
    assert [GoalStatus.model_validate_json(p) for p in json_pub.puts] == out  # the JSON twin says the same
    return out


def test_every_goal_payload_gets_an_answer() -> None:
    agent = robot_with_fakes()
    agent.on_goal_bytes(b"junk")
    agent.on_goal_bytes(b'{"robot_id": "r", "x": 1, "goal_id": "no-y"}')
    agent.tick(0.0)
    agent.on_goal_bytes(encode(NbvGoal(goal_id="other", robot_id="someone", stamp_ns=1, x=1, y=1, yaw_rad=0)))
    agent.tick(0.0)
    agent.on_goal_bytes(b'{"robot_id": "r", "x": 1.5, "y": 1.0, "yaw": 0.0, "goal_id": "first"}')
    agent.on_goal_bytes(b'{"robot_id": "r", "x": 2.0, "y": 1.0, "yaw": 0.0}')  # supersedes "first"
    agent.tick(0.0)
    got = answers(agent)
    assert [(a.goal_id, a.accepted, a.received) for a in got] == [
        (None, False, 1), ("no-y", False, 2), ("other", False, 3), ("first", False, 4), ("r-goal-5", True, 5)]
    assert "neither JSON nor msgpack" in got[0].reason and "y: Field required" in got[1].reason
    assert "addressed to robot 'someone'" in got[2].reason and "superseded by goal 'r-goal-5'" in got[3].reason
    assert got[4].reason == "" and agent.status == "moving"
    assert all(a.robot_id == "r" and a.stamp_ns > 0 for a in got)
    assert agent.counters.get("goals_garbage") == 2 and agent.counters.get("goals_json") == 2


def test_resent_goal_is_acknowledged_again_without_restarting() -> None:
    agent = robot_with_fakes()
    g = encode(NbvGoal(goal_id="same", robot_id="r", stamp_ns=1, x=2.0, y=1.0, yaw_rad=0.0))
    agent.on_goal_bytes(g)
    agent.tick(0.1)
    agent.on_goal_bytes(g)
    agent.tick(0.1)
    assert [(a.goal_id, a.accepted) for a in answers(agent)] == [("same", True), ("same", True)]
    assert agent.counters.get("goals_duplicate") == 1


def test_refusal_flood_is_rate_limited_and_counted() -> None:
    agent = robot_with_fakes()
    for _ in range(1000):
        agent.on_goal_bytes(b"\xc1garbage")
    agent.tick(0.0)
    got = answers(agent)
    assert 20 <= len(got) <= 25 and all(not a.accepted for a in got)  # the burst (plus a few refilled tokens)
    # Each published answer says how many refusals went unpublished before it: nothing is lost silently.
    assert sum(a.suppressed for a in got) + len(got) == 1000 == agent.limiter.suppressed_total + len(got)
    time.sleep(0.15)
    agent.on_goal_bytes(b"junk")
    agent.tick(0.0)
    assert answers(agent)[-1].received == 1001 and answers(agent)[-1].suppressed == 0
    # A valid goal is still accepted while refusals are being throttled.
    agent.on_goal_bytes(b'{"robot_id": "r", "x": 2, "y": 1, "goal_id": "ok"}')
    agent.tick(0.0)
    assert answers(agent)[-1].goal_id == "ok" and answers(agent)[-1].accepted


# --- argus goal against a real robot agent (kinematic body: fast) --------------------------------------
def test_argus_goal_prints_the_robots_answer(router: str, procs: list[Proc]) -> None:
    robot = Proc(["robot-agent", "--connect", router, "--body", "kinematic", "--id", "rg", "--site", "wiretest",
                  "--set", "frames.on_start=false"])
    procs.append(robot)
    base = ["goal", "--connect", router, "--site", "wiretest", "--robot", "rg", "--timeout", "10"]
    wait_for(lambda: "goals on" in robot.output or not robot.alive(), 30, what=f"robot up\n{robot.output}")
    from protocol.session import client, open_session

    keys = Keys("wiretest")
    encodings: dict[str, set[str]] = {}

    def on_sample(sample: Any) -> None:
        encodings.setdefault(str(sample.key_expr), set()).add(str(sample.encoding))

    session = open_session(client(router))
    subs = [session.declare_subscriber(k, on_sample) for k in (
        keys.robot_goal_status("rg"), keys.robot_goal_status_json("rg"), keys.robot_state("rg"), keys.all_status)]
    ok = Proc([*base, "--x", "1.0", "--y", "0.5", "--yaw-deg", "90", "--goal-id", "cli-ok"])
    assert ok.wait(30) == 0, ok.output + robot.output
    ok.stop()
    assert "robot rg accepted goal cli-ok" in ok.output
    far = Proc([*base, "--x", "1e6", "--y", "0", "--json", "--goal-id", "cli-far"])
    assert far.wait(30) == 1, far.output
    far.stop()
    status = GoalStatus.model_validate_json(far.lines[-1])
    assert status.goal_id == "cli-far" and not status.accepted and "far away" in status.reason
    nobody = Proc([*base[:-1], "1", "--robot", "nobody", "--x", "0", "--y", "0"])
    assert nobody.wait(30) == 4
    nobody.stop()
    assert "no answer from robot 'nobody'" in nobody.output
    # Every sample names its schema in its Zenoh encoding; the viewpoint query reply too.
    (vp,) = [r.ok for r in session.get(keys.robot_viewpoints("rg"), timeout=5.0) if r.ok is not None]
    wait_for(lambda: keys.status("robot-agent", "rg") in encodings, 10, what="a Status sample")
    for sub in subs:
        sub.undeclare()
    session.close()
    assert str(vp.encoding) == "application/msgpack;argus/viewpoint_set/1.0"
    assert encodings[keys.robot_goal_status("rg")] == {"application/msgpack;argus/goal_status/1.0"}
    assert encodings[keys.robot_goal_status_json("rg")] == {"application/json;argus/goal_status/1.0"}
    assert encodings[keys.robot_state("rg")] == {"application/msgpack;argus/robot_state/1.1"}
    assert encodings[keys.status("robot-agent", "rg")] == {"application/msgpack;argus/status/1.0"}


# --- prose of WIRE.md that code must keep true ------------------------------------------------------
def test_status_periods_and_counters_in_wire_md_are_the_codes() -> None:
    """WIRE.md, "Status": the periods are the configs' defaults, and every counter it names is one a process
    of that role publishes (its name is a string in that role's package)."""
    from edge_camera.config import EdgeCameraConfig
    from mapper.config import MapperConfig
    from mapper.work.config import WorkerConfig
    from planner.config import PlannerNodeConfig
    from robot_agent.config import RobotAgentConfig

    text = wire.WIRE_MD.read_text(encoding="utf-8")
    assert "**1 s** for `mapper`, `planner` and `worker`, **2 s** for `edge-camera` and\n`robot-agent`" in text
    def period(cfg: Any) -> float:
        return float(cfg.model_fields["status_period_s"].default)

    assert period(MapperConfig) == period(PlannerNodeConfig) == period(WorkerConfig) == 1
    assert period(EdgeCameraConfig) == period(RobotAgentConfig) == 2
    section = text[text.index("### Status"):text.index("### What receivers accept")]
    packages = {"edge-camera": ["edge_camera"], "robot-agent": ["robot_agent"], "mapper": ["mapper", "protocol"],
                "planner": ["planner"], "worker": ["mapper/work"]}
    root = wire.WIRE_MD.parents[1]
    for role, dirs in packages.items():
        (row,) = [line for line in section.splitlines() if line.startswith(f"| `{role}` |")]
        source = "".join(p.read_text(encoding="utf-8") for d in dirs for p in (root / d).rglob("*.py"))
        for name in re.findall(r"`([a-z_0-9]+)`", row.split("|")[2]):
            assert f'"{name}"' in source or f"'{name}'" in source or f"{name}=" in source, (role, name)
