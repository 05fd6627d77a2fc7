"""Evidence for absence and moves (mapper.absence, ObjectMap.integrate): ray-cast keyframes of a room with a
floor and a back wall, so that where an object stood the camera sees the floor or the wall behind it."""

from __future__ import annotations

import dataclasses

import numpy as np

from mapper.absence import AbsenceParams, Verdict, judge
from mapper.association import KeyframeView
from mapper.core import MapperCore
from mapper.fusion import FusionConfig, Object3D, ObjectMap, PixelRecord, UpdateResult, voxel_downsample
from mapper.geometry.contract import OracleData, View
from mapper.geometry.singleview import SeenView, depth_to_world
from mapper.perception.base import label_descriptor
from protocol.poses import look_at
from protocol.query import GraphQuery
from tests.support.boxes import INTR, oracle_core, raycast

Box = tuple[np.ndarray, np.ndarray]


def box(lo: list[float], hi: list[float]) -> Box:
    return np.array(lo, np.float64), np.array(hi, np.float64)


FLOOR = box([-3.0, -3.0, -0.05], [6.0, 6.0, 0.0])
WALL = box([4.0, -3.0, 0.0], [4.1, 6.0, 2.6])
CHAIR = box([1.3, 0.1, 0.0], [1.75, 0.55, 0.9])
MOVED = (CHAIR[0] + [0.0, 1.0, 0.0], CHAIR[1] + [0.0, 1.0, 0.0])  # the chair, 1 m to the side
LAMP = box([1.4, -1.4, 0.0], [1.7, -1.1, 1.5])
PERSON = box([0.15, 0.0, 0.0], [0.55, 0.65, 1.8])  # a passer-by between the camera and the chair
EYE = [-1.5, 0.6, 1.6]
TARGET = (1.5, 0.6, 0.5)


def keyframe(objects: dict[str, Box], occluders: tuple[Box, ...] = (), eye: list[float] = EYE,
             depth_scale: float = 1.0, hole: Box | None = None, target: tuple[float, float, float] = TARGET,
             ) -> tuple[KeyframeView, list[Object3D]]:
    """A keyframe of the room (floor, wall), ``objects`` (label -> box, each detected) and ``occluders``
    (undetected: people). ``depth_scale`` scales the depth (wrong estimated depth); ``hole``: no confident
    depth where that box would be seen (textureless)."""
    T = look_at(eye, list(target))
    scene = [FLOOR, WALL, *objects.values(), *occluders]
    depth, idx = raycast(T, scene)
    depth = np.where(np.isfinite(depth), depth * depth_scale, 0.0).astype(np.float32)
    if hole is not None:
        _, hidx = raycast(T, [hole])
        depth[hidx >= 0] = 0.0
    pts = depth_to_world(depth, INTR.K(), T)
    objs = []
    for k, label in enumerate(objects, start=2):
        m = (idx == k) & (depth > 0)
        if m.sum() >= 5:
            objs.append(Object3D(voxel_downsample(pts[m], 0.03).astype(np.float32), label, 0.9,
                                 label_descriptor(label), mask=idx == k))
    return KeyframeView(INTR.K(), T, depth), objs


def mapped(objects: dict[str, Box], cfg: FusionConfig | None = None) -> ObjectMap:
    """An object map that saw ``objects`` from two places."""
    om = ObjectMap(cfg or FusionConfig(merge_every_updates=100))
    for t, eye in enumerate((EYE, [-1.2, -0.4, 1.5])):
        kv, objs = keyframe(objects, eye=eye)
        om.integrate(objs, "cam1", t + 1, kv)
    assert len(om.nodes) == len(objects)
    return om


def node_of(om: ObjectMap, label: str) -> str:
    return next(k for k, n in om.nodes.items() if n.label_ranking()[0][0] == label)


class TestJudge:
    def test_a_node_where_the_keyframe_sees_it_is_there(self) -> None:
        kv, objs = keyframe({"chair": CHAIR})
        assert judge(kv, objs[0].points, AbsenceParams()).verdict is Verdict.THERE

    def test_an_empty_place_is_free(self) -> None:
        _, objs = keyframe({"chair": CHAIR})
        kv, _ = keyframe({})
        j = judge(kv, objs[0].points, AbsenceParams())
        assert j.verdict is Verdict.FREE and j.free > 0.9 * j.known

    def test_a_passer_by_in_front_is_no_evidence(self) -> None:
        _, objs = keyframe({"chair": CHAIR})
        kv, _ = keyframe({}, occluders=(PERSON,))
        j = judge(kv, objs[0].points, AbsenceParams())
        assert j.verdict is Verdict.UNKNOWN and j.occluded > 0.5 * j.pixels

    def test_furniture_in_front_hides_less_than_a_person_does(self) -> None:
        """A table hides the lower 60 % of where the chair stood: with the keyframe's people known (none here),
        the rest in sight (29 pixels) seeing through is evidence; not knowing where people are, or the table
        being a person, it is none; hidden up to 80 %, it is none either."""
        _, objs = keyframe({"chair": CHAIR})
        kv, _ = keyframe({}, occluders=(box([0.7, -0.3, 0.0], [1.2, 1.0, 0.75]),))
        nobody = dataclasses.replace(kv, people=np.zeros(kv.depth_m.shape, bool))
        j = judge(nobody, objs[0].points, AbsenceParams())
        assert j.verdict is Verdict.FREE and 0.5 * j.pixels < j.occluded < 0.7 * j.pixels
        assert judge(kv, objs[0].points, AbsenceParams()).verdict is Verdict.UNKNOWN
        bare, _ = keyframe({})
        person = dataclasses.replace(kv, people=kv.depth_m < bare.depth_m - 0.05)  # where the table is
        assert judge(person, objs[0].points, AbsenceParams()).verdict is Verdict.UNKNOWN
        tall, _ = keyframe({}, occluders=(box([0.7, -0.3, 0.0], [1.2, 1.0, 0.9]),))
        tall = dataclasses.replace(tall, people=np.zeros(kv.depth_m.shape, bool))
        assert judge(tall, objs[0].points, AbsenceParams()).verdict is Verdict.UNKNOWN

    def test_a_person_standing_in_the_place_hides_it(self) -> None:
        """The chair gone and a person standing where it stood: their surface is at the chair's depth. Known to
        be a person, it hides the place (no verdict, so no miss either); not known, it looks like the chair."""
        _, objs = keyframe({"chair": CHAIR})
        there = box([1.35, 0.1, 0.0], [1.75, 0.55, 1.8])
        kv, _ = keyframe({}, occluders=(there,))
        assert judge(kv, objs[0].points, AbsenceParams()).verdict is Verdict.THERE
        bare, _ = keyframe({})
        person = dataclasses.replace(kv, people=kv.depth_m < bare.depth_m - 0.05)
        j = judge(person, objs[0].points, AbsenceParams())
        assert j.verdict is Verdict.UNKNOWN and j.occluded > 0.75 * j.pixels and j.there < 0.15 * j.pixels

    def test_missing_depth_is_no_evidence(self) -> None:
        _, objs = keyframe({"chair": CHAIR})
        kv, _ = keyframe({}, hole=box([1.0, -0.2, 0.0], [4.2, 0.9, 2.0]))
        assert judge(kv, objs[0].points, AbsenceParams()).verdict is Verdict.UNKNOWN

    def test_out_of_view_or_out_of_range_is_no_evidence(self) -> None:
        _, objs = keyframe({"chair": CHAIR})
        behind, _ = keyframe({}, target=(-3.0, 0.6, 0.5))  # looking away from the chair
        assert judge(behind, objs[0].points, AbsenceParams()).verdict is Verdict.UNKNOWN
        kv, _ = keyframe({})
        assert judge(kv, objs[0].points, AbsenceParams(max_range_m=1.0)).verdict is Verdict.UNKNOWN

    def test_no_points(self) -> None:
        kv, _ = keyframe({})
        assert judge(kv, np.zeros((0, 3)), AbsenceParams()).verdict is Verdict.UNKNOWN


class TestRetirement:
    def test_a_node_seen_empty_from_two_keyframes_is_retired(self) -> None:
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair, lamp = node_of(om, "chair"), node_of(om, "lamp")
        kv, objs = keyframe({"lamp": LAMP})
        res = om.integrate(objs, "cam1", 10, kv)
        assert chair in om.nodes and om.nodes[chair].absent == 1 and not res.removed
        kv, objs = keyframe({"lamp": LAMP}, eye=[-1.4, 0.4, 1.7])
        res = om.integrate(objs, "cam1", 11, kv)
        assert res.removed == {chair} and set(res.retired) == {chair} and chair not in res.changed
        assert list(om.nodes) == [lamp]

    def test_one_keyframe_is_not_enough_and_a_detection_clears_the_count(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        kv, objs = keyframe({})
        om.integrate(objs, "cam1", 10, kv)
        assert om.nodes[chair].absent == 1
        kv, objs = keyframe({"chair": CHAIR})
        om.integrate(objs, "cam1", 11, kv)
        assert om.nodes[chair].absent == 0
        kv, objs = keyframe({})
        res = om.integrate(objs, "cam1", 12, kv)
        assert chair in om.nodes and not res.removed

    def test_a_passer_by_in_front_retires_nothing(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        for t in range(6):  # the chair is still there, hidden: and also when it has gone, hidden
            kv, objs = keyframe({"chair": CHAIR} if t % 2 else {}, occluders=(PERSON,))
            res = om.integrate([o for o in objs if o.label != "chair"], "cam1", 10 + t, kv)
            assert not res.removed
        assert chair in om.nodes and om.nodes[chair].absent == 0

    def test_missing_or_wrong_depth_in_one_keyframe_retires_nothing(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        hole = box([1.0, -0.2, 0.0], [4.2, 0.9, 2.0])
        for t in range(4):  # the chair is there but its pixels have no depth, and it is not detected
            kv, _ = keyframe({"chair": CHAIR}, hole=hole)
            assert not om.integrate([], "cam1", 10 + t, kv).removed
        kv, _ = keyframe({"chair": CHAIR}, depth_scale=1.6)  # estimated depth far beyond, once
        om.integrate([], "cam1", 20, kv)
        kv, _ = keyframe({"chair": CHAIR})  # then right again, still undetected: a surface where it stands
        om.integrate([], "cam1", 21, kv)
        assert chair in om.nodes and om.nodes[chair].absent == 0

    def test_a_detection_at_a_wrong_depth_is_still_a_detection(self) -> None:
        """Estimated depth far beyond the chair, on its pixels and on its detection alike: the detection's mask
        holds the node, so the node was seen (not absent) and did not move to where the wrong depth put it."""
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        before = om.nodes[chair].centre
        for t in range(3):
            kv, objs = keyframe({"chair": CHAIR}, depth_scale=1.6)
            res = om.integrate(objs, "cam1", 10 + t, kv)
            assert chair in om.nodes and not res.moved and not res.retired
        assert om.nodes[chair].centre == before and om.nodes[chair].absent == 0

    def test_a_detection_that_could_not_be_lifted_is_still_a_detection(self) -> None:
        """The chair's pixels show the wall's depth and its detection had too little depth to be lifted (no 3D
        object): its mask still says the chair was seen."""
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        _, objs = keyframe({"chair": CHAIR})
        empty, _ = keyframe({})
        for t in range(3):
            res = om.integrate([], "cam1", 10 + t, empty, detected=[(objs[0].mask, label_descriptor("chair"))])
            assert not res.removed and om.nodes[chair].absent == 0
        res = om.integrate([], "cam1", 20, empty, detected=[(objs[0].mask, label_descriptor("lamp"))])
        assert om.nodes[chair].absent == 1  # a mask of something else is no detection of the chair

    def test_absence_check_can_be_switched_off(self) -> None:
        om = mapped({"chair": CHAIR}, FusionConfig(merge_every_updates=100, absence_check=False))
        for t in range(3):
            kv, _ = keyframe({})
            assert not om.integrate([], "cam1", 10 + t, kv).removed
        assert len(om.nodes) == 1


class TestMoves:
    def test_a_moved_chair_keeps_its_id(self) -> None:
        """The first keyframe after the move sees the old place empty once: not enough to move a node (one wrong
        estimated depth must not move it onto a twin), so the chair there is a new node; the second keyframe
        that sees the old place empty moves the chair's node there and folds the newcomer into it."""
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair = node_of(om, "chair")
        before = np.asarray(om.nodes[chair].centre)
        kv, objs = keyframe({"chair": MOVED, "lamp": LAMP})
        res = om.integrate(objs, "cam1", 10, kv)
        assert res.created == 1 and not res.moved and om.nodes[chair].absent == 1
        (newcomer,) = set(om.nodes) - {chair, node_of(om, "lamp")}
        kv, objs = keyframe({"chair": MOVED, "lamp": LAMP}, eye=[-1.4, 0.4, 1.7])
        res = om.integrate(objs, "cam1", 11, kv)
        assert len(om.nodes) == 2 and res.removed == {newcomer} and not res.retired and set(res.moved) == {chair}
        assert chair in res.changed
        node = om.nodes[chair]
        after = np.asarray(node.centre)
        assert np.linalg.norm(after - before - [0.0, 1.0, 0.0]) < 0.1
        assert node.last_moved_ns == 10 and node.moves == 1 and node.absent == 0 and node.observations == 4
        assert np.allclose(res.moved[chair][0], before) and np.allclose(res.moved[chair][1], after)
        msg = om.messages([chair])[0]
        assert msg.node_id == chair and abs(msg.centroid[1] - after[1]) < 1e-6

    def test_a_second_identical_chair_while_the_first_is_seen_is_a_new_node(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        kv, objs = keyframe({"chair": CHAIR, "chair2": MOVED})
        objs = [Object3D(o.points, "chair", o.confidence, label_descriptor("chair"), mask=o.mask) for o in objs]
        res = om.integrate(objs, "cam1", 10, kv)
        assert res.created == 1 and not res.moved and len(om.nodes) == 2 and chair in om.nodes

    def test_a_new_object_of_another_label_is_a_new_node(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        before = om.nodes[chair].centre
        kv, objs = keyframe({"lamp": MOVED})  # the chair's place is empty, a lamp elsewhere: not the chair
        res = om.integrate(objs, "cam1", 10, kv)
        assert res.created == 1 and not res.moved and om.nodes[chair].centre == before
        assert om.nodes[chair].absent == 1

    def test_a_chair_seen_gone_once_moves_when_seen_gone_again_in_the_same_keyframe_as_elsewhere(self) -> None:
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair = node_of(om, "chair")
        kv, objs = keyframe({"lamp": LAMP})  # gone from its place (one keyframe)
        om.integrate(objs, "cam1", 10, kv)
        kv, objs = keyframe({"chair": MOVED, "lamp": LAMP}, eye=[-1.4, 0.4, 1.7])  # gone again, and there
        res = om.integrate(objs, "cam1", 11, kv)
        assert set(res.moved) == {chair} and res.created == 0 and om.nodes[chair].last_moved_ns == 11
        assert not res.removed

    def test_state_round_trip_keeps_the_counts(self) -> None:
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair = node_of(om, "chair")
        kv, objs = keyframe({"chair": MOVED, "lamp": LAMP})
        om.integrate(objs, "cam1", 9, kv)
        kv, objs = keyframe({"chair": MOVED})
        om.integrate(objs, "cam1", 10, kv)
        lamp = node_of(om, "lamp")
        assert om.nodes[lamp].absent == 1
        again = ObjectMap(om.cfg)
        again.load_state(om.state())
        assert again.nodes[chair].last_moved_ns == 9 and again.nodes[chair].moves == 1
        assert again.nodes[lamp].absent == 1


# ------------------------------------------------------------------------------------------------
# Through MapperCore: a calibrated fixed camera with ORACLE depth and masks (people labelled "person")


def fixed_view(objects: dict[str, Box], seq: int, people: tuple[Box, ...] = ()) -> View:
    """A calibrated fixed camera's frame of the room with ``objects`` and ``people`` (ORACLE masks: the
    objects by their labels, people as "person"; floor and wall are structure), 0.5 s apart by ``seq`` (from
    1 s: a stamp of 0 means none)."""
    T = look_at(EYE, list(TARGET))
    depth, idx = raycast(T, [FLOOR, WALL, *objects.values(), *people])
    inst = np.where(idx >= 2, idx - 1, 0).astype(np.int32)
    labels = {i + 1: lab for i, lab in enumerate(objects)}
    labels.update({len(objects) + 1 + j: "person" for j in range(len(people))})
    rgb = np.full((INTR.height, INTR.width, 3), 90, np.uint8)
    rgb[inst > 0] = np.array([230, 20, 170, 250], np.uint8)[inst[inst > 0] % 4, None]  # objects stand out
    oracle = OracleData(depth_m=depth, T_world_cam_true=T, instance_id=inst, labels=labels)
    return View(image=rgb, source_id="cam1", intrinsics=INTR, T_world_cam=T, pose_trusted=True,
                stamp_ns=1_000_000_000 + seq * 500_000_000, seq=seq, oracle=oracle)


def core_that_saw(objects: dict[str, Box], **fusion: object) -> tuple[MapperCore, dict[str, str]]:
    core = oracle_core(**fusion)
    core.ingest(fixed_view(objects, 0))
    ids = {n.label: n.node_id for n in core.nodes()}
    assert set(ids) == set(objects)
    return core, ids


class TestMapperCore:
    def test_a_removed_object_is_retired_and_a_delta_says_so(self) -> None:
        core, ids = core_that_saw({"chair": CHAIR, "lamp": LAMP})
        # one second after its first keyframe it confirms the nodes it made (a keyframe without any change)
        assert core.ingest(fixed_view({"chair": CHAIR, "lamp": LAMP}, 2)) is not None
        assert core.counters["keyframes_confirming_new"] == 1 and core.counters["keyframes"] == 2
        # taken away: the camera's image changes (a keyframe), one second later it confirms (another)
        deltas = [core.ingest(fixed_view({"lamp": LAMP}, seq)) for seq in range(3, 10)]
        removals = [d for d in deltas if d is not None and d.removed]
        assert len(removals) == 1 and removals[0].removed == [ids["chair"]]
        (record,) = removals[0].retired
        assert record.node.node_id == ids["chair"] and record.node.label == "chair" and record.reason == "absent"
        assert [n.node_id for n in core.nodes()] == [ids["lamp"]]
        assert core.counters["nodes_retired"] == 1 and core.counters["keyframes_confirming_absence"] >= 1
        assert [r.node.node_id for r in core.retired(GraphQuery(include_retired=True))] == [ids["chair"]]
        assert core.retired(GraphQuery(label="lamp")) == []

    def test_a_passer_by_retires_nothing_and_is_no_node(self) -> None:
        core, ids = core_that_saw({"chair": CHAIR, "lamp": LAMP})
        walk = [(PERSON[0] + [0.0, dy, 0.0], PERSON[1] + [0.0, dy, 0.0]) for dy in (-0.4, 0.0, 0.2, 0.0, -0.2)]
        for seq, person in enumerate(walk * 2, start=1):
            d = core.ingest(fixed_view({"chair": CHAIR, "lamp": LAMP}, seq, people=(person,)), force_keyframe=True)
            assert d is None or not d.removed
        assert {n.node_id for n in core.nodes()} == set(ids.values())
        assert core.counters["detections_people"] >= 5 and "person" not in {n.label for n in core.nodes()}

    def test_a_removed_object_half_hidden_by_furniture_is_retired(self) -> None:
        """The chair taken away and a table put in front of its place, hiding 58 % of it: too much for a
        passer-by, but the table is no person (the keyframe's 2D perception says where people are), so what the
        camera sees of the place decides."""
        table = box([0.7, -0.3, 0.0], [1.2, 1.0, 0.65])
        core, ids = core_that_saw({"chair": CHAIR})
        removed = set()
        for seq in range(1, 8):
            d = core.ingest(fixed_view({"table": table}, seq))
            removed |= set(d.removed) if d is not None else set()
        assert removed == {ids["chair"]} and {n.label for n in core.nodes()} == {"table"}

    def test_a_person_in_front_of_a_removed_object_is_no_evidence(self) -> None:
        """... the same place hidden by a person instead: no verdict, the node stays."""
        hider = box([0.7, -0.3, 0.0], [1.2, 1.0, 0.65])
        core, ids = core_that_saw({"chair": CHAIR})
        for seq in range(1, 8):
            d = core.ingest(fixed_view({}, seq, people=(hider,)), force_keyframe=True)
            assert d is None or not d.removed
        assert [n.node_id for n in core.nodes()] == [ids["chair"]]

    def test_people_are_nodes_when_asked(self) -> None:
        core = oracle_core(fuse_people=True)
        core.ingest(fixed_view({"lamp": LAMP}, 0, people=(PERSON,)))
        assert {n.label for n in core.nodes()} == {"lamp", "person"}

    def test_a_moved_object_keeps_its_id_and_the_delta_has_a_move(self) -> None:
        core, ids = core_that_saw({"chair": CHAIR, "lamp": LAMP})
        # its next keyframe (refresh_s later) sees the old place empty and a chair elsewhere (a new node), the
        # confirming keyframe a second later sees the old place empty again: the chair's node moves there
        deltas = [core.ingest(fixed_view({"chair": MOVED, "lamp": LAMP}, seq)) for seq in range(4, 7)]
        d = next(d for d in deltas if d is not None and d.moves)
        assert [m.node_id for m in d.moves] == [ids["chair"]] and d.retired == [] and len(d.removed) == 1
        m = d.moves[0]
        assert m.stamp_ns == 3_000_000_000 and abs(m.to_centroid[1] - m.from_centroid[1] - 1.0) < 0.1
        chair = next(n for n in d.upserted if n.node_id == ids["chair"])
        assert abs(chair.centroid[1] - m.to_centroid[1]) < 1e-9 and len(core.nodes()) == 2
        assert [x.node_id for x in core.snapshot().moves] == [ids["chair"]]


def test_a_chair_seen_elsewhere_first_takes_its_old_id_when_its_place_is_seen_empty() -> None:
    """A robot that comes round the other way sees the moved chair first (a new node), then the old place
    empty: the old node moves there and the newcomer folds into it."""
    om = mapped({"chair": CHAIR, "lamp": LAMP})
    chair = node_of(om, "chair")
    far = (CHAIR[0] + [-3.5, 0.0, 0.0], CHAIR[1] + [-3.5, 0.0, 0.0])  # behind the cameras that saw it
    kv, objs = keyframe({"chair": far}, eye=[-0.3, 0.3, 1.6], target=(-2.0, 0.3, 0.4))  # facing away from it
    res = om.integrate(objs, "robot1", 10, kv)
    (newcomer,) = {k for k in res.changed if k != chair}
    assert res.created == 1 and not res.moved
    for t, eye in enumerate((EYE, [-1.4, 0.4, 1.7])):  # the old place, empty, from two keyframes
        kv, objs = keyframe({"lamp": LAMP}, eye=eye)
        res = om.integrate(objs, "robot1", 11 + t, kv)
    assert res.removed == {newcomer} and not res.retired and set(res.moved) == {chair}
    node = om.nodes[chair]
    assert abs(node.centre[0] - (CHAIR[0][0] + CHAIR[1][0]) / 2 + 3.5) < 0.1 and node.last_moved_ns == 10
    assert sorted(om.nodes) == sorted([chair, node_of(om, "lamp")])


class _Query:
    """What GraphQueries reads of a Zenoh query, recording the replies."""

    def __init__(self, key: str, parameters: str = "") -> None:
        self.key_expr, self.parameters = key, parameters
        self.replies: list[tuple[str, object]] = []
        self.errors: list[str] = []

    def reply(self, key: str, payload: object, encoding: object = None) -> None:
        self.replies.append((key, payload))

    def reply_err(self, payload: str, encoding: object = None) -> None:
        self.errors.append(payload)


def test_retired_nodes_are_answered_to_include_retired_queries_json_and_msgpack() -> None:
    import json

    from mapper.queries import GraphQueries
    from protocol.codec import decode
    from protocol.keys import Keys
    from protocol.messages import GraphSnapshot
    from protocol.transport import Counters

    core, ids = core_that_saw({"chair": CHAIR, "lamp": LAMP})
    for seq in range(1, 7):
        core.ingest(fixed_view({"lamp": LAMP}, seq))
    keys = Keys("s")
    queries = GraphQueries(core, keys, Counters(), lambda *a: None)
    q = _Query(keys.graph_json(keys.graph_nodes), "include_retired=true")
    queries.on_json_query(q)
    (_, payload), = q.replies
    body = json.loads(str(payload))
    assert [n["node_id"] for n in body["nodes"]] == [ids["lamp"]]
    assert [r["node"]["node_id"] for r in body["retired"]] == [ids["chair"]]
    # seen empty at 2 s (the keyframe confirming the nodes it made at 1 s) and at 3 s (refresh_s): retired
    assert body["retired"][0]["reason"] == "absent" and body["retired"][0]["retired_ns"] == 3_000_000_000
    q = _Query(keys.graph_nodes, "label=chair;include_retired=1")
    queries.on_query(q)
    (_, data), = q.replies
    snap = decode(bytes(data), GraphSnapshot)  # type: ignore[arg-type]
    assert snap.nodes == [] and [r.node.node_id for r in snap.retired] == [ids["chair"]]
    q = _Query(keys.graph_nodes, "label=chair")
    queries.on_query(q)
    assert decode(bytes(q.replies[0][1]), GraphSnapshot).retired == []  # type: ignore[arg-type]


def test_a_thin_object_whose_depth_is_mostly_the_backgrounds_is_not_seen_through() -> None:
    """A pole five pixels wide whose estimated depth is right on its middle column only, the wall's behind it on the
    others (stereo is weakest on thin things): without the nearest depth around each pixel it looks seen
    through, with it (absence_window_px = 1) it does not."""
    from mapper.absence import nearest_depth

    pole = box([1.5, 0.45, 0.0], [1.55, 0.7, 1.5])
    T = look_at(EYE, list(TARGET))
    true, idx = raycast(T, [FLOOR, WALL, pole])
    wall_only, _ = raycast(T, [FLOOR, WALL])
    cols = np.flatnonzero((idx == 2).any(axis=0))
    assert len(cols) == 5
    pts = depth_to_world(true, INTR.K(), T)[idx == 2]
    wrong = np.where((idx == 2) & (np.arange(true.shape[1]) != cols[2]), wall_only, true)
    kv = KeyframeView(INTR.K(), T, wrong)
    params = AbsenceParams(min_pixels=10)
    assert judge(kv, pts, params).verdict is Verdict.FREE
    assert judge(nearest_depth(kv, 1), pts, params).verdict is not Verdict.FREE
    assert nearest_depth(kv, 0) is kv


CABINET = box([3.8, 0.1, 0.0], [4.0, 0.6, 1.2])  # shallow, flush against the wall: gone, the wall is at its depth


class TestMisses:
    def test_depth_alone_cannot_see_a_flush_object_gone(self) -> None:
        _, objs = keyframe({"cabinet": CABINET})
        kv, _ = keyframe({})
        assert judge(kv, objs[0].points, AbsenceParams()).verdict is Verdict.THERE

    def test_a_fixed_camera_that_no_longer_detects_it_retires_it_after_its_misses(self) -> None:
        om = mapped({"cabinet": CABINET, "lamp": LAMP})
        cab = node_of(om, "cabinet")
        kv, objs = keyframe({"lamp": LAMP})
        for t in range(2):
            res = om.integrate(objs, "cam1", 10 + t, kv, fixed=True)
            assert not res.removed and res.seen_gone == {cab} and om.nodes[cab].missed == t + 1
        res = om.integrate(objs, "cam1", 12, kv, fixed=True)
        assert res.removed == {cab} and set(res.retired) == {cab}

    def test_a_detection_clears_the_misses(self) -> None:
        om = mapped({"cabinet": CABINET})
        cab = node_of(om, "cabinet")
        kv, _ = keyframe({})
        om.integrate([], "cam1", 10, kv, fixed=True)
        om.integrate([], "cam1", 11, kv, fixed=True)
        kv2, objs = keyframe({"cabinet": CABINET})
        om.integrate(objs, "cam1", 12, kv2, fixed=True)
        assert om.nodes[cab].missed == 0
        res = om.integrate([], "cam1", 13, kv, fixed=True)
        assert not res.removed and om.nodes[cab].missed == 1

    def test_robots_and_other_cameras_do_not_count_misses(self) -> None:
        om = mapped({"cabinet": CABINET})
        cab = node_of(om, "cabinet")
        kv, _ = keyframe({})
        for t in range(4):
            assert not om.integrate([], "robot1", 10 + t, kv).removed  # not fixed
            assert not om.integrate([], "cam2", 20 + t, kv, fixed=True).removed  # never detected it
        assert om.nodes[cab].missed == 0

    def test_a_passer_by_in_front_of_part_of_it_is_no_miss(self) -> None:
        om = mapped({"cabinet": CABINET})
        cab = node_of(om, "cabinet")
        part = box([2.0, 0.1, 0.0], [2.3, 0.3, 1.8])  # hides part of the cabinet
        kv, _ = keyframe({"cabinet": CABINET}, occluders=(part,))
        for t in range(4):
            assert not om.integrate([], "cam1", 10 + t, kv, fixed=True).removed
        assert om.nodes[cab].missed == 0


def test_masks_at_another_resolution_than_the_depth_are_resized() -> None:
    """A coarse placement's mask comes at the image's resolution, the keyframe's depth at the reconstructor's:
    mask association used to index one with the other's pixels (IndexError: the keyframe was lost)."""
    om = mapped({"chair": CHAIR})
    kv, objs = keyframe({"chair": CHAIR})
    big = np.repeat(np.repeat(objs[0].mask, 2, axis=0), 2, axis=1)  # the same mask at twice the size
    small = Object3D(objs[0].points, "chair", 0.9, label_descriptor("chair"), mask=big[::4, ::4])
    for o in (Object3D(objs[0].points, "chair", 0.9, label_descriptor("chair"), mask=big), small):
        res = om.integrate([o], "cam1", 10, kv)
        assert res.associated == 1 and res.created == 0


BAG = box([1.3, 0.35, 0.0], [1.75, 0.9, 0.9])  # stands where half the chair stood


class TestMixed:
    def test_a_neighbour_in_half_its_place_is_mixed(self) -> None:
        _, objs = keyframe({"chair": CHAIR})
        kv, _ = keyframe({"bag": BAG})
        j = judge(kv, objs[0].points, AbsenceParams())
        assert j.verdict is Verdict.MIXED and j.free > 0.3 * j.known and j.there > 0.3 * j.known

    def test_a_fixed_camera_counts_mixed_views_without_a_detection_as_misses(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        kv, objs = keyframe({"bag": BAG})
        for t in range(2):
            res = om.integrate(objs, "cam1", 10 + t, kv, fixed=True)
            assert not res.removed and res.seen_gone == {chair} and om.nodes[chair].missed == t + 1
        assert om.integrate(objs, "cam1", 12, kv, fixed=True).removed == {chair}

    def test_a_robot_counts_mixed_views_where_it_saw_the_object_from(self) -> None:
        """A low table gone from beside a sofa: the robot that saw it from about here now sees part floor, part
        sofa within the margin (MIXED) and detects nothing: misses, as a fixed camera counts them."""
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        kv, objs = keyframe({"bag": BAG})
        for t in range(2):
            res = om.integrate(objs, "robot1", 10 + t, kv)
            assert not res.removed and res.seen_gone == {chair} and om.nodes[chair].missed == t + 1
        assert om.integrate(objs, "robot1", 12, kv).removed == {chair}

    def test_mixed_views_from_a_robot_elsewhere_or_switched_off_are_no_evidence(self) -> None:
        side = [1.5, -2.4, 1.6]  # 90 degrees round from where the chair was detected
        for cfg, eye in ((FusionConfig(merge_every_updates=100), side),
                         (FusionConfig(merge_every_updates=100, absence_mixed_sight_deg=0.0), EYE)):
            om = mapped({"chair": CHAIR}, cfg)
            chair = node_of(om, "chair")
            kv, objs = keyframe({"bag": BAG}, eye=eye)
            assert om.absence_verdicts(kv)[chair] is Verdict.MIXED
            for t in range(4):
                assert not om.integrate(objs, "robot1", 10 + t, kv).removed
            assert om.nodes[chair].absent == om.nodes[chair].missed == 0


def seen_view(objects: dict[str, Box], occluders: dict[str, Box] | None = None,
              people_known: bool = False) -> SeenView:
    """What a calibrated camera at EYE sees without depth (a single-view keyframe): each of ``objects`` and
    ``occluders`` (label -> box) detected with its label's descriptor; ``people_known``: the view says which
    detections are people (those labelled "person")."""
    T = look_at(EYE, list(TARGET))
    named = {**objects, **(occluders or {})}
    _, idx = raycast(T, [FLOOR, WALL, *named.values()])
    owner = np.where(idx >= 2, idx - 2, -1).astype(np.int16)
    desc = np.stack([label_descriptor(k) for k in named]) if named else np.zeros((0, 1), np.float32)
    people = np.array([k == "person" for k in named], bool) if people_known else None
    return SeenView(INTR.K(), T, owner, idx == 0, desc.astype(np.float32), people=people)


class TestSingleViewMisses:
    """A fixed camera's keyframe without depth (no stereo partner): it counts a miss where its previous one saw
    the node on a similar detection and this one sees it on none."""

    def test_a_node_the_camera_saw_and_no_longer_detects_is_retired_after_its_misses(self) -> None:
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair = node_of(om, "chair")
        before, now = seen_view({"chair": CHAIR, "lamp": LAMP}), seen_view({"lamp": LAMP})
        for t in range(2):
            res = UpdateResult()
            assert om.count_misses(now, before if t == 0 else now, "cam1", res) == {chair}
            assert not res.removed and res.seen_gone == {chair} and om.nodes[chair].missed == t + 1
        res = UpdateResult()
        om.count_misses(now, now, "cam1", res)
        assert res.removed == {chair} and set(res.retired) == {chair}

    def test_no_count_starts_unless_the_previous_view_saw_it_there(self) -> None:
        om = mapped({"chair": CHAIR})
        now = seen_view({})
        assert om.count_misses(now, None, "cam1", UpdateResult()) == set()
        assert om.count_misses(now, now, "cam1", UpdateResult()) == set()  # its geometry is elsewhere

    def test_a_coarse_node_another_camera_placed_anew_moves_there_and_keeps_its_id(self) -> None:
        """Fixed cameras without depth: cam1 placed the chair by single-view geometry; it is carried into cam2's
        view, which places it anew; cam1's misses then move the old node there (same id, still coarse)."""
        om = ObjectMap(FusionConfig(merge_every_updates=100))
        _, objs = keyframe({"chair": CHAIR})
        om.integrate([Object3D(objs[0].points, "chair", 0.9, label_descriptor("chair"),
                               ray_origin=np.asarray(EYE, float))], "cam1", 1)
        (chair,) = om.nodes
        eye2 = [-1.2, 2.4, 1.5]
        _, objs = keyframe({"chair": MOVED}, eye=eye2)
        om.integrate([Object3D(objs[0].points, "chair", 0.9, label_descriptor("chair"),
                               ray_origin=np.asarray(eye2, float))], "cam2", 5)
        (newcomer,) = set(om.nodes) - {chair}
        there = np.asarray(om.nodes[newcomer].centre)
        before, now = seen_view({"chair": CHAIR}), seen_view({})
        res = UpdateResult()
        for t in range(3):
            res = UpdateResult()
            om.count_misses(now, before if t == 0 else now, "cam1", res)
        assert set(om.nodes) == {chair} and set(res.moved) == {chair} and res.removed == {newcomer}
        assert not res.retired and om.nodes[chair].rays  # still a single-view placement
        assert np.linalg.norm(np.asarray(om.nodes[chair].centre) - there) < 1e-6

    def test_a_camera_sees_again_what_it_placed_though_other_cameras_moved_it_along_its_ray(self) -> None:
        """A fixed camera without depth keyframes whenever its image changes (a person walking elsewhere); each
        keyframe places the same television at the same guessed depth. Other cameras moved the node along the
        ray, so the guess no longer overlaps it: it made a new node every keyframe."""
        for deg, created in ((1.0, 0), (0.0, 1)):
            om = ObjectMap(FusionConfig(merge_every_updates=100, coarse_same_ray_deg=deg))
            _, objs = keyframe({"chair": CHAIR, "lamp": LAMP})
            coarse = [Object3D(o.points, o.label, 0.9, label_descriptor(o.label), ray_origin=np.asarray(EYE, float))
                      for o in objs]
            om.integrate(coarse, "cam1", 1)
            chair = node_of(om, "chair")
            node = om.nodes[chair]
            (_, d), = node.rays
            node.points = node.points + (0.6 * d).astype(np.float32)  # triangulated 0.6 m farther
            node.touch()
            moved = node.points.copy()
            res = om.integrate(coarse, "cam1", 2)
            assert res.created == created and len(om.nodes) == 2 + created
            if created == 0:
                assert np.array_equal(om.nodes[chair].points, moved) and len(om.nodes[chair].rays) == 1
                assert om.nodes[chair].observations == 2

    def test_a_passer_by_in_front_or_another_camera_is_no_miss(self) -> None:
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        before = seen_view({"chair": CHAIR})
        hidden = seen_view({}, occluders={"person": PERSON})
        assert om.count_misses(hidden, before, "cam1", UpdateResult()) == set()
        assert om.count_misses(seen_view({}), before, "cam2", UpdateResult()) == set()  # cam2 never detected it
        assert om.count_misses(before, before, "cam1", UpdateResult()) == set()  # still detected
        assert om.count_misses(seen_view({}, occluders={"person": PERSON}, people_known=True), before, "cam1",
                               UpdateResult()) == set()
        assert om.nodes[chair].missed == 0

    def test_the_camera_asks_the_pixels_where_it_detected_the_node(self) -> None:
        """Other cameras' RGB-only depth spread the chair's points over the lamp beside it (their projection lands
        on the lamp's detection: no evidence either way); the pixels where this camera detected the chair show
        it gone: misses, and the node retired. A person on those pixels is no miss; without the record (or with
        ``absence_pixels`` off) the projected points decide, and count none."""
        for use_pixels, retired in ((True, True), (False, False)):
            om = mapped({"chair": CHAIR, "lamp": LAMP},
                        FusionConfig(merge_every_updates=100, absence_pixels=use_pixels))
            chair, lamp = node_of(om, "chair"), node_of(om, "lamp")
            before = seen_view({"chair": CHAIR, "lamp": LAMP})
            _, objs = keyframe({"chair": CHAIR, "lamp": LAMP})
            om.remember_pixels(objs, [chair, lamp], "cam1", before)
            rec = om.nodes[chair].seen_px["cam1"]
            assert np.array_equal(rec.pixels, np.flatnonzero(before.owner == 0)) and rec.shape == before.owner.shape
            om.nodes[chair].points = om.nodes[lamp].points.copy()
            om.nodes[chair].touch()
            hidden = seen_view({"lamp": LAMP}, occluders={"person": PERSON}, people_known=True)
            assert om.count_misses(hidden, before, "cam1", UpdateResult()) == set()
            now = seen_view({"lamp": LAMP}, people_known=True)
            # the camera moved (recalibrated): its record is of another view, and the points decide
            turned = dataclasses.replace(now, T_world_cam=now.T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))
            assert om.count_misses(turned, dataclasses.replace(before, T_world_cam=turned.T_world_cam), "cam1",
                                   UpdateResult()) == set()
            res = UpdateResult()
            for t in range(3):
                res = UpdateResult()
                om.count_misses(now, before if t == 0 else now, "cam1", res)
            assert (chair in res.retired) is retired and lamp in om.nodes

    def test_pixel_records_follow_moves_and_merges(self) -> None:
        om = mapped({"chair": CHAIR, "lamp": LAMP})
        chair, lamp = node_of(om, "chair"), node_of(om, "lamp")
        c, n = om.nodes[chair], om.nodes[lamp]
        def rec(*px: int) -> PixelRecord:
            return PixelRecord(np.eye(4), (4, 4), np.array(px, np.int32))

        c.seen_px = {"cam1": rec(1, 2)}
        n.seen_px = {"cam1": rec(7), "cam2": rec(9)}
        om.merge_nodes(c, n)  # the survivor's own record kept, the other camera's taken over
        assert set(c.seen_px) == {"cam1", "cam2"} and c.seen_px["cam1"].pixels.tolist() == [1, 2]
        _, objs = keyframe({"chair": MOVED})
        om._move(c, objs[0], 5, UpdateResult())
        assert c.seen_px == {}  # of the old place

    def test_furniture_in_front_hides_less_than_a_person_does(self) -> None:
        """The chair's place half hidden by a table: no miss while any detection in front might be a person; a
        miss once the view knows the table is none (the rest of the place in sight shows no chair)."""
        om = mapped({"chair": CHAIR})
        chair = node_of(om, "chair")
        before = seen_view({"chair": CHAIR})
        table = {"table": box([0.7, -0.3, 0.0], [1.2, 1.0, 0.65])}
        assert om.count_misses(seen_view({}, occluders=table), before, "cam1", UpdateResult()) == set()
        now = seen_view({}, occluders=table, people_known=True)
        c = now.coverage(om.nodes[chair].points, om.nodes[chair].descriptor, 0.8)
        assert 0.3 * c.points < c.other < 0.7 * c.points and c.people == 0
        assert om.count_misses(now, before, "cam1", UpdateResult()) == {chair}
        as_person = seen_view({}, occluders={"person": table["table"]}, people_known=True)
        assert om.count_misses(as_person, before, "cam1", UpdateResult()) == set()


def test_boxes_out_of_view_only_where_no_point_can_count() -> None:
    """A box said to be out of view has no point that judge would count (in the image, in front, in range)."""
    from mapper.absence import boxes_out_of_view
    from protocol.poses import invert, project

    rng = np.random.default_rng(8)
    view, _ = keyframe({"chair": CHAIR})
    h, w = view.depth_m.shape
    T = invert(view.T_world_cam)
    lo = rng.uniform(-6.0, 6.0, (400, 3))
    hi = lo + rng.uniform(0.01, 1.5, (400, 3))
    out = boxes_out_of_view(view, lo, hi, 6.0)
    assert 0 < out.sum() < len(out)
    for k in np.flatnonzero(out):
        pts = rng.uniform(lo[k], hi[k], (2000, 3))
        corners = np.array(np.meshgrid(*zip(lo[k], hi[k], strict=True), indexing="ij")).reshape(3, -1).T
        uv, z = project(view.K, np.concatenate([pts, corners]) @ T[:3, :3].T + T[:3, 3])
        inside = (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        assert not inside.any() or (z[inside] > 6.0).all(), k  # none counted, or all beyond range
    assert len(boxes_out_of_view(view, np.zeros((0, 3)), np.zeros((0, 3)), 6.0)) == 0
