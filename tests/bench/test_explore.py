"""``argus explore``: closed-loop episodes in-process on a small simulated scene."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.explore import (
    Episode,
    decision_stats,
    main,
    markdown,
    reach,
    recall_at_team_steps,
    report_steps,
    run_episode,
    start_pose,
    summarize,
    team_starts,
)
from protocol.messages import Viewpoint


def test_start_pose_is_deterministic_and_navigable() -> None:
    vps = [Viewpoint(vp_id=i, x=float(i % 5), y=float(i // 5), yaw_rad=0.0) for i in range(25)]
    a = start_pose(vps, seed=3, start_index=1)
    assert a == start_pose(vps, seed=3, start_index=1)
    assert (a[0], a[1]) in {(v.x, v.y) for v in vps}
    assert {start_pose(vps, 3, k)[:2] for k in range(6)} != {a[:2]}  # different starts differ


def test_an_episode_is_its_parameters_with_keywords_written_over() -> None:
    """run_episode(Episode(...), k=v) runs the same episode as run_episode(all keywords); an unknown keyword is
    refused before anything runs."""
    kw: dict[str, Any] = dict(family="furnished_room", seed=1, strategy="see", steps=0, start_index=0)
    base = Episode(family="furnished_room", seed=1, strategy="asp", steps=0)
    a, b = run_episode(**kw), run_episode(base, strategy="see")
    for ep in (a, b):
        del ep["seconds"]
        for r in ep["steps"]:
            del r["decision_s"], r["decision_cpu_s"]
    assert a == b and a["strategy"] == "see" and len(a["steps"]) == 1
    with pytest.raises(TypeError, match="stepz"):
        run_episode(base, stepz=3)


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["see", "asp"])
def test_episode_records_every_step(strategy: str) -> None:
    ep = run_episode(family="furnished_room", seed=1, strategy=strategy, steps=3, start_index=0)
    steps = ep["steps"]
    assert [s["step"] for s in steps] == [0, 1, 2, 3]
    assert ep["n_true"] > 0 and ep["n_candidates"] > 0
    assert steps[0]["distance_m"] == 0.0 and steps[0]["goal"] is None
    assert all(0.0 <= s["recall"] <= 1.0 for s in steps)
    dist = [s["distance_m"] for s in steps]
    assert dist == sorted(dist)
    assert any(s["goal"] is not None for s in steps[1:])
    assert steps[-1]["n_nodes"] >= 1
    assert all(s["reason"].startswith(("see", "asp")) for s in steps[1:] if s["goal"] is not None)


@pytest.mark.slow
def test_cli_writes_json(tmp_path: Path) -> None:
    out = tmp_path / "ex.json"
    rc = main(
        [
            "--strategy",
            "see",
            "--steps",
            "1",
            "--starts",
            "1",
            "--family",
            "furnished_room",
            "--seeds",
            "2",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert rc == 0
    data = json.loads(out.read_text())
    assert len(data["episodes"]) == 1 and len(data["episodes"][0]["steps"]) == 2
    row = data["summary"][0]
    assert row["strategy"] == "see" and row["episodes"] == 1


def test_summarize_mean_and_std() -> None:
    def ep(strategy: str, recalls: list[float]) -> dict:
        return {
            "strategy": strategy,
            "external_cameras": 0,
            "n_true": 10,
            "steps": [
                {"step": i, "n_nodes": i, "recall": r, "distance_m": float(i), "decision_s": 0.1}
                for i, r in enumerate(recalls)
            ],
        }

    rows = summarize([ep("asp", [0.0, 0.4]), ep("asp", [0.0, 0.6]), ep("see", [0.0, 0.2])], (0, 1))
    asp = next(r for r in rows if r["strategy"] == "asp")
    assert asp["episodes"] == 2
    assert asp["recall@1"] == pytest.approx([0.5, 0.1])
    assert asp["n_nodes@0"] == [0.0, 0.0]


def test_decision_stats_percentiles_and_cpu() -> None:
    """Wall mean / p50 / p95 / max over the steps after the first, CPU mean / p95 where every step has it; the
    decide column shows them (older records without CPU: wall only)."""
    steps = [{"step": 0, "decision_s": 0.0, "decision_cpu_s": 0.0}] + [
        {"step": i, "decision_s": float(i), "decision_cpu_s": 0.5 * i} for i in range(1, 21)
    ]
    st = decision_stats([{"steps": steps}])
    assert st["decision_s_mean"] == pytest.approx(10.5)
    assert st["decision_s_p50"] == pytest.approx(10.5)
    assert st["decision_s_p95"] == pytest.approx(19.05)
    assert st["decision_s_max"] == 20.0
    assert st["decision_cpu_s_mean"] == pytest.approx(5.25)
    assert st["decision_cpu_s_p95"] == pytest.approx(9.525)
    old = decision_stats([{"steps": [{k: v for k, v in r.items() if k != "decision_cpu_s"} for r in steps]}])
    assert old["decision_cpu_s_mean"] is None and old["decision_s_p95"] == pytest.approx(19.05)


def test_mapper_overrides_reach_the_mapper() -> None:
    """RGB-only geometry: a robot's first frame has no stereo partner, so it maps nothing, unless single-view
    floor geometry is switched on for robot (prior-posed) frames."""
    kw = dict(family="furnished_room", seed=1, strategy="see", steps=0, start_index=0, geometry="mvs")
    plain = run_episode(**kw)  # type: ignore[arg-type]
    single = run_episode(**kw, mapper_overrides={"single_view": {"untrusted_poses": True}})  # type: ignore[arg-type]
    assert plain["steps"][0]["n_nodes"] == 0
    assert single["steps"][0]["n_nodes"] > 0


def test_goal_capture_gives_the_arrival_view_stereo_partners() -> None:
    """With --goal-capture, each goal adds views from the camera moved sideways; the view selection the mapper
    uses accepts them as stereo sources for the arrival view, and the sidesteps count in the distance."""
    from mapper.config import KeyframeConfig
    from mapper.core import MapperCore
    from mapper.keyframes import KeyframeStore

    seen: list[Any] = []
    orig = MapperCore.ingest

    def spy(self: MapperCore, view: Any, force_keyframe: bool = False) -> Any:
        seen.append(view)
        return orig(self, view, force_keyframe)

    kw = dict(family="furnished_room", seed=1, strategy="see", steps=1, start_index=0)
    MapperCore.ingest = spy  # type: ignore[method-assign]
    try:
        plain = run_episode(**kw)  # type: ignore[arg-type]
        n_plain = len(seen)
        seen.clear()
        captured = run_episode(**kw, goal_capture_m=0.3)  # type: ignore[arg-type]
    finally:
        MapperCore.ingest = orig  # type: ignore[method-assign]
    extra = len(seen) - n_plain
    assert extra in (1, 2)  # one sidestep may be blocked by a wall or furniture
    arrival, sides = seen[-1], seen[-1 - extra:-1]
    for v in sides:
        assert np.linalg.norm(v.T_world_cam[:3, 3] - arrival.T_world_cam[:3, 3]) == pytest.approx(0.3, abs=1e-6)
    store = KeyframeStore(KeyframeConfig())
    for v in sides:
        store.add(v)
    assert {v.key for v in store.neighbours(arrival, 2.5)} == {v.key for v in sides}
    assert captured["steps"][1]["distance_m"] == pytest.approx(plain["steps"][1]["distance_m"] + 0.6 * extra, abs=1e-3)


def test_a_calibrated_external_camera_maps_at_step_0_with_rgb_only_geometry() -> None:
    """The external camera's pose is surveyed: RGB-only geometry places its objects from the floor plane at
    step 0 (single-view), as the mapper does for a calibrated edge camera."""
    kw = dict(family="furnished_room", seed=1, strategy="see", steps=0, start_index=0, geometry="mvs")
    ext = run_episode(**kw, external_cameras=1)  # type: ignore[arg-type]
    assert ext["steps"][0]["n_nodes"] > 0


def test_team_starts_dock_the_robots_near_the_first() -> None:
    xy = np.array([[0.0, 0.0], [0.3, 0.0], [0.6, 0.0], [1.2, 0.0], [0.0, 0.7], [5.0, 5.0]])
    geo = np.array([0.0, 0.3, 0.6, 1.2, np.inf, 7.0])  # (0, 0.7) is across a wall: unreachable from the dock
    starts = team_starts((0.0, 0.0, 0.5), xy, geo, 3, gap_m=0.6)
    assert starts[0] == (0.0, 0.0, 0.5)
    assert [s[:2] for s in starts[1:]] == [(0.6, 0.0), (1.2, 0.0)]  # nearest along the floor, >= 0.6 m apart
    yaws = [s[2] for s in starts]
    assert yaws[1] == pytest.approx(0.5 + 2 * np.pi / 3) and yaws[2] == pytest.approx(0.5 + 4 * np.pi / 3 - 2 * np.pi)
    assert team_starts((0.0, 0.0, 0.5), xy, geo, 1) == [(0.0, 0.0, 0.5)]
    with pytest.raises(ValueError, match="robot 2"):
        team_starts((0.0, 0.0, 0.0), xy[:3], geo[:3], 3, gap_m=0.6)


def _team_ep(strategy: str, recalls: list[float], robots: int, per_step_m: float = 1.0) -> dict:
    return {
        "strategy": strategy,
        "external_cameras": 0,
        "robots": robots,
        "n_true": 10,
        "steps": [
            {
                "step": i,
                "team_steps": i * robots,
                "n_nodes": i,
                "recall": r,
                "distance_m": per_step_m * i * robots,
                "decision_s": 0.1,
                "robots": {f"robot{k}": {"distance_m": per_step_m * i, "frames": 1 + i} for k in range(robots)},
            }
            for i, r in enumerate(recalls)
        ],
    }


def test_team_figures_count_every_robots_steps() -> None:
    two = _team_ep("asp", [0.1, 0.4, 0.6, 0.85], robots=2)
    assert recall_at_team_steps(two, 2) == 0.4 and recall_at_team_steps(two, 3) == 0.4
    assert recall_at_team_steps(two, 6) == 0.85 and recall_at_team_steps(two, 7) is None
    assert reach(two, 0.5) == {"wall": 2, "team": 4, "metres": 4.0}
    assert reach(two, 0.8) == {"wall": 3, "team": 6, "metres": 6.0}
    assert reach(two, 0.9) is None
    one = _team_ep("asp", [0.1, 0.3, 0.5, 0.6], robots=1)
    rows = summarize([one, two], (0, 2, 3))
    r1, r2 = sorted(rows, key=lambda r: r["robots"])
    assert (r1["robots"], r2["robots"]) == (1, 2)
    assert r2["recall@2"] == pytest.approx([0.6, 0.0]) and r2["recall@team2"] == pytest.approx([0.4, 0.0])
    assert r1["recall@team2"] == r1["recall@2"]  # one robot: team steps are wall steps
    assert r2["recall@team3"] is not None and r1["to80%"]["runs"] == [None]
    assert r2["to80%"] == {"mean_curve_wall": 3, "runs": [{"wall": 3, "team": 6, "metres": 6.0}]}
    assert r2["robot_distance_m"] == {"robot0": 3.0, "robot1": 3.0} and r2["robot_frames"]["robot1"] == 4.0
    md = markdown(rows, (0, 2, 3))
    assert "ASP x2 robots" in md and "1/1: 6" in md and "0/1" in md


def test_records_without_per_robot_counts_still_summarise() -> None:
    """JSONs written before the team counts (one robot, no ``robots`` / ``team_steps`` per step)."""
    old = _team_ep("see", [0.1, 0.6], robots=1, per_step_m=2.0)
    del old["robots"]
    for rec in old["steps"]:
        del rec["robots"], rec["team_steps"]
    (row,) = summarize([old], (0, 1))
    assert row["robots"] == 1 and row["recall@team1"] == pytest.approx([0.6, 0.0])
    assert row["robot_distance_m"] == {"robot0": 2.0} and "robot_frames" not in row


def test_report_steps_include_the_last_step() -> None:
    assert report_steps(30) == (0, 10, 20, 30)
    assert report_steps(3) == (0, 3)
    assert report_steps(15) == (0, 10, 15)


def test_report_rewrites_tables_and_plot_from_episodes(tmp_path: Path) -> None:
    src, src1 = tmp_path / "two.json", tmp_path / "one.json"
    src.write_text(json.dumps({"episodes": [_team_ep("see", [0.1, 0.5, 0.9], 2)]}))
    src1.write_text(json.dumps({"episodes": [_team_ep("see", [0.1, 0.6], 1)]}))
    out = tmp_path / "again.json"
    assert main(["--report", str(src), str(src1), "--out", str(out), "--steps", "2"]) == 0
    assert "SEE x2 robots" in out.with_suffix(".md").read_text()
    old = json.loads(out.read_text())["summary"]
    assert next(r for r in old if r["robots"] == 2)["robot_frames"] == {"robot0": 3.0, "robot1": 3.0}
    assert out.with_suffix(".png").stat().st_size > 1000
    assert len(json.loads(out.read_text())["summary"]) == 2
    (tmp_path / "bad.json").write_text("{}")
    assert main(["--report", str(tmp_path / "bad.json")]) == 2


def test_two_robots_both_move_and_both_map() -> None:
    """A short bounded 2-robot episode: each robot drives to its own goals (kept apart by the planner's
    claims), each gives the mapper its frames, and the team counts both robots' steps and metres."""
    from mapper.core import MapperCore

    sources: list[str] = []
    orig = MapperCore.ingest

    def spy(self: MapperCore, view: Any, force_keyframe: bool = False) -> Any:
        sources.append(view.source_id)
        return orig(self, view, force_keyframe)

    MapperCore.ingest = spy  # type: ignore[method-assign]
    try:
        ep = run_episode(family="furnished_room", seed=1, strategy="see", steps=2, start_index=0, robots=2)
    finally:
        MapperCore.ingest = orig  # type: ignore[method-assign]
    assert ep["robots"] == 2 and len(ep["starts"]) == 2
    (x0, y0, _), (x1, y1, _) = ep["starts"]
    assert np.hypot(x1 - x0, y1 - y0) >= 0.6
    assert sources.count("robot0") == 3 and sources.count("robot1") == 3  # start view + one per step each
    last = ep["steps"][-1]
    assert [s["team_steps"] for s in ep["steps"]] == [0, 2, 4]
    per = last["robots"]
    assert per["robot0"]["distance_m"] > 0 and per["robot1"]["distance_m"] > 0
    assert per["robot0"]["frames"] == 3 and per["robot1"]["frames"] == 3
    assert last["distance_m"] == pytest.approx(per["robot0"]["distance_m"] + per["robot1"]["distance_m"], abs=3e-3)
    for s in ep["steps"][1:]:
        g0, g1 = s["robots"]["robot0"]["goal"], s["robots"]["robot1"]["goal"]
        assert g0 is not None and g1 is not None
        assert np.hypot(g0[0] - g1[0], g0[1] - g1[1]) >= 1.0  # planner.claim_radius_m
