"""The pure planner on hand-made point maps and graphs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner import synthetic as S
from planner.completion import (
    Completion,
    HypObject,
    PriorSampler,
    SamplerInfo,
    SceneContext,
    build_context,
    rooms_from_viewpoints,
)
from planner.config import AspConfig, PlannerConfig
from planner.core import Planner
from planner.frontier import classify_frontier
from planner.prior import load_prior
from protocol.messages import Intrinsics, Viewpoint, ViewpointSet

VOXEL = 0.05
ROOM = ((-3.0, -3.0), (3.0, 3.0))


def two_view_set(headings: tuple[float, ...] = (0.0, math.pi)) -> ViewpointSet:
    vps = [Viewpoint(vp_id=i, x=0.0, y=0.0, yaw_rad=h) for i, h in enumerate(headings)]
    return ViewpointSet(
        robot_id="r1",
        camera_height_m=1.0,
        camera_pitch_deg=-15.0,
        intrinsics=Intrinsics.from_fov(640, 480, 90.0),
        max_range_m=6.0,
        viewpoints=vps,
    )


def closed_room(hole: bool) -> np.ndarray:
    """A closed box room (floor, walls, ceiling); optionally a missing patch in the wall at x = -3."""
    pts = np.concatenate(
        [
            S.room_points(*ROOM, 2.6, VOXEL),
            S.plane_points(np.array([-3.0, -3.0, 2.6]), np.array([6.0, 0, 0]), np.array([0, 6.0, 0]), VOXEL),
        ]
    )
    if hole:
        on_wall = np.abs(pts[:, 0] + 3.0) < 1e-6
        in_patch = (np.abs(pts[:, 1]) < 1.0) & (pts[:, 2] > 0.4) & (pts[:, 2] < 1.8)
        pts = pts[~(on_wall & in_patch)]
    return pts


class StubSampler:
    """Fixed completions (what a sampler returned), to test the gain without the prior's randomness."""

    name = "stub"

    def __init__(self, completions: list[Completion]) -> None:
        self.completions = completions
        self.info = SamplerInfo()

    def sample(self, ctx: SceneContext, k: int, rng: np.random.Generator) -> list[Completion]:
        return self.completions[:k]


class TestFrontier:
    def test_closed_room_has_no_frontier_and_a_hole_has_edges(self) -> None:
        cfg = PlannerConfig().see
        closed = S.point_map(closed_room(False), VOXEL, counts=5.0)
        assert classify_frontier(closed.points, closed.counts, VOXEL, cfg).sum() == 0
        holed = S.point_map(closed_room(True), VOXEL, counts=5.0)
        f = classify_frontier(holed.points, holed.counts, VOXEL, cfg)
        edge = holed.points[f]
        assert f.sum() > 50
        assert np.all(np.abs(edge[:, 0] + 3.0) < 2 * VOXEL)  # only around the hole in the x = -3 wall

    def test_low_counts_are_frontier(self) -> None:
        pm = S.point_map(closed_room(False), VOXEL, counts=0.2)
        assert classify_frontier(pm.points, pm.counts, VOXEL, PlannerConfig().see).all()

    def test_empty(self) -> None:
        assert classify_frontier(np.zeros((0, 3)), None, VOXEL, PlannerConfig().see).shape == (0,)


class TestSee:
    def test_prefers_view_facing_frontier_over_observed_wall(self) -> None:
        planner = Planner(PlannerConfig(strategy="see"))
        pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
        state = S.robot_state("r1", 0.5, 0.5, math.pi / 2)
        goals = planner.plan(S.snapshot([]), pm, {"r1": (state, two_view_set())})
        assert len(goals) == 1
        g = goals[0]
        assert g.vp_id == 1 and g.yaw_rad == pytest.approx(math.pi)
        scores = planner.last_scores["r1"]
        assert scores[1] > 20 and scores[0] == 0
        assert g.strategy == "see" and "frontier" in g.reason

    def test_tie_goes_to_the_nearer_view(self) -> None:
        # Same view direction from two positions: equal frontier counts, the nearer one wins.
        pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
        vps = [
            Viewpoint(vp_id=0, x=0.6, y=0.0, yaw_rad=math.pi),
            Viewpoint(vp_id=1, x=0.0, y=0.0, yaw_rad=math.pi),
        ]
        vset = two_view_set().model_copy(update={"viewpoints": vps})
        state = S.robot_state("r1", -0.1, 0.9, math.pi / 2)
        planner = Planner(PlannerConfig(strategy="see"))
        g = planner.plan(S.snapshot([]), pm, {"r1": (state, vset)})[0]
        s = planner.last_scores["r1"]
        assert s[0] > 0 and s[1] > 0
        assert g.vp_id == (1 if s[1] >= 0.9 * s[0] else 0)

    def test_does_not_retake_a_view(self) -> None:
        pm = S.point_map(closed_room(True), VOXEL, counts=5.0)
        planner = Planner(PlannerConfig(strategy="see"))
        state = S.robot_state("r1", 0.0, 0.0, math.pi)  # already standing on viewpoint 1
        g = planner.plan(S.snapshot([]), pm, {"r1": (state, two_view_set())})[0]
        assert g.vp_id == 0


def half_observed_room() -> tuple[np.ndarray, S.PointMap]:
    pts = closed_room(False)
    pts = pts[pts[:, 0] > 0.0]  # only the +x half has been observed
    return pts, S.point_map(pts, VOXEL, counts=5.0)


class TestAsp:
    def config(self, **asp: object) -> PlannerConfig:
        return PlannerConfig(strategy="asp", asp=AspConfig(n_completions=2, n_jitter=1, **asp))

    def test_view_of_disputed_region_beats_view_of_mapped_space(self) -> None:
        _, pm = half_observed_room()
        comps = [Completion((HypObject("chair", xyz=(-2.0, 0.0, 0.45)),)), Completion(())]
        planner = Planner(self.config(), sampler=StubSampler(comps))
        state = S.robot_state("r1", 0.5, 0.5, math.pi / 2)
        g = planner.plan(S.snapshot([]), pm, {"r1": (state, two_view_set())})[0]
        gains = planner.last_scores["r1"]
        # One completion has a chair there, the other not: exactly 1 bit for the view facing it.
        assert gains[1] == pytest.approx(1.0)
        assert gains[0] == pytest.approx(0.0)
        assert g.vp_id == 1 and g.expected_gain == pytest.approx(1.0) and g.strategy == "asp"

    def test_agreeing_completions_give_no_gain(self) -> None:
        _, pm = half_observed_room()
        chair = HypObject("chair", xyz=(-2.0, 0.0, 0.45))
        planner = Planner(self.config(), sampler=StubSampler([Completion((chair,)), Completion((chair,))]))
        state = S.robot_state("r1", 0.5, 0.5, math.pi / 2)
        g = planner.plan(S.snapshot([]), pm, {"r1": (state, two_view_set())})[0]
        assert np.all(planner.last_scores["r1"] < 1e-9)
        assert "fallback" in g.reason  # no semantic gain left: the geometric score decides

    def test_hypothesis_a_past_view_would_have_seen_is_ruled_out(self) -> None:
        _, pm = half_observed_room()
        comps = [Completion((HypObject("chair", xyz=(-2.0, 0.0, 0.45)),)), Completion(())]
        planner = Planner(self.config(detect_reject=1.0), sampler=StubSampler(comps))
        vset = two_view_set()
        # A past view from the origin facing -x saw that spot and found no chair.
        planner.record_view(S.robot_state("r1", 0.2, 0.0, math.pi).T_world_cam, vset.intrinsics)
        state = S.robot_state("r1", 0.5, 0.5, math.pi / 2)
        planner.plan(S.snapshot([]), pm, {"r1": (state, vset)})
        assert planner.info.n_hypotheses == 0

    def test_a_place_looked_at_again_and_again_is_ruled_out_behind_stray_points(self) -> None:
        pts, _ = half_observed_room()
        g = np.arange(0.0, 1.0001, VOXEL)
        blob = np.stack(np.meshgrid(-1.1 + 0.2 * g, -0.4 + 0.8 * g, 0.2 + 0.9 * g, indexing="ij"), -1).reshape(-1, 3)
        pm = S.point_map(np.concatenate([pts, blob]), VOXEL, counts=5.0)  # stray estimated depth before the chair
        comps = [Completion((HypObject("chair", xyz=(-2.0, 0.0, 0.45)),)), Completion(())]
        vset = two_view_set()

        def left(max_attempts: int) -> int:
            planner = Planner(self.config(detect_reject=1.0, max_attempts=max_attempts), sampler=StubSampler(comps))
            for y in (-0.1, 0.1):  # two past views from beside the origin, facing the chair's place
                planner.record_view(S.robot_state("r1", 0.2, y, math.pi).T_world_cam, vset.intrinsics)
            planner.plan(S.snapshot([]), pm, {"r1": (S.robot_state("r1", 0.5, 0.5, math.pi / 2), vset)})
            return planner.info.n_hypotheses

        assert left(0) > 0  # hidden behind the stray points from both views: never ruled out
        assert left(3) > 0  # two attempts are not three
        assert left(2) == 0

    def test_small_object_needs_a_close_view(self) -> None:
        _, pm = half_observed_room()
        comps = [Completion((HypObject("cup", xyz=(-2.5, 0.0, 0.8)),)), Completion(())]
        headings = (math.pi, math.pi)
        vps = [
            Viewpoint(vp_id=0, x=2.0, y=0.0, yaw_rad=headings[0]),
            Viewpoint(vp_id=1, x=-1.2, y=0.0, yaw_rad=headings[1]),
        ]
        vset = two_view_set().model_copy(update={"viewpoints": vps})
        planner = Planner(self.config(), sampler=StubSampler(comps))
        state = S.robot_state("r1", 2.5, 2.5, math.pi / 2)
        g = planner.plan(S.snapshot([]), pm, {"r1": (state, vset)})[0]
        gains = planner.last_scores["r1"]
        assert gains[0] == pytest.approx(0.0)  # 4.5 m away: a cup is a few pixels
        assert gains[1] == pytest.approx(1.0)
        assert g.vp_id == 1

    def test_prior_sampler_end_to_end_prefers_unexplored_room(self) -> None:
        w = S.apartment(0)
        name = S.room_namer(w["rooms"])
        vset = S.grid_viewpoints("r1", (0.6, 0.6), (9.4, 8.4), spacing_m=1.0, room_of=name)
        vset = vset.model_copy(update={"viewpoints": [v for v in vset.viewpoints if v.room]})
        pts = w["points"]
        living = (pts[:, 0] < 6) & (pts[:, 1] < 5)
        pm = S.point_map(pts[living], VOXEL)
        nodes = [n for n in w["nodes"] if n.centroid[0] < 6 and n.centroid[1] < 5]
        planner = Planner(PlannerConfig(strategy="asp", seed=1))
        state = S.robot_state("r1", 3.0, 2.5, 0.0)
        g = planner.plan(S.snapshot(nodes), pm, {"r1": (state, vset)})[0]
        assert planner.info.n_hypotheses > 0
        assert g.expected_gain > 0.5
        # The living room was seen: the best view looks into the kitchen or the bedroom.
        assert name(g.x, g.y) in ("kitchen", "bedroom_1")
        assert planner.info.decision_s < 5.0


class TestMultiRobot:
    @pytest.mark.parametrize("strategy", ["see", "asp"])
    def test_distinct_goals(self, strategy: str) -> None:
        w = S.apartment(0)
        name = S.room_namer(w["rooms"])
        pts = w["points"]
        pm = S.point_map(pts[(pts[:, 0] < 6) & (pts[:, 1] < 5)], VOXEL)
        planner = Planner(PlannerConfig(strategy=strategy, seed=2))
        robots = {}
        for rid in ("r1", "r2"):
            vset = S.grid_viewpoints(rid, (0.6, 0.6), (9.4, 8.4), spacing_m=1.0, room_of=name)
            vset = vset.model_copy(update={"viewpoints": [v for v in vset.viewpoints if v.room]})
            robots[rid] = (S.robot_state(rid, 3.0, 2.5, 0.0), vset)
        goals = planner.plan(S.snapshot(w["nodes"][:2]), pm, robots)
        assert {g.robot_id for g in goals} == {"r1", "r2"}
        a, b = goals
        assert math.hypot(a.x - b.x, a.y - b.y) >= planner.config.claim_radius_m
        # A later re-plan of r1 alone keeps r2's goal claimed.
        g1 = planner.plan(S.snapshot(w["nodes"][:2]), pm, {"r1": robots["r1"]})[0]
        assert math.hypot(g1.x - b.x, g1.y - b.y) >= planner.config.claim_radius_m


class TestPrior:
    def test_loads_and_canonicalises(self) -> None:
        prior = load_prior()
        assert prior.canonical_label("Wooden Dining Chair") == "chair"
        assert prior.canonical_label("couch") == "sofa"
        assert prior.canonical_label("TV") == "television"
        assert prior.canonical_label("glowing orb") == "glowing orb"
        assert prior.room_kind("bedroom_2") == "bedroom"
        assert prior.room_kind("Living Room") == "living_room"
        assert prior.room_kind("room_7") is None

    def test_room_kind_inferred_from_objects(self) -> None:
        prior = load_prior()
        xy = np.array([[0.0, 0.0], [3.0, 3.0]])
        rooms = rooms_from_viewpoints([None, None], xy, prior)
        ctx = build_context([S.node("n1", "double bed", (1.0, 1.0, 0.3), (1.6, 2.0, 0.6))], [], rooms, prior)
        comps = PriorSampler(prior).sample(ctx, 16, np.random.default_rng(0))
        labels = [o.label for c in comps for o in c.objects]
        assert labels.count("nightstand") >= 8  # a bed makes this a bedroom: nightstands are likely
        assert labels.count("refrigerator") <= 2
        assert (
            "bed" not in [o.label for c in comps for o in c.objects if o.parent is None]
            or labels.count("bed") < 16
        )  # the seen bed satisfies most draws
        assert any(o.parent == "n1" and o.label == "pillow" for c in comps for o in c.objects)

    def test_bad_file(self, tmp_path) -> None:
        p = tmp_path / "p.json"
        p.write_text('{"format": "something-else", "version": 1}')
        with pytest.raises(ValueError):
            load_prior(p)


class TestVisibility:
    def test_frustum(self) -> None:
        from planner.geometry import project_many
        from protocol.poses import camera_pose_from_base

        T = camera_pose_from_base(0.0, 0.0, 0.0, 1.0, 0.0)[None]
        K = Intrinsics.from_fov(640, 480, 90.0).K()
        pts = np.array([[2.0, 0.0, 1.0], [-2.0, 0.0, 1.0], [2.0, 2.5, 1.0], [7.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
        ok, z = project_many(T, K, 640, 480, pts, near_m=0.2, far_m=6.0)
        assert ok[0].tolist() == [True, False, False, False, False]
        assert z[0, 0] == pytest.approx(2.0)

    def test_wall_occludes_what_is_behind_it(self) -> None:
        from planner.config import VisibilityConfig
        from planner.geometry import Panoramas

        wall = S.plane_points(np.array([2.0, -1.5, 0.0]), np.array([0, 3.0, 0]), np.array([0, 0, 2.5]), 0.05)
        pano = Panoramas(np.array([[0.0, 0.0, 1.0]]), wall, VisibilityConfig())
        vis = pano.unoccluded(np.array([[1.0, 0.0, 1.0], [3.0, 0.0, 1.0], [2.0, 0.0, 1.0], [3.0, 3.0, 1.0]]))[
            0
        ]
        assert vis.tolist() == [True, False, True, True]  # in front, behind, on the wall, beside it

    def test_sparse_wall_still_occludes(self) -> None:
        from planner.config import VisibilityConfig
        from planner.geometry import Panoramas

        wall = S.plane_points(np.array([4.0, -2.0, 0.0]), np.array([0, 4.0, 0]), np.array([0, 0, 2.5]), 0.2)
        pano = Panoramas(np.array([[0.0, 0.0, 1.0]]), wall, VisibilityConfig())
        behind = np.column_stack([np.full(20, 5.0), np.linspace(-1, 1, 20), np.full(20, 1.0)])
        assert not pano.unoccluded(behind)[0].any()


class TestRealize:
    def test_items_stand_on_their_new_parent_and_jitter_makes_samples(self) -> None:
        from planner.hypotheses import realize

        prior = load_prior()
        xy = np.array([[0.0, 0.0], [4.0, 4.0]])
        rooms = rooms_from_viewpoints(["kitchen", "kitchen"], xy, prior)
        ctx = build_context([], [], rooms, prior)
        comp = Completion((HypObject("dining table", "kitchen"), HypObject("mug", "kitchen", "new:0")))
        nothing = np.zeros
        h = realize(
            [comp, Completion(())],
            ctx,
            prior,
            n_jitter=3,
            jitter_m=0.0,
            proposals=4,
            detect_reject=1.0,
            seen=lambda t, s: nothing(t.shape[0], bool),
            floor_seen=lambda xy: nothing(xy.shape[0], bool),
            rng=np.random.default_rng(0),
        )
        assert h.labels == ("cup", "dining table")  # labels are canonicalised ("mug" -> "cup")
        assert h.size == 6 and sorted(set(h.sample_idx.tolist())) == [
            0,
            1,
            2,
        ]  # 2 objects x 3 jitters, comp 0
        table = h.xyz[h.label_idx == 1][0]
        cup = h.xyz[h.label_idx == 0][0]
        assert cup[2] == pytest.approx(0.75 + 0.05)  # on the table top (catalogue heights)
        assert np.all(np.abs(cup[:2] - table[:2]) <= np.array([0.8, 0.45]))
        assert np.all((table[:2] >= rooms[0].xy_min) & (table[:2] <= rooms[0].xy_max))

    def test_everything_seen_drops_the_object(self) -> None:
        from planner.hypotheses import realize

        prior = load_prior()
        rooms = rooms_from_viewpoints(["kitchen", "kitchen"], np.array([[0.0, 0.0], [4.0, 4.0]]), prior)
        ctx = build_context([], [], rooms, prior)
        h = realize(
            [Completion((HypObject("refrigerator", "kitchen"),))],
            ctx,
            prior,
            n_jitter=1,
            jitter_m=0.0,
            proposals=5,
            detect_reject=1.0,
            seen=lambda t, s: np.ones(t.shape[0], bool),
            floor_seen=lambda xy: np.zeros(xy.shape[0], bool),
            rng=np.random.default_rng(0),
        )
        assert h.size == 0 and h.dropped == 1
