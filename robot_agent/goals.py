"""Pure goal and budget logic of the robot agent (no I/O): reading goal payloads, judging goals,
the exploration budget, the rate limit on published refusals and the one-slot goal mailbox."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from typing import Any

import msgpack
from pydantic import ValidationError

from protocol.codec import DecodeError, decode
from protocol.messages import NbvGoal, PlainGoal


def goal_problem(goal: NbvGoal, robot_id: str) -> str | None:
    """Why a decoded goal cannot be pursued by this robot, or ``None`` when it is well-formed."""
    if goal.robot_id != robot_id:
        return f"goal {goal.goal_id!r} is addressed to robot {goal.robot_id!r}, not {robot_id!r}"
    if not all(math.isfinite(v) for v in (goal.x, goal.y, goal.yaw_rad)):
        return f"goal {goal.goal_id!r} has a non-finite pose"
    if abs(goal.x) > 1e4 or abs(goal.y) > 1e4:
        return f"goal {goal.goal_id!r} lies absurdly far away ({goal.x:g}, {goal.y:g})"
    return None


def capture_waypoints(x: float, y: float, yaw_rad: float, lateral_m: float) -> list[tuple[float, float, float]]:
    """The goal capture: the poses ``lateral_m`` to the left and to the right of a goal, facing the goal's
    heading (the camera looks along ``yaw_rad``, so a sidestep is a baseline across its view), then the
    goal itself. Empty when ``lateral_m`` is 0."""
    if lateral_m <= 0:
        return []
    lx, ly = -math.sin(yaw_rad) * lateral_m, math.cos(yaw_rad) * lateral_m
    return [(x + lx, y + ly, yaw_rad), (x - lx, y - ly, yaw_rad), (x, y, yaw_rad)]


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


MAX_GOAL_BYTES = 64 * 1024
"""Larger goal payloads are refused unread."""


class GoalRefused(ValueError):
    """A goal payload that cannot be read as a goal; ``goal_id`` when one could still be made out."""

    def __init__(self, reason: str, goal_id: str | None = None) -> None:
        super().__init__(reason)
        self.reason, self.goal_id = reason, goal_id


def _validation_reason(e: ValidationError, limit: int = 4) -> str:
    errs = e.errors()
    parts = [f"{'.'.join(str(p) for p in err['loc']) or 'goal'}: {err['msg']}" for err in errs[:limit]]
    more = f" (+{len(errs) - limit} more)" if len(errs) > limit else ""
    return "; ".join(parts) + more


def _goal_id_of(body: Any) -> str | None:
    """The ``goal_id`` a refused payload carried, if it is a usable string (to echo it back)."""
    gid = body.get("goal_id") if isinstance(body, dict) else None
    return gid if isinstance(gid, str) and 0 < len(gid) <= 128 else None


def plain_to_goal(plain: PlainGoal, default_id: str, stamp_ns: int) -> NbvGoal:
    """The NbvGoal of a plain goal (``default_id`` when it has no ``goal_id``)."""
    return NbvGoal(
        goal_id=plain.goal_id or default_id, robot_id=plain.robot_id, stamp_ns=stamp_ns, x=plain.x, y=plain.y,
        yaw_rad=plain.yaw_rad, vp_id=plain.vp_id, strategy="plain", reason="plain goal",
    )


def parse_goal(data: bytes, default_id: str, stamp_ns: int) -> tuple[NbvGoal, str]:
    """Read a goal payload: an Argus ``nbv_goal`` envelope, or a plain JSON object / msgpack map.

    Returns ``(goal, form)`` with form ``envelope``, ``json`` or ``msgpack``; raises :class:`GoalRefused`
    with a one-line reason otherwise. Plain goals are validated as :class:`PlainGoal`.
    """
    if len(data) > MAX_GOAL_BYTES:
        raise GoalRefused(f"goal payload of {len(data)} bytes exceeds {MAX_GOAL_BYTES}")
    if data.lstrip()[:1] in (b"{", b"["):  # JSON (0x7b and 0x5b are msgpack ints, never a goal)
        try:
            body, form = json.loads(data.decode("utf-8")), "json"
        except (UnicodeDecodeError, ValueError) as e:
            raise GoalRefused(f"not a JSON object: {e}") from None
    else:
        try:
            body, form = msgpack.unpackb(data, raw=False, strict_map_key=False, max_bin_len=MAX_GOAL_BYTES), "msgpack"
        except Exception as e:  # noqa: BLE001 - msgpack raises many types on garbage
            raise GoalRefused(f"neither JSON nor msgpack: {type(e).__name__}: {e}") from None
        if isinstance(body, list):  # an envelope
            try:
                return decode(data, NbvGoal), "envelope"
            except DecodeError as e:
                gid = _goal_id_of(body[4]) if len(body) == 5 else None
                raise GoalRefused(str(e), gid) from None
    if not isinstance(body, dict):
        raise GoalRefused(f"a {form} goal must be an object/map, got {type(body).__name__}")
    try:
        plain = PlainGoal.model_validate(body)
    except ValidationError as e:
        raise GoalRefused(f"{form} goal refused: {_validation_reason(e)}", _goal_id_of(body)) from None
    return plain_to_goal(plain, default_id, stamp_ns), form


class RefusalLimiter:
    """Token bucket bounding how many refusals are published: ``rate_per_s`` on average, bursts of ``burst``.

    ``allow(now)`` spends a token or counts the refusal as suppressed; ``take_suppressed()`` returns that
    count and resets it (the next published status carries it). Thread-safe.
    """

    def __init__(self, rate_per_s: float = 10.0, burst: int = 20) -> None:
        if rate_per_s <= 0 or burst < 1:
            raise ValueError("rate_per_s must be > 0 and burst >= 1")
        self.rate_per_s, self.burst = rate_per_s, burst
        self._tokens = float(burst)
        self._last: float | None = None
        self._suppressed = 0
        self.suppressed_total = 0
        self._lock = threading.Lock()

    def allow(self, now: float) -> bool:
        with self._lock:
            if self._last is not None:
                self._tokens = min(float(self.burst), self._tokens + (now - self._last) * self.rate_per_s)
            self._last = now
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                return True
            self._suppressed += 1
            self.suppressed_total += 1
            return False

    def take_suppressed(self) -> int:
        with self._lock:
            n, self._suppressed = self._suppressed, 0
            return n


class GoalMailbox:
    """One slot, newest wins; ``superseded`` counts goals replaced before the loop took them.

    Each goal is held with the receipt number its answer (GoalStatus.received) will carry.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._goal: tuple[NbvGoal, int] | None = None
        self.superseded = 0

    def put(self, goal: NbvGoal, received: int = 0) -> tuple[NbvGoal, int] | None:
        """Hold ``goal``; returns the goal (and receipt number) it replaced, if any."""
        with self._lock:
            old, self._goal = self._goal, (goal, received)
            if old is not None:
                self.superseded += 1
            return old

    def take_with_receipt(self) -> tuple[NbvGoal, int] | None:
        with self._lock:
            item, self._goal = self._goal, None
            return item

    def take(self) -> NbvGoal | None:
        item = self.take_with_receipt()
        return item[0] if item is not None else None
