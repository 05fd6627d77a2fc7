"""Pure goal and budget logic of the robot agent (no I/O)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol.messages import NbvGoal


def goal_problem(goal: NbvGoal, robot_id: str) -> str | None:
    """Why a decoded goal cannot be pursued by this robot, or ``None`` when it is well-formed."""
    if goal.robot_id != robot_id:
        return f"goal {goal.goal_id!r} is addressed to robot {goal.robot_id!r}, not {robot_id!r}"
    if not all(math.isfinite(v) for v in (goal.x, goal.y, goal.yaw_rad)):
        return f"goal {goal.goal_id!r} has a non-finite pose"
    if abs(goal.x) > 1e4 or abs(goal.y) > 1e4:
        return f"goal {goal.goal_id!r} lies absurdly far away ({goal.x:g}, {goal.y:g})"
    return None


@dataclass(frozen=True)
class Budget:
    """Exploration budget: metres driven and/or goals reached (``None``: unlimited)."""

    max_distance_m: float | None = None
    max_steps: int | None = None

    def exhausted(self, distance_m: float, steps: int) -> str | None:
        """The reason the budget is used up, or ``None``."""
        if self.max_distance_m is not None and distance_m >= self.max_distance_m:
            return f"distance budget of {self.max_distance_m:g} m used ({distance_m:.2f} m driven)"
        if self.max_steps is not None and steps >= self.max_steps:
            return f"step budget of {self.max_steps} goals used"
        return None
