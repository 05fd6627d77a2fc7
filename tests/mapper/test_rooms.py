"""Rooms from the map (mapper.rooms) on generated floor plans: exact room counts, doorways, ids, labels."""

from __future__ import annotations

import numpy as np
import pytest

from mapper.rooms import (
    RoomMapper,
    RoomParams,
    bridge_walls,
    build_grid,
    dominant_angle,
    estimate_floor_z,
    in_sight,
    label_room,
)
from protocol.prior import load_prior
from tests.support.floorplans import NODES, floor_points, node, two_rooms, wall_points


class TestFloorZ:
    def test_floor_height_found_above_strays(self) -> None:
        pts = np.concatenate([floor_points(0, 0, 3, 3, z=0.42), wall_points((0, 0), (3, 0), z=0.42),
                              [[1.0, 1.0, -2.0]]])
        assert estimate_floor_z(pts) == pytest.approx(0.42, abs=0.02)

    def test_empty_map_has_no_grid(self) -> None:
        assert estimate_floor_z(np.zeros((0, 3))) is None
        assert build_grid(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 6))) is None


class TestTwoRooms:
    def test_two_rooms_one_doorway_objects_in_the_right_room(self) -> None:
        rm = RoomMapper()
        layer = rm.update(two_rooms(), NODES)
        assert [r.room_id for r in layer.rooms] == ["room1", "room2"]
        left, right = sorted(layer.rooms, key=lambda r: r.centroid_xy[0])
        assert left.area_m2 == pytest.approx(16.0, rel=0.08) and right.area_m2 == pytest.approx(16.0, rel=0.08)
        assert len(layer.doorways) == 1
        d = layer.doorways[0]
        assert {d.room_a, d.room_b} == {left.room_id, right.room_id}
        assert d.position_xy[0] == pytest.approx(4.05, abs=0.15) and d.position_xy[1] == pytest.approx(1.95, abs=0.15)
        assert 0.6 <= d.width_m <= 1.0
        assert rm.in_room == {"a": left.room_id, "b": left.room_id, "c": right.room_id, "d": right.room_id}
        assert left.floor_z_m == pytest.approx(0.0, abs=0.02)
        # the outline is the room's rectangle, counter-clockwise
        poly = left.polygon_xy
        area = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
        assert area == pytest.approx(16.0, rel=0.1)
        assert poly[:, 0].min() == pytest.approx(0.0, abs=0.15) and poly[:, 0].max() == pytest.approx(4.0, abs=0.15)

    def test_labels_from_contents_unknown_without_evidence(self) -> None:
        rm = RoomMapper()
        layer = rm.update(two_rooms(), NODES[:2])
        left, right = sorted(layer.rooms, key=lambda r: r.centroid_xy[0])
        assert left.label == "bedroom" and left.label_confidence > 0.5
        assert right.label == "unknown" and right.label_confidence == 0.0
        layer = rm.update(two_rooms(), NODES)
        right = max(layer.rooms, key=lambda r: r.centroid_xy[0])
        assert right.label == "kitchen"

    def test_label_room_canonicalises_and_ignores_unknown_words(self) -> None:
        prior = load_prior()
        assert label_room([], prior)[:2] == ("unknown", 0.0)
        assert label_room(["xyzzy"], prior)[:2] == ("unknown", 0.0)
        kind, conf, post = label_room(["Toilet", "bath tub", "sink"], prior)
        assert kind == "bathroom" and conf == max(post.values()) and sum(post.values()) == pytest.approx(1.0)

    def test_no_doorway_no_connects_edge(self) -> None:
        layer = RoomMapper().update(two_rooms(door=None), NODES)
        assert len(layer.rooms) == 2 and layer.doorways == []

    def test_objects_far_outside_every_room_are_not_assigned(self) -> None:
        rm = RoomMapper()
        rm.update(two_rooms(), [*NODES, node("far", "chair", 20.0, 20.0)])
        assert "far" not in rm.in_room and len(rm.in_room) == 4


class TestIds:
    def test_a_room_keeps_its_id_as_the_map_grows_into_it(self) -> None:
        rm = RoomMapper()
        first = rm.update(two_rooms(right_to_x=5.8), NODES[:2])  # the right room seen only near the door
        ids = {r.room_id: r for r in first.rooms}
        assert len(ids) == 2
        right_id = max(first.rooms, key=lambda r: r.centroid_xy[0]).room_id
        grown = rm.update(two_rooms(), NODES)
        right = max(grown.rooms, key=lambda r: r.centroid_xy[0])
        assert right.room_id == right_id and right.area_m2 > ids[right_id].area_m2 + 3.0
        assert {r.room_id for r in grown.rooms} == set(ids)

    def test_rooms_merge_only_when_the_wall_is_seen_open(self) -> None:
        rm = RoomMapper()
        before = rm.update(two_rooms(), NODES)
        ids = sorted(r.room_id for r in before.rooms)
        # wall points lost and the floor along it never seen: not evidence of an opening, the rooms stay
        unseen = rm.update(two_rooms(wall=False, floor_under_wall=False), NODES)
        assert sorted(r.room_id for r in unseen.rooms) == ids
        # the floor is seen right through where the wall stood, over 4 m: the rooms are one, an old id kept
        opened = rm.update(two_rooms(wall=False, floor_under_wall=True), NODES)
        assert len(opened.rooms) == 1 and opened.rooms[0].room_id in ids
        assert opened.doorways == []
        assert set(rm.in_room.values()) == {opened.rooms[0].room_id}

    def test_rooms_merge_where_a_camera_walked_through_where_the_wall_stood(self) -> None:
        # RGB-only sees floor in patches: the other evidence that a wall is open is known free space along it, a
        # camera's passage here, with no wall cell left in the strip
        def walked(ys: np.ndarray) -> RoomMapper:
            rm = RoomMapper()
            rm.update(two_rooms(), NODES)
            for y in ys:
                rm.note_camera(np.array([4.05, y, 1.0]))
            return rm

        lost = two_rooms(wall=False, floor_under_wall=False)
        through_door = walked(np.arange(1.6, 2.35, 0.15))  # only the doorway's width: no opening seen
        assert len(through_door.update(lost, NODES).rooms) == 2
        along = walked(np.arange(0.4, 3.7, 0.3))  # along the whole line where the wall stood
        assert len(along.update(lost, NODES).rooms) == 1
        # the same walk with the wall still in the map beside the door: a camera's path merges nothing
        kept = walked(np.arange(0.4, 3.7, 0.3))
        assert len(kept.update(two_rooms(floor_under_wall=False), NODES).rooms) == 2
        # an object's footprint over the line is no passage: a box against a wall reaches over it
        boxed = walked(np.arange(1.6, 2.35, 0.15))
        assert len(boxed.update(lost, [*NODES, node("rug", "rug", 4.05, 2.0, 3.0)]).rooms) == 2
        off = RoomMapper(RoomParams(merge_free_fraction=0.0))
        off.update(two_rooms(), NODES)
        for y in np.arange(0.4, 3.7, 0.3):
            off.note_camera(np.array([4.05, y, 1.0]))
        assert len(off.update(lost, NODES).rooms) == 2

    def test_a_sliver_left_by_the_split_back_joins_its_neighbour(self) -> None:
        rm = RoomMapper()
        ids = sorted(r.room_id for r in rm.update(two_rooms(), NODES).rooms)
        # An earlier, coarser segmentation left a 0.8 x 0.8 m piece of the left room numbered as a room of its own
        # (under min_room_m2): the region that covers both is split back along them, and the sliver is no room.
        t = rm.tracker
        assert t._numbers is not None
        ij = np.argwhere(t._numbers > 0)
        corner = ij.min(0)
        t._numbers[corner[0]:corner[0] + 8, corner[1]:corner[1] + 8] = 99
        t._ids[99] = "room99"
        again = rm.update(two_rooms(), NODES)
        assert sorted(r.room_id for r in again.rooms) == ids
        assert "room99" not in rm.in_room.values()

    def test_a_new_room_gets_a_fresh_id_never_reused(self) -> None:
        rm = RoomMapper()
        one = rm.update(floor_points(0, 0, 4, 4), [])
        assert [r.room_id for r in one.rooms] == ["room1"]
        two = rm.update(two_rooms(), [])
        assert sorted(r.room_id for r in two.rooms) == ["room1", "room2"]

    def test_state_round_trip_keeps_ids(self) -> None:
        rm = RoomMapper()
        rm.note_camera(np.array([1.0, 1.0, 1.0]))
        rm.update(two_rooms(right_to_x=5.8), [])
        again = RoomMapper()
        again.load_state(rm.state())
        assert list(again.cameras) == list(rm.cameras)
        assert sorted(r.room_id for r in again.update(two_rooms(), []).rooms) == ["room1", "room2"]


def test_params_defaults_match_config() -> None:
    from mapper.config import RoomsConfig

    cfg = RoomsConfig()
    for f, v in RoomParams.__dataclass_fields__.items():
        assert getattr(cfg, f) == v.default, f


def test_voxels_seen_once_are_left_out_unless_that_leaves_almost_nothing() -> None:
    pts = two_rooms()
    stray = np.array([[6.0, 2.0, 1.5]] * 1 + [[6.0 + 0.01 * k, 2.0, 1.2 + 0.08 * k] for k in range(10)])
    counts = np.concatenate([np.full(len(pts), 3), np.ones(len(stray), int)])
    both = np.concatenate([pts, stray])
    assert len(RoomMapper().update(both, NODES).rooms) == 2  # the stray column is a wall blob: still two rooms
    layer = RoomMapper().update(both, NODES, counts)
    assert len(layer.rooms) == 2 and not layer.grid.wall[layer.grid.cells_of(np.array([[6.0, 2.0]]))[0][0],
                                                          layer.grid.cells_of(np.array([[6.0, 2.0]]))[0][1]]
    single = RoomMapper().update(pts, NODES, np.ones(len(pts), int))  # one keyframe's map: kept whole
    assert len(single.rooms) == 2


def test_a_thick_wall_band_splits_down_its_middle_between_the_rooms() -> None:
    """RGB-only depth scatters a wall's points across a band: each room takes the half of the band on its side."""
    rng = np.random.default_rng(3)
    thin = two_rooms(wall=False, floor_under_wall=False)
    face = wall_points((4.05, 0.0), (4.05, 4.0), gaps=((1.5, 2.4),))
    band = np.concatenate([face + [rng.uniform(-0.3, 0.3), 0.0, 0.0] for _ in range(40)])
    pts = np.concatenate([thin, band])
    edges = {}
    for share in (0.3, 0.0):
        layer = RoomMapper(RoomParams(wall_share_m=share)).update(pts, NODES)
        assert len(layer.rooms) == 2
        left, right = sorted(layer.rooms, key=lambda r: r.centroid_xy[0])
        g = layer.grid
        row = g.cells_of(np.stack([np.arange(2.0, 6.0, 0.05), np.full(80, 0.8)], 1))  # along y = 0.8, off the door
        owner = g.xy_of(row)[:, 0]
        room = layer.labels[row[:, 0], row[:, 1]]
        ids = [r.room_id for r in layer.rooms]
        edges[share] = (owner[room == ids.index(left.room_id) + 1].max(),
                        owner[room == ids.index(right.room_id) + 1].min())
    assert edges[0.3][0] == pytest.approx(4.05, abs=0.15) and edges[0.3][1] == pytest.approx(4.05, abs=0.15)
    # a ring of wall cells alone leaves most of the band to no room
    assert edges[0.0][0] < 3.9 and edges[0.0][1] > 4.2


def test_a_neck_wider_than_any_doorway_does_not_split_a_room() -> None:
    """One 8 x 5 m room whose floor was seen in two patches joined by 2.6 m of floor (RGB-only sees a large room's
    floor in patches): h-maxima alone split it at the neck; no doorway is that wide, so it stays one room."""
    pts = np.concatenate([floor_points(0.0, 0.0, 3.5, 5.0), floor_points(4.5, 0.0, 8.0, 5.0),
                          floor_points(3.5, 1.2, 4.5, 3.8), wall_points((0.0, 0.0), (8.0, 0.0)),
                          wall_points((0.0, 5.0), (8.0, 5.0)), wall_points((0.0, 0.0), (0.0, 5.0)),
                          wall_points((8.0, 0.0), (8.0, 5.0))])
    assert len(RoomMapper(RoomParams(door_max_m=0.0)).update(pts, NODES).rooms) == 2
    layer = RoomMapper().update(pts, NODES)
    assert len(layer.rooms) == 1 and layer.doorways == []
    assert layer.rooms[0].area_m2 == pytest.approx(40.0, rel=0.12)
    # a doorway (0.9 m) between two rooms stays a split
    assert len(RoomMapper().update(two_rooms(), NODES).rooms) == 2


class TestBridges:
    """A straight wall the map saw in two stretches is one wall, unless a camera passed through the gap."""

    @staticmethod
    def plan() -> np.ndarray:
        # the wall between the rooms seen only for y < 1.2 and y > 2.8: a 1.6 m gap, floor seen all through it
        return np.concatenate([two_rooms(wall=False), wall_points((4.05, 0.0), (4.05, 1.2)),
                               wall_points((4.05, 2.8), (4.05, 4.0))])

    @staticmethod
    def walked(params: RoomParams, y: float) -> RoomMapper:
        """A mapper whose camera walked along ``y`` from x = 1 to 7, 1.2 m above the floor (a robot's path)."""
        rm = RoomMapper(params)
        for x in np.arange(1.0, 7.01, 0.25):
            rm.note_camera(np.array([x, y, 1.2]))
        return rm

    def test_a_gap_no_camera_passed_is_wall(self) -> None:
        layer = self.walked(RoomParams(), 3.4).update(self.plan(), NODES)  # through the wall's seen stretch
        assert len(layer.rooms) == 2 and layer.doorways == []
        open_ = self.walked(RoomParams(wall_bridge_m=0.0), 3.4).update(self.plan(), NODES)
        assert len(open_.doorways) == 1 and open_.doorways[0].width_m >= 1.5
        # stretches of wall shorter than wall_run_m (tall furniture) bridge nothing (these are 1.2 m)
        short = self.walked(RoomParams(wall_run_m=1.5), 3.4).update(self.plan(), NODES)
        assert len(short.doorways) == 1
        # cameras fixed high on a wall pass through nothing: no bridge, the gap stays the opening it looks like
        fixed = RoomMapper()
        fixed.note_camera(np.array([0.2, 0.2, 2.4]))
        assert len(fixed.update(self.plan(), NODES).doorways) == 1

    def test_a_gap_a_camera_passed_through_stays_open(self) -> None:
        layer = self.walked(RoomParams(), 2.0).update(self.plan(), NODES)
        assert len(layer.doorways) == 1 and layer.doorways[0].width_m >= 1.5

    def test_bridges_follow_the_walls_dominant_angle(self) -> None:
        # a 6 m wall at 30 degrees to the grid with a 1.5 m gap in its middle, as grid cells
        t = np.deg2rad(30.0)
        s = np.concatenate([np.arange(0.0, 22.5, 0.5), np.arange(37.5, 60.0, 0.5)])
        ij = np.round(np.stack([10 + s * np.cos(t), 10 + s * np.sin(t)], 1)).astype(int)
        wall = np.zeros((70, 50), bool)
        wall[ij[:, 0], ij[:, 1]] = True
        assert np.rad2deg(dominant_angle(np.argwhere(wall))) == pytest.approx(30.0, abs=1.5)
        bridge = bridge_walls(wall, np.zeros_like(wall), gap_max=25.0, run_min=5.0)
        mid = np.round([10 + 30 * np.cos(t), 10 + 30 * np.sin(t)]).astype(int)
        assert bridge[mid[0] - 1:mid[0] + 2, mid[1] - 1:mid[1] + 2].any()
        far = np.argwhere(bridge) - [10, 10]
        assert np.abs(far[:, 0] * np.sin(t) - far[:, 1] * np.cos(t)).max() <= 1.5  # on the wall's line only
        shorter = bridge_walls(wall, np.zeros_like(wall), gap_max=10.0, run_min=5.0)  # the gap is longer: open
        assert not shorter[mid[0] - 3:mid[0] + 4, mid[1] - 3:mid[1] + 4].any()


class TestSight:
    """Free space only where a camera can have seen it: nothing is seen through a wall."""

    @staticmethod
    def beyond_the_wall() -> tuple[np.ndarray, list]:
        # one 4 x 4 m room walled all round, floor seen (RGB-only-like) 1 m past its right wall, and a box stretched
        # through that wall; the camera walked the room's middle
        pts = np.concatenate([floor_points(0.0, 0.0, 4.0, 4.0), floor_points(4.2, 1.0, 5.2, 3.0),
                              wall_points((0.0, 0.0), (4.0, 0.0)), wall_points((0.0, 4.0), (4.0, 4.0)),
                              wall_points((0.0, 0.0), (0.0, 4.0)), wall_points((4.05, 0.0), (4.05, 4.0))])
        return pts, [node("s", "sofa", 4.6, 2.0, 1.6)]

    def test_floor_and_footprints_behind_a_wall_make_no_room(self) -> None:
        pts, nodes = self.beyond_the_wall()
        reach = {}
        for sight in (16, 0):
            # (bridging off with the check: it would close the gap the stretched box cut in the wall)
            rm = RoomMapper(RoomParams(sight_cameras=sight, wall_bridge_m=2.5 if sight else 0.0))
            for y in (1.0, 2.0, 3.0):
                rm.note_camera(np.array([2.0, y, 1.2]))
            layer = rm.update(pts, nodes)
            assert len(layer.rooms) == 1
            reach[sight] = layer.rooms[0].polygon_xy[:, 0].max()
        assert reach[16] <= 4.2  # to its wall
        assert reach[0] >= 5.0  # the check off: the room reaches through its wall

    def test_a_doorway_keeps_what_is_seen_through_it(self) -> None:
        g = np.zeros((40, 40), bool)
        g[20, :] = True  # a wall along x = 20 cells
        g[20, 18:23] = False  # a doorway
        ask = np.zeros_like(g)
        ask[25:30, 18:23] = True  # straight through the doorway
        ask[25:30, 2:6] = True  # behind the wall
        cams = np.array([[10.0, 20.5]])
        seen = in_sight(ask, g, cams, 4, 3.0)
        assert seen[25:30, 18:23].all() and not seen[25:30, 2:6].any() and not seen[~ask].any()
        # a second camera past the wall sees it all; with no camera at all nothing is judged hidden
        assert in_sight(ask, g, np.array([[10.0, 20.5], [35.0, 4.0]]), 4, 3.0)[ask].all()
        assert in_sight(ask, g, np.zeros((0, 2)), 4, 3.0)[ask].all()

    def test_compiled_and_numpy_twins_agree(self) -> None:
        from scipy.spatial import cKDTree

        from mapper.rooms import _sight_compiled, _sight_loops, _sight_numpy

        rng = np.random.default_rng(3)
        wall = rng.random((70, 50)) < 0.06
        cells = np.argwhere((rng.random((70, 50)) < 0.6) & ~wall)
        cams = rng.uniform(0.0, 50.0, (25, 2))
        order = cKDTree(cams).query(cells + 0.5, k=6)[1].astype(np.int64)
        order[::7, 3:] = -1  # fewer cameras for some cells
        ref = _sight_numpy(wall, cells, cams, order, 3.0)
        assert 0.3 < ref.mean() < 0.99  # a test that can tell the two apart
        loops = _sight_compiled if _sight_compiled is not None else _sight_loops
        assert np.array_equal(loops(wall, cells, cams, order, 3.0), ref)


@pytest.mark.parametrize("structure", ["square", "cross", "disk1", "disk2", "disk3", "disk4"])
def test_opencv_morphology_matches_scipy(structure: str) -> None:
    from scipy import ndimage

    from mapper.rooms import _closing, _dilation, _disk, _erosion

    st = {"square": np.ones((3, 3), bool), "cross": ndimage.generate_binary_structure(2, 1)}.get(structure)
    st = st if st is not None else _disk(int(structure[-1]))
    rng = np.random.default_rng(7)
    for p in (0.03, 0.3, 0.8):
        for shape in ((61, 47), (3, 11), (1, 5)):
            m = rng.random(shape) < p
            assert np.array_equal(_dilation(m, st), ndimage.binary_dilation(m, structure=st))
            assert np.array_equal(_erosion(m, st), ndimage.binary_erosion(m, structure=st))
            assert np.array_equal(_closing(m, st), ndimage.binary_closing(m, structure=st))
