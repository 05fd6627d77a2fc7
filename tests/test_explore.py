"""``argus explore``: closed-loop episodes in-process on a small simulated scene."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.explore import main, run_episode, start_pose, summarize
from protocol.messages import Viewpoint


def test_start_pose_is_deterministic_and_navigable() -> None:
    vps = [Viewpoint(vp_id=i, x=float(i % 5), y=float(i // 5), yaw_rad=0.0) for i in range(25)]
    a = start_pose(vps, seed=3, start_index=1)
    assert a == start_pose(vps, seed=3, start_index=1)
    assert (a[0], a[1]) in {(v.x, v.y) for v in vps}
    assert {start_pose(vps, 3, k)[:2] for k in range(6)} != {a[:2]}  # different starts differ


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
