"""argus eval changes: the scorer on hand-made graph timelines (time to right, stale nodes, false retirements,
person nodes), and a small end-to-end run."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from bench.changes import ChangeScorer, live_nodes, place_seen, place_visible
from protocol.messages import GraphNode, Intrinsics, OrientedBox
from protocol.poses import look_at
from sim.changes import ChangingScene, add_edit, move_edit, remove_edit
from sim.materials import make_material
from sim.people import PERSON_ID_BASE, People, Walk
from sim.scene import Room, Scene, SceneObject
from sim.scoring import LabelSimilarity


def _obj(obj_id: int, label: str, xy: tuple[float, float]) -> SceneObject:
    T = np.eye(4)
    T[:2, 3] = xy
    mesh = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    mesh.apply_translation((xy[0], xy[1], 0.2))
    return SceneObject(obj_id=obj_id, label=label, category=label.replace(" ", "_"), room="hall", mesh=mesh,
                       box=OrientedBox(center=(xy[0], xy[1], 0.2), extent=(0.4, 0.4, 0.4)), parent_id=None,
                       centroid=np.array([xy[0], xy[1], 0.2]), T_world_obj=T, face_material=np.zeros(12, np.int32))


def _scene() -> Scene:
    floor = trimesh.creation.box(extents=(10.0, 10.0, 0.1))
    floor.apply_translation((0.0, 0.0, -0.05))
    objs = [_obj(3, "storage box", (1.0, 0.0)), _obj(5, "mug", (-2.0, 1.0)), _obj(9, "potted plant", (3.0, 3.0))]
    return Scene(family="test", seed=0, rooms=[Room("hall", "living_room", np.array([-5.0, -5.0]),
                                                    np.array([5.0, 5.0]))],
                 objects=objs, relations=[], bounds_min=np.array([-5.0, -5.0, -0.1]), bounds_max=np.array([5, 5, 2.5]),
                 structure=floor, structure_face_material=np.zeros(len(floor.faces), np.int32),
                 materials=[make_material("wood", np.random.default_rng(0))])


def _node(node_id: str, label: str, xy: tuple[float, float]) -> GraphNode:
    c = (xy[0], xy[1], 0.2)
    return GraphNode(node_id=node_id, label=label, label_confidence=1.0, centroid=c,
                     box=OrientedBox(center=c, extent=(0.4, 0.4, 0.4)), point_count=10, observation_count=1,
                     first_seen_ns=0, last_seen_ns=0)


@pytest.fixture
def world() -> ChangingScene:
    s = _scene()
    return ChangingScene(s, [move_edit(s, 3, 2.0, (1.0, 2.5)), remove_edit(s, 5, 4.0),
                             add_edit(s, "backpack", 6.0, (-3.0, -3.0), obj_id=10)])


def test_time_to_right_stale_nodes_and_false_retirements(world: ChangingScene) -> None:
    # a person stands next to the potted plant the whole time
    people = People([Walk(PERSON_ID_BASE, np.array([0.0]), np.array([[3.5, 3.0]]))])
    sc = ChangeScorer(world, people, similarity=LabelSimilarity("exact"))
    box_old, box_new, mug, plant, bag = (1.0, 0.0), (1.0, 2.5), (-2.0, 1.0), (3.0, 3.0), (-3.0, -3.0)
    person = _node("p1", "person", (3.5, 3.0))
    timeline = {
        0.0: [_node("n1", "storage box", box_old), _node("n2", "mug", mug), _node("n9", "potted plant", plant), person],
        1.0: [_node("n1", "storage box", box_old), _node("n2", "mug", mug), _node("n9", "potted plant", plant)],
        2.0: [_node("n1", "storage box", box_old), _node("n2", "mug", mug), _node("n9", "potted plant", plant)],
        3.0: [_node("n1", "storage box", box_old), _node("n3", "storage box", box_new), _node("n2", "mug", mug),
              _node("n9", "potted plant", plant)],
        4.0: [_node("n3", "storage box", box_new), _node("n2", "mug", mug), _node("n9", "potted plant", plant)],
        5.0: [_node("n3", "storage box", box_new)],  # the mug's node retired (right), the plant's lost (wrong)
        6.0: [_node("n3", "storage box", box_new)],
        7.0: [_node("n3", "storage box", box_new), _node("n4", "backpack", bag)],
    }
    # the mapper says it retired n9 as seen gone (the mug's n2 went some other way)
    samples = [sc.observe(t, nodes, retired={"n9"} if t >= 5.0 else ()) for t, nodes in timeline.items()]
    assert samples[0]["precision"] == 1.0 and samples[0]["nodes"] == 3 and samples[0]["person_nodes"] == 1
    assert [s["stale"] for s in samples] == [0, 0, 1, 1, 1, 0, 0, 0]
    res = sc.result()
    by_kind = {e["kind"]: e for e in res["edits"]}
    assert by_kind["move"]["time_to_right_s"] == 2.0  # found at 3 s, the old node gone at 4 s
    assert by_kind["move"]["known_before"] is True and by_kind["move"]["kept_id"] is False
    assert by_kind["remove"]["time_to_right_s"] == 1.0 and by_kind["remove"]["known_before"] is True
    assert by_kind["add"]["time_to_right_s"] == 1.0 and by_kind["add"]["known_before"] is None
    fr = res["false_retirements"]
    assert [(r["obj_id"], r["node_id"], r["t_s"], r["person"], r["seen_gone"]) for r in fr] == [
        (9, "n9", 5.0, True, True)]
    s = res["summary"]
    assert s["right"] == 3 and s["all_p50_s"] == 1.0 and s["all_p90_s"] == 2.0
    assert s["false_retirements"] == 1 and s["false_retirements_people"] == 1 and s["person_nodes"] == 1
    assert s["false_retirements_seen_gone"] == 1
    assert s["stale_max"] == 1 and s["moves_kept_id"] == "0/1"


def test_a_static_graph_never_gets_moves_and_removals_right(world: ChangingScene) -> None:
    """Today's baseline: nodes stay where first seen; the added object is found."""
    sc = ChangeScorer(world, similarity=LabelSimilarity("exact"))
    static = [_node("n1", "storage box", (1.0, 0.0)), _node("n2", "mug", (-2.0, 1.0)),
              _node("n9", "potted plant", (3.0, 3.0))]
    for t in np.arange(0.0, 10.0, 0.5):
        sc.observe(float(t), static + ([_node("n4", "backpack", (-3.0, -3.0))] if t >= 8.0 else []))
    res = sc.result(reference=[{"t_s": float(t), "f1": 1.0} for t in np.arange(0.0, 10.0, 0.5)])
    e = {x["kind"]: x for x in res["edits"]}
    assert e["move"]["time_to_right_s"] is None and e["remove"]["time_to_right_s"] is None
    assert e["add"]["time_to_right_s"] == 2.0
    s = res["summary"]
    assert s["right"] == 1 and s["all_p90_s"] == float("inf") and s["stale_end"] == 2 and s["false_retirements"] == 0
    # at the end: 2 true of 4 nodes (the box's and the mug's are stale), 2 of 3 objects found
    assert res["timeline"][-1]["f1"] == pytest.approx(4 / 7)
    assert s["f1_ratio_min_calm"] == 1.0  # outside 5 s after each edit (2, 4, 6 s): only the first 2 s


def test_a_moved_node_that_keeps_its_id(world: ChangingScene) -> None:
    sc = ChangeScorer(world, similarity=LabelSimilarity("exact"))
    sc.observe(1.0, [_node("n1", "storage box", (1.0, 0.0))])
    sc.observe(2.5, [_node("n1", "storage box", (1.0, 2.4))])
    e = sc.result()["edits"][0]
    assert e["kind"] == "move" and e["time_to_right_s"] == 0.5 and e["kept_id"] is True
    # an object the graph did not know before it moved: found at its new place, but no id to keep
    sc = ChangeScorer(world, similarity=LabelSimilarity("exact"))
    sc.observe(1.0, [])
    sc.observe(2.5, [_node("n7", "storage box", (1.0, 2.4))])
    e = sc.result()["edits"][0]
    assert e["known_before"] is False and e["time_to_right_s"] == 0.5 and e["kept_id"] is None


def test_retired_nodes_are_gone_and_places_are_seen() -> None:
    nodes = [SimpleNamespace(node_id="a", retired=True), SimpleNamespace(node_id="b", retired_ns=5),
             SimpleNamespace(node_id="c", status="retired"), SimpleNamespace(node_id="d")]
    assert [n.node_id for n in live_nodes(nodes)] == ["d"]
    K = Intrinsics(width=100, height=100, fx=50.0, fy=50.0, cx=50.0, cy=50.0)
    T = look_at((0.0, 0.0, 1.0), (5.0, 0.0, 1.0))
    depth = np.full((100, 100), 3.0, np.float32)
    assert place_visible((2.0, 0.0, 1.0), K, T, depth)  # in front of what the camera sees
    assert place_visible((3.2, 0.0, 1.0), K, T, depth)  # just behind a surface: within the margin
    assert not place_visible((5.0, 0.0, 1.0), K, T, depth)  # hidden
    assert not place_visible((-2.0, 0.0, 1.0), K, T, depth)  # behind the camera
    # a place is seen when most of it is: not its centre through a doorway in a wall
    box = OrientedBox(center=(2.0, 0.0, 1.0), extent=(0.6, 0.6, 0.6))
    assert place_seen(box, K, T, depth)
    wall = np.full((100, 100), 1.0, np.float32)
    wall[:, 47:54] = 3.0  # a doorway 7 pixels wide
    assert place_visible(box.center, K, T, wall) and not place_seen(box, K, T, wall)
    # a surface 0.35 m before the place's centre: the object's own front where it stands, else a table in front
    near = np.full((100, 100), 1.65, np.float32)
    assert place_seen(box, K, T, near) and not place_seen(box, K, T, near, occupied=False)


@pytest.mark.slow
def test_quick_run_writes_json_markdown_and_plot(tmp_path) -> None:
    from bench.changes import quick_changes
    from bench.eval import EvalConfig, run

    cfg = EvalConfig(out=tmp_path, experiments=["changes"], changes=quick_changes().model_copy(
        update={"duration_s": 12.0, "edits": 2, "edit_window": (0.2, 0.5)}))
    lines: list[str] = []
    run(cfg, log=lines.append)
    res = json.loads((tmp_path / "changes.json").read_text())
    run_ = res["per_run"][0]
    assert run_["geometry"] == "oracle" and len(run_["timeline"]) == 13 and len(run_["edits"]) >= 1
    assert "Dynamic scenes" in (tmp_path / "changes.md").read_text() and (tmp_path / "changes.png").stat().st_size
    assert any("edit at" in m for m in lines) and any("t=10s" in m for m in lines)
