"""``argus query`` against a graph holder on loopback: nodes, snapshot and watch return what it holds."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from deploy.query import QueryError, format_delta, format_nodes, format_retired, get_nodes, get_selection, get_snapshot
from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphEdge, GraphNode, GraphSnapshot, OrientedBox, RetiredNode
from protocol.query import GraphQuery
from protocol.rooms import RoomLayer
from protocol.session import ZenohSettings, open_session
from tests.support.procs import Proc, wait_for

SITE = "qtest"


def _node(node_id: str, label: str, xyz: tuple[float, float, float]) -> GraphNode:
    return GraphNode(
        node_id=node_id, label=label, label_confidence=0.8, centroid=xyz,
        box=OrientedBox(center=xyz, extent=(0.5, 0.5, 0.9)), point_count=100, observation_count=3,
        sources=["cam_a"], first_seen_ns=1, last_seen_ns=2,
    )


SNAP = GraphSnapshot(
    version=7, stamp_ns=123,
    nodes=[_node("n1", "chair", (1.0, 2.0, 0.4)), _node("n2", "office chair", (5.0, 5.0, 0.4)),
           _node("n3", "table", (1.5, 2.0, 0.4))],
    edges=[GraphEdge(subject_id="n1", predicate="next_to", object_id="n3")],
)


# Seen gone: answered only to include_retired queries (newest first, as the mapper keeps them).
RETIRED = [RetiredNode(node=_node("n4", "box", (3.0, 1.0, 0.2)), retired_ns=2_000_000_000_000_000_000, version=6),
           RetiredNode(node=_node("n0", "chair", (0.5, 0.5, 0.4)), retired_ns=1_000_000_000_000_000_000, version=5)]


class FakeGraphHolder:
    """Answers graph queries the way the mapper's queryable does (selection by GraphQuery)."""

    def __init__(self, endpoint: str) -> None:
        self.keys = Keys(SITE)
        self.session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        self.queries = 0
        self.qbl = self.session.declare_queryable(self.keys.graph_all, self._on_query)
        self.delta_pub = self.session.declare_publisher(self.keys.graph_delta)

    def _on_query(self, query: Any) -> None:
        self.queries += 1
        key = str(query.key_expr)
        if key == self.keys.graph_snapshot:
            query.reply(self.keys.graph_snapshot, encode(SNAP))
        elif key == self.keys.graph_nodes:
            sel = GraphQuery.from_parameters(str(query.parameters))
            picked = [n for n in SNAP.nodes if sel.matches(n)]
            gone = [r for r in RETIRED if sel.matches(r.node)] if sel.include_retired else []
            query.reply(self.keys.graph_nodes,
                        encode(SNAP.model_copy(update={"nodes": picked, "edges": [], "retired": gone})))

    def close(self) -> None:
        self.qbl.undeclare()
        self.session.close()


@pytest.fixture
def holder(router: str):
    h = FakeGraphHolder(router)
    yield h
    h.close()


def test_get_nodes_selects_like_the_holder(router: str, holder: FakeGraphHolder) -> None:
    with open_session(ZenohSettings(mode="client", connect=[router])) as s:
        keys = Keys(SITE)
        wait_for(lambda: _answers(s, keys), timeout=10, what="queryable reachable")
        chairs = get_nodes(s, keys, GraphQuery(label="chair", near=(1, 2, 0), radius=2))
        assert [n.node_id for n in chairs] == ["n1"]
        assert {n.node_id for n in get_nodes(s, keys, GraphQuery(label="CHAIR"))} == {"n1", "n2"}
        snap = get_snapshot(s, keys)
        assert snap == SNAP
        # retired nodes only when asked for, selected like the live ones
        assert get_selection(s, keys, GraphQuery(label="chair"))[1] == []
        nodes, gone = get_selection(s, keys, GraphQuery(label="chair", include_retired=True))
        assert [n.node_id for n in nodes] == ["n1", "n2"] and [r.node.node_id for r in gone] == ["n0"]
        assert [r.node.node_id for r in get_selection(s, keys, GraphQuery(include_retired=True))[1]] == ["n4", "n0"]


def _answers(session: Any, keys: Keys) -> bool:
    try:
        get_snapshot(session, keys, timeout_s=1.0)
        return True
    except QueryError:  # no (decodable) answer yet; anything else is a bug and fails the test
        return False


def test_snapshot_survives_a_peer_answering_garbage_later(router: str, holder: FakeGraphHolder) -> None:
    """A second replier that answers after the mapper with junk must not hide the mapper's snapshot."""
    keys = Keys(SITE)
    with open_session(ZenohSettings(mode="client", connect=[router])) as rogue_session:

        def garbage(query: Any) -> None:
            time.sleep(0.2)  # answer last: default (latest) consolidation would keep only this reply
            query.reply(str(query.key_expr), b"\x93not a snapshot")

        rogue = rogue_session.declare_queryable(keys.graph_all, garbage)
        with open_session(ZenohSettings(mode="client", connect=[router])) as s:
            wait_for(lambda: _answers(s, keys), timeout=10, what="queryable reachable")
            for _ in range(3):
                assert get_snapshot(s, keys, timeout_s=3.0) == SNAP
                assert [n.node_id for n in get_nodes(s, keys, GraphQuery(label="table"), timeout_s=3.0)] == ["n3"]
        rogue.undeclare()


def test_cli_nodes_snapshot_and_watch(router: str, holder: FakeGraphHolder, procs: list[Proc]) -> None:
    base = ["query", "--connect", router, "--site", SITE]
    p = Proc([*base, "nodes", "--label", "chair", "--near", "1,2,0", "--radius", "2", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    got = json.loads(p.output[p.output.index("["):])
    assert [n["node_id"] for n in got] == ["n1"] and got[0]["label"] == "chair"

    p = Proc([*base, "snapshot", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    snap = GraphSnapshot.model_validate_json(p.output[p.output.index("{"):])
    assert snap == SNAP

    p = Proc([*base, "snapshot"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    assert "version 7: 3 nodes, 1 edges" in p.output and "chair (n1) next_to table (n3)" in p.output

    w = Proc([*base, "watch", "--count", "2"])
    procs.append(w)
    wait_for(lambda: "watching" in w.output, timeout=20, what="watch started")
    # The subscriber may take a moment to be routed: keep publishing until two deltas are printed.
    version = 8
    stop = threading.Event()

    def publish() -> None:
        nonlocal version
        while not stop.is_set():
            holder.delta_pub.put(encode(GraphDelta(version=version, stamp_ns=1, upserted=[_node("n9", "lamp",
                                                                                                 (0, 0, 1))])))
            version += 1
            time.sleep(0.1)

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        assert w.wait(30) == 0, w.output
    finally:
        stop.set()
        t.join()
    assert w.output.count("1 upserted") == 2 and "lamp(n9)" in w.output


def test_cli_takes_endpoint_and_site_from_the_environment(router: str, holder: FakeGraphHolder,
                                                         procs: list[Proc]) -> None:
    p = Proc(["query", "snapshot"], env={"ARGUS_CONNECT": router, "ARGUS_SITE": SITE})
    procs.append(p)
    assert p.wait(30) == 0, p.output
    assert "version 7: 3 nodes" in p.output
    p = Proc(["query", "--site", "elsewhere", "--timeout", "1", "snapshot"], env={"ARGUS_CONNECT": router,
                                                                                 "ARGUS_SITE": SITE})
    procs.append(p)
    assert p.wait(30) == 4, p.output  # the flag wins over the environment: no graph on that site


def test_env_defaults_for_every_process_config(monkeypatch: pytest.MonkeyPatch) -> None:
    from mapper.config import MapperConfig
    from planner.config import PlannerNodeConfig
    from protocol.session import ZenohSettings, default_endpoints
    from protocol.tomlconfig import AgentConfig

    assert default_endpoints() == ["tcp/127.0.0.1:7447"] and MapperConfig().site == "default"
    monkeypatch.setenv("ARGUS_CONNECT", "tcp/127.0.0.1:7501, tcp/127.0.0.1:7502")
    monkeypatch.setenv("ARGUS_SITE", "lab")
    assert ZenohSettings().connect == ["tcp/127.0.0.1:7501", "tcp/127.0.0.1:7502"]
    for cfg in (MapperConfig(), PlannerNodeConfig(), AgentConfig()):  # AgentConfig: camera and robot
        assert cfg.site == "lab" and cfg.zenoh.connect == ["tcp/127.0.0.1:7501", "tcp/127.0.0.1:7502"]
    assert MapperConfig(site="other").site == "other"  # a config value wins over the environment
    monkeypatch.setenv("ARGUS_SITE", "bad/site")
    for make in (AgentConfig, MapperConfig, PlannerNodeConfig):
        with pytest.raises(ValueError):
            make()  # validated like a site given any other way


def test_watch_exits_cleanly_on_ctrl_c(router: str, procs: list[Proc]) -> None:
    import signal

    w = Proc(["query", "--connect", router, "--site", SITE, "watch"])
    procs.append(w)
    wait_for(lambda: "watching" in w.output, timeout=20, what="watch started")
    w.signal(signal.SIGINT)
    assert w.wait(10) == 0, w.output
    assert "Traceback" not in w.output


def test_cli_without_mapper_fails_cleanly(router: str, procs: list[Proc]) -> None:
    p = Proc(["query", "--connect", router, "--site", "nobody", "--timeout", "1", "snapshot"])
    procs.append(p)
    assert p.wait(30) == 4  # no answer: the same status as no router (protocol/exits.py)
    assert "is a mapper running?" in p.output and "Traceback" not in p.output


def test_cli_missing_node_is_not_found_with_its_own_status(router: str, holder: FakeGraphHolder,
                                                           procs: list[Proc]) -> None:
    p = Proc(["query", "--connect", router, "--site", SITE, "nodes", "--id", "n999999"])
    procs.append(p)
    assert p.wait(30) == 3, p.output
    assert "node 'n999999' is not in the graph" in p.output and "0 node(s)" not in p.output
    p = Proc(["query", "--connect", router, "--site", SITE, "nodes", "--id", "n1"])
    procs.append(p)
    assert p.wait(30) == 0 and "1 node(s)" in p.output, p.output
    # a retired node is found when retired nodes are asked for, and listed as retired
    p = Proc(["query", "--connect", router, "--site", SITE, "nodes", "--id", "n4", "--include-retired", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    got = json.loads(p.output[p.output.index("{"):])
    assert got["nodes"] == [] and [r["node"]["node_id"] for r in got["retired"]] == ["n4"]
    assert "embedding" not in got["retired"][0]["node"]


@pytest.mark.integration
def test_unreachable_router_is_status_4_for_query_and_goal(capsys: pytest.CaptureFixture[str]) -> None:
    from deploy.goal import main as goal_main
    from deploy.query import main as query_main
    from tests.support.procs import endpoint, free_port

    nobody = endpoint(free_port())
    assert query_main(["--connect", nobody, "--timeout", "1", "snapshot"]) == 4
    assert goal_main(["--connect", nobody, "--robot", "r", "--x", "1", "--y", "2", "--timeout", "1"]) == 4
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all("cannot open a Zenoh session" in line for line in err), err


@pytest.mark.parametrize(("argv", "line"), [
    (["--connect", "foo", "snapshot"], "argus query: connect: 'foo' is not a Zenoh endpoint"),
    (["nodes", "--radius", "-1", "--near", "1,2,0"], "argus query: radius: Input should be greater than 0"),
    (["nodes", "--near", "1,2"], "argus query: --near: '1,2' is not x,y,z in metres"),
    (["nodes", "--near", "1,x,2"], "argus query: --near: '1,x,2' is not x,y,z in metres"),
])
def test_cli_bad_arguments_are_one_line_and_status_2(argv: list[str], line: str,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    from deploy.query import main

    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [err.strip()] and err.startswith(line), err
    assert "pydantic" not in err and "Json5Err" not in err and "http" not in err


def test_goal_bad_endpoint_is_one_line_and_status_2(capsys: pytest.CaptureFixture[str]) -> None:
    from deploy.goal import main

    assert main(["--connect", "foo", "--robot", "r", "--x", "1", "--y", "2"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("argus goal: connect: 'foo' is not a Zenoh endpoint (<protocol>/<address>, "
                           "e.g. tcp/127.0.0.1:7447)")


def test_formatting() -> None:
    table = format_nodes(SNAP.nodes, near=(1.0, 2.0, 0.4))
    assert "3 node(s)" in table and "office chair" in table and "0.00" in table
    line = format_delta(GraphDelta(version=3, stamp_ns=0, upserted=SNAP.nodes, removed=["x"]))
    assert line.startswith("v3: 3 upserted, 1 removed")
    table = format_retired(RETIRED)
    assert table.splitlines()[1].startswith("n4") and "2033-05-18 03:33:20" in table and "2 retired node(s)" in table


def test_cli_returns_what_a_real_mapper_holds(router: str, procs: list[Proc], tmp_path: Path) -> None:
    """A graph built in-process is persisted, a real ``argus mapper`` resumes it, ``argus query`` reads it."""
    from bench.eval import FramesConfig, _mapper_views, scan_walk
    from mapper.core import MapperCore
    from mapper.persistence import save_state
    from protocol.messages import Intrinsics
    from sim.scene import generate_scene

    scene = generate_scene("furnished_room", 0)
    frames = FramesConfig(n_frames=3, width=160, height=120)
    poses, _ = scan_walk(scene, frames, 0)
    views = _mapper_views(scene, poses, poses, Intrinsics.from_fov(160, 120, 90.0), "robot0", trusted=True)
    core = MapperCore(core_config_oracle())
    for v in views:
        core.ingest(v, force_keyframe=True)
    held = core.snapshot()
    assert held.nodes, "the in-process mapper found nothing to serve"
    save_state(tmp_path / "state", core.state())

    site = "qreal"
    mapper = Proc(["mapper", "--connect", router, "--site", site, "--state-dir", str(tmp_path / "state")])
    procs.append(mapper)
    base = ["query", "--connect", router, "--site", site, "--timeout", "2"]

    def snapshot_served() -> bool:
        p = Proc([*base, "snapshot", "--json"])
        procs.append(p)
        return p.wait(30) == 0

    wait_for(snapshot_served, timeout=90, interval=0.5, what="mapper serving its resumed graph")
    p = Proc([*base, "snapshot", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    got = GraphSnapshot.model_validate_json(p.output[p.output.index("{"):])
    assert got.version == held.version
    assert [(n.node_id, n.label) for n in got.nodes] == [(n.node_id, n.label) for n in held.nodes]
    assert {(e.subject_id, e.predicate, e.object_id) for e in got.edges} == {
        (e.subject_id, e.predicate, e.object_id) for e in held.edges}

    target = held.nodes[0]
    p = Proc([*base, "nodes", "--label", target.label, "--near", ",".join(f"{v:.3f}" for v in target.centroid),
              "--radius", "0.5", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    ids = [n["node_id"] for n in json.loads(p.output[p.output.index("["):])]
    assert target.node_id in ids
    expected = {n.node_id for n in held.nodes
                if target.label.lower() in n.label.lower()
                and sum((a - b) ** 2 for a, b in zip(n.centroid, target.centroid, strict=True)) <= 0.25}
    assert set(ids) == expected

    # The room layer: what the in-process core built from the same map, served by the resumed mapper.
    held_rooms = core.room_layer()
    assert held_rooms is not None and held_rooms.rooms, "no room in a furnished room"
    p = Proc([*base, "rooms", "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    got_rooms = RoomLayer.model_validate_json(p.output[p.output.index("{"):])
    assert [r.room_id for r in got_rooms.rooms] == [r.room_id for r in held_rooms.rooms]
    room = got_rooms.rooms[0].room_id
    p = Proc([*base, "nodes", "--room", room, "--json"])
    procs.append(p)
    assert p.wait(30) == 0, p.output
    assert {n["node_id"] for n in json.loads(p.output[p.output.index("["):])} == set(got_rooms.members(room))
    p = Proc([*base, "rooms"])
    procs.append(p)
    assert p.wait(30) == 0 and f"{len(got_rooms.rooms)} room(s) at graph version" in p.output, p.output


def core_config_oracle() -> Any:
    from bench.explore import core_config

    return core_config("oracle", "sim", 1)


def test_watch_into_a_reader_that_closes_early_exits_quietly(router: str) -> None:
    """``argus query watch | head -n 1``: once the reader is gone, exit 0 with no BrokenPipeError."""
    import os
    import subprocess
    import sys

    from tests.support.procs import REPO

    p = subprocess.Popen([sys.executable, "-m", "deploy.cli", "query", "--connect", router, "--site", SITE, "watch"],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
    stop = threading.Event()

    def publish() -> None:
        with open_session(ZenohSettings(mode="client", connect=[router])) as s:
            pub = s.declare_publisher(Keys(SITE).graph_delta)
            version = 1
            while not stop.is_set():
                pub.put(encode(GraphDelta(version=version, stamp_ns=1)))
                version += 1
                time.sleep(0.05)

    t = threading.Thread(target=publish, daemon=True)
    t.start()
    try:
        assert p.stdout is not None and p.stderr is not None
        first = p.stdout.readline()  # head -n 1
        p.stdout.close()
        assert "upserted" in first
        code = p.wait(30)
        err = p.stderr.read()
    finally:
        stop.set()
        t.join()
        if p.poll() is None:
            p.kill()
            p.wait()
    assert "BrokenPipe" not in err and "Traceback" not in err, err
    assert code == 0, err


def test_the_printed_query_line_runs_without_the_venv_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 38: ``argus up`` printed ``argus query ...``, which failed after ``make install`` without
    ``source .venv/bin/activate``; it now names this install's argus unless the PATH finds that one."""
    import sys

    from deploy.query import argus_command, query_hint

    here = Path(sys.executable).with_name("argus")
    if not here.exists():
        pytest.skip("no argus script beside this interpreter")
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    cmd = argus_command()
    assert cmd != "argus" and Path(cmd).resolve() == here.resolve()
    assert query_hint("tcp/127.0.0.1:7447", "s") == f"{cmd} query --connect tcp/127.0.0.1:7447 --site s snapshot"
    monkeypatch.setenv("PATH", f"{here.parent}:/usr/bin:/bin")
    assert argus_command() == "argus"
