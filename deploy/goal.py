"""``argus goal``: send one goal to a robot and print its answer (accepted, or refused with the reason).

Examples::

    argus goal --robot robot0 --x 2.0 --y 1.5 --yaw-deg 90
    argus goal --robot robot0 --x 2 --y 1.5 --json          # the GoalStatus as JSON
    argus goal --robot robot0 --room kitchen                 # go to the kitchen (a room label or id)

The goal is an ``nbv_goal`` envelope put on ``robot/<id>/goal``; the robot answers every goal payload
with a :class:`~protocol.messages.GoalStatus` on ``robot/<id>/goal/status`` (docs/WIRE.md), which this
command subscribes to before sending, so the answer cannot be missed.

``--room`` names a room of the mapper's room layer (``graph/rooms``) by id or label (the most confident room with
that label): the goal is the robot's own viewpoint inside the room nearest its centre, facing the centre (the
room's centre itself when none of its viewpoints is inside).
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import time
from typing import Any

import numpy as np

from protocol import exits
from protocol.codec import DecodeError, decode, encode
from protocol.keys import Keys
from protocol.messages import GoalStatus, NbvGoal, ViewpointSet
from protocol.rooms import RoomLayer, RoomNode
from protocol.session import ZenohConfigError, ZenohUnavailable, open_session
from protocol.tomlconfig import add_consumer_flags, consumer_values

EXIT_ACCEPTED, EXIT_REFUSED, EXIT_USAGE, EXIT_NO_ANSWER = exits.OK, exits.FAILED, exits.USAGE, exits.UNREACHABLE

EPILOG = """examples:
  argus goal --robot robot0 --x 2.0 --y 1.5 --yaw-deg 90
  argus goal --robot robot0 --room kitchen
  argus goal --robot robot0 --x 2 --y 1.5 --connect tcp/127.0.0.1:7447 --json

exit status: 0 accepted, 1 refused (the reason is printed), 2 bad arguments (a bad endpoint or value),
3 no such room (--room), 4 no answer: no router at --connect, or no answer from the robot (or, with --room,
the mapper) within --timeout (is its agent running, on this site?)."""


def make_goal(robot_id: str, x: float, y: float, yaw_rad: float, goal_id: str | None = None) -> NbvGoal:
    """The goal this command sends (``goal_id`` defaults to ``cli-<robot>-<ms since epoch>``)."""
    now = time.time_ns()
    return NbvGoal(goal_id=goal_id or f"cli-{robot_id}-{now // 1_000_000}", robot_id=robot_id, stamp_ns=now,
                   x=x, y=y, yaw_rad=yaw_rad, strategy="cli", reason="argus goal")


def send_goal(session: Any, keys: Keys, goal: NbvGoal, timeout_s: float = 5.0) -> GoalStatus | None:
    """Put ``goal`` and wait for the robot's GoalStatus naming it; None after ``timeout_s`` without one."""
    inbox: queue.Queue[bytes] = queue.Queue(maxsize=64)

    def on_sample(sample: Any) -> None:
        try:
            inbox.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            pass  # answers to other senders' goals; ours is matched by id below

    sub = session.declare_subscriber(keys.robot_goal_status(goal.robot_id), on_sample)
    try:
        session.put(keys.robot_goal(goal.robot_id), encode(goal))
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                status = decode(inbox.get(timeout=left), GoalStatus)
            except queue.Empty:
                break
            except DecodeError:
                continue
            if status.goal_id == goal.goal_id:
                return status
        return None
    finally:
        sub.undeclare()


def pick_room(layer: RoomLayer, name: str) -> RoomNode | None:
    """The room ``name`` names: its id, else the most confident (then largest) room with that label."""
    by_id = next((r for r in layer.rooms if r.room_id == name), None)
    if by_id is not None:
        return by_id
    same = [r for r in layer.rooms if r.label == name]
    return max(same, key=lambda r: (r.label_confidence, r.area_m2)) if same else None


def room_goal_xy(room: RoomNode, vps: ViewpointSet | None) -> tuple[float, float, float]:
    """Where to go to look around ``room``: the viewpoint inside it nearest its centre, facing the centre; the centre
    itself when no viewpoint is inside (x, y, yaw)."""
    from planner.completion import in_polygon

    cx, cy = room.centroid
    pts = np.array([[v.x, v.y] for v in vps.viewpoints]).reshape(-1, 2) if vps is not None else np.zeros((0, 2))
    inside = np.flatnonzero(in_polygon(pts, room.polygon))
    if inside.size == 0:
        return cx, cy, 0.0
    d = np.hypot(pts[inside, 0] - cx, pts[inside, 1] - cy)
    x, y = pts[inside[int(np.argmin(d))]]
    yaw = math.atan2(cy - y, cx - x) if float(d.min()) > 0.2 else 0.0
    return float(x), float(y), yaw


def get_viewpoints(session: Any, keys: Keys, robot_id: str, timeout_s: float) -> ViewpointSet | None:
    """The robot's viewpoint set (its agent answers the query), None without an answer."""
    for reply in session.get(keys.robot_viewpoints(robot_id), timeout=timeout_s):
        if reply.ok is not None:
            try:
                return decode(reply.ok.payload.to_bytes(), ViewpointSet)
            except DecodeError:
                continue
    return None


def describe(status: GoalStatus) -> str:
    if status.accepted:
        return f"robot {status.robot_id} accepted goal {status.goal_id}"
    return f"robot {status.robot_id} refused goal {status.goal_id}: {status.reason}"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus goal", description="Send one goal to a robot and print its answer.", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robot", required=True, help="robot id (the robot agent's --id)")
    p.add_argument("--x", type=float, default=None, help="goal x, metres (world frame)")
    p.add_argument("--y", type=float, default=None, help="goal y, metres (world frame)")
    p.add_argument("--room", default=None,
                   help="instead of --x/--y: a room of the mapper's room layer, by id (room3) or label (kitchen)")
    yaw = p.add_mutually_exclusive_group()
    yaw.add_argument("--yaw", type=float, default=None, help="goal heading, radians from +x counter-clockwise")
    yaw.add_argument("--yaw-deg", type=float, default=None, help="goal heading in degrees (instead of --yaw)")
    p.add_argument("--goal-id", default=None, help="goal id (default: cli-<robot>-<ms since epoch>)")
    add_consumer_flags(p)
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the robot's answer")
    p.add_argument("--json", action="store_true", help="print the GoalStatus as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    yaw = math.radians(a.yaw_deg) if a.yaw_deg is not None else (a.yaw or 0.0)
    if (a.room is None) == (a.x is None or a.y is None) or (a.room is not None and (a.x, a.y) != (None, None)):
        print("argus goal: give either --x and --y, or --room", file=sys.stderr)
        return EXIT_USAGE
    try:
        settings, site = consumer_values(a)
        keys = Keys(site)
        keys.robot_goal(a.robot)
        goal = make_goal(a.robot, a.x, a.y, yaw, a.goal_id) if a.room is None else None
    except ValueError as e:  # pydantic's ValidationError included: one line per field, no URL
        print(f"argus goal: {exits.one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    try:
        with open_session(settings) as session:
            if goal is None:
                from deploy.query import QueryError, get_rooms

                try:
                    layer = get_rooms(session, keys, a.timeout)
                except QueryError as e:
                    print(f"argus goal: {e}", file=sys.stderr)
                    return e.exit_code
                room = pick_room(layer, a.room)
                if room is None:
                    known = ", ".join(f"{r.room_id} ({r.label})" for r in layer.rooms) or "none yet"
                    print(f"argus goal: no room {a.room!r} in the mapper's room layer (rooms: {known})",
                          file=sys.stderr)
                    return exits.NOT_FOUND
                x, y, room_yaw = room_goal_xy(room, get_viewpoints(session, keys, a.robot, a.timeout))
                goal = make_goal(a.robot, x, y, yaw if (a.yaw is not None or a.yaw_deg is not None) else room_yaw,
                                 a.goal_id).model_copy(update={"reason": f"argus goal --room {a.room}: {room.room_id}"})
            status = send_goal(session, keys, goal, a.timeout)
    except ZenohConfigError as e:
        print(f"argus goal: {exits.one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except ZenohUnavailable as e:
        print(f"argus goal: {e}", file=sys.stderr)
        return EXIT_NO_ANSWER
    except Exception as e:  # noqa: BLE001 - anything else: a message, not a traceback
        print(f"argus goal: {type(e).__name__}: {exits.one_line(e)}", file=sys.stderr)
        return exits.FAILED
    if status is None:
        print(f"argus goal: no answer from robot {goal.robot_id!r} on site {site!r} within {a.timeout:g} s "
              f"(is its robot agent running and connected to {', '.join(settings.connect)}?)", file=sys.stderr)
        return EXIT_NO_ANSWER
    print(status.model_dump_json() if a.json else describe(status))
    return EXIT_ACCEPTED if status.accepted else EXIT_REFUSED


if __name__ == "__main__":
    sys.exit(main())
