"""The planner's goals on a fixed synthetic exploration are the ones the dense (pre-issue-14) implementation chose.

``walk`` drives one or two robots through the synthetic apartment (planner.synthetic): each decision sees
the map points and graph nodes within 4.5 m of every place a robot has stood, the robots move to their
goals, and the next decision follows. ``GOLDEN`` holds the goals (viewpoint id, expected gain) the dense
implementation (one (C, T) frustum projection per call, every completion row's entropy) chose on it: the
culled and filtered implementation must choose the same ones with the same gains. Regenerate only for a
deliberate change of behaviour: ``python -m tests.planner.test_planner_same_goals``.
"""

from __future__ import annotations

import numpy as np
import pytest

from planner import synthetic as S
from planner.config import PlannerConfig
from planner.core import Planner
from protocol.messages import RobotState, ViewpointSet

SEEN_M = 4.5


def walk(strategy: str, n_robots: int, steps: int) -> list[tuple[str, int, float]]:
    """(robot, viewpoint id, expected gain) of every goal of a ``steps``-decision synthetic exploration."""
    w = S.apartment(0)
    name = S.room_namer(w["rooms"])
    base = S.grid_viewpoints("r0", (0.3, 0.3), (9.7, 8.7), spacing_m=0.5, room_of=name)
    base = base.model_copy(update={"viewpoints": [v for v in base.viewpoints if v.room]})
    vsets = {f"r{k}": base.model_copy(update={"robot_id": f"r{k}"}) for k in range(n_robots)}
    pose = {f"r{k}": (2.0 + 0.6 * k, 2.0, 0.5 * k) for k in range(n_robots)}
    stood: list[tuple[float, float]] = [p[:2] for p in pose.values()]
    planner = Planner(PlannerConfig(strategy=strategy, seed=3))  # type: ignore[arg-type]
    pts = w["points"]
    out: list[tuple[str, int, float]] = []
    for step in range(steps):
        near = np.min(np.hypot(pts[:, None, 0] - np.array(stood)[None, :, 0],
                               pts[:, None, 1] - np.array(stood)[None, :, 1]), axis=1) <= SEEN_M
        pm = S.point_map(pts[near], 0.05, counts=2.0)
        nodes = [n for n in w["nodes"]
                 if min(np.hypot(n.centroid[0] - x, n.centroid[1] - y) for x, y in stood) <= SEEN_M]
        robots: dict[str, tuple[RobotState, ViewpointSet]] = {
            rid: (S.robot_state(rid, *pose[rid]), vsets[rid]) for rid in sorted(vsets)
        }
        for g in planner.plan(S.snapshot(nodes, version=step + 1), pm, robots):
            out.append((g.robot_id, int(g.vp_id or 0), round(float(g.expected_gain), 9)))
            pose[g.robot_id] = (g.x, g.y, g.yaw_rad)
            stood.append((g.x, g.y))
    return out


GOLDEN: dict[tuple[str, int], list[tuple[str, int, float]]] = {
    ('see', 1): [('r0', 296, 218.0), ('r0', 304, 215.0), ('r0', 312, 213.0), ('r0', 818, 226.0), ('r0', 2389, 322.0)],
    ('asp', 1): [('r0', 1696, 30.922593339), ('r0', 2350, 28.550146685), ('r0', 915, 22.953274881),
                 ('r0', 462, 13.493573037), ('r0', 1655, 13.048524405)],
    ('see', 2): [('r0', 682, 239.0), ('r1', 1710, 208.0), ('r0', 1360, 233.0), ('r1', 232, 213.0), ('r0', 2214, 367.0),
                 ('r1', 746, 216.0), ('r0', 2078, 241.0), ('r1', 882, 207.0), ('r0', 1290, 190.0), ('r1', 894, 133.0)],
    ('asp', 2): [('r0', 1696, 31.058618437), ('r1', 218, 21.530130226), ('r0', 2199, 30.037550327),
                 ('r1', 462, 13.665641595), ('r0', 2197, 15.934262042), ('r1', 724, 9.694912842),
                 ('r0', 2078, 14.791888753), ('r1', 368, 9.448203215), ('r0', 1655, 6.607605578),
                 ('r1', 1348, 7.729481795)],
}


@pytest.mark.parametrize("strategy,n_robots", [("see", 1), ("asp", 1), ("see", 2), ("asp", 2)])
def test_same_goals_as_the_dense_implementation(strategy: str, n_robots: int) -> None:
    got = walk(strategy, n_robots, 5)
    want = GOLDEN[(strategy, n_robots)]
    assert [(r, v) for r, v, _ in got] == [(r, v) for r, v, _ in want]
    np.testing.assert_allclose([g for *_, g in got], [g for *_, g in want], rtol=1e-9, atol=1e-9)


if __name__ == "__main__":
    for key in [("see", 1), ("asp", 1), ("see", 2), ("asp", 2)]:
        print(f"    {key!r}: {walk(key[0], key[1], 5)!r},")
