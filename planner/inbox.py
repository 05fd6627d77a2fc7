"""What the planner knows of the world, fed by Zenoh callbacks and read by the planning thread.

Callbacks only decode into bounded holders (newest map, newest state and viewpoint set per robot, bounded
queues of graph snapshots and deltas) and wake the planning thread. That thread follows the graph with
:class:`protocol.graph.GraphFollower` (snapshot + deltas; a new mapper epoch is adopted at once, a gap or
another epoch's delta re-queries the snapshot, and a run of stale snapshots from a live mapper overrides a
forged or lost future version). A robot whose liveliness token goes away is forgotten until it comes back.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING, TypeVar

from planner.config import PlannerNodeConfig
from planner.core import Planner
from planner.schedule import FusionWait, Pending
from protocol.codec import DecodeError, M, decode
from protocol.graph import GraphFollower
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphSnapshot, PointMap, RobotState, ViewpointSet
from protocol.ratelog import RateLimitedLog
from protocol.transport import Counters

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("argus.planner")
MAX_ROBOTS = 64
MAX_PENDING_DELTAS = 256
MAX_PENDING_SNAPSHOTS = 8
ROBOT_ROLE = "robot-agent"  # the role in a robot agent's liveliness token
R = TypeVar("R", RobotState, ViewpointSet)


class PlannerInbox:
    """The planner's view of the graph, the map and the robots (thread-safe holders, bounded)."""

    def __init__(self, config: PlannerNodeConfig, planner: Planner | None = None) -> None:
        self.config = config
        self.keys = Keys(config.site, config.prefix)
        self.planner = planner or Planner(config.planner)
        self.counters = Counters()
        self.bad_input = RateLimitedLog(log)  # bad-input warnings: first per reason, then a summary per period
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self.follower = GraphFollower()
        self._deltas: collections.deque[GraphDelta] = collections.deque(maxlen=MAX_PENDING_DELTAS)
        # Every snapshot counts (stale ones in a row resync the follower), so they queue rather than overwrite.
        self._snapshots: collections.deque[GraphSnapshot] = collections.deque(maxlen=MAX_PENDING_SNAPSHOTS)
        self.point_map: PointMap | None = None
        self.states: dict[str, RobotState] = {}
        # robots waiting for their arrival frame to be fused, as long as the mapper's measured pace asks
        self.fusion_wait = FusionWait(config.fusion_wait_s, config.fusion_wait_max_s, config.fusion_wait_factor)
        self.viewpoints: dict[str, ViewpointSet] = {}
        self.pending: dict[str, Pending] = {}
        self._gone: set[str] = set()  # robots whose liveliness token went away (until it comes back)
        self._alive: set[str] = set()  # robots whose liveliness token is there now
        self._heard: dict[str, float] = {}  # robot -> when its newest state arrived (monotonic s)

    @property
    def graph(self) -> GraphSnapshot:
        """The graph followed (see :class:`GraphFollower`)."""
        return self.follower.graph

    @graph.setter
    def graph(self, snap: GraphSnapshot) -> None:
        self.follower.graph = snap

    @property
    def _need_snapshot(self) -> bool:
        return self.follower.need_snapshot

    # --- callbacks (Zenoh threads) -----------------------------------------------------------
    def _decode(self, sample: zenoh.Sample, cls: type[M]) -> M | None:
        try:
            return decode(sample.payload.to_bytes(), cls)
        except DecodeError as e:
            self.counters.add("decode_errors")
            self.bad_input.warning("decode_errors", "dropping bad %s on %s: %s", cls.KIND, sample.key_expr, e)
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            self.counters.add("decode_errors")
            self.bad_input.warning("decode_errors", "dropping %s on %s: %s", cls.KIND, sample.key_expr, e)
        return None

    def on_snapshot(self, sample: zenoh.Sample) -> None:
        snap = self._decode(sample, GraphSnapshot)
        if snap is not None:
            self.offer_snapshot(snap)

    def offer_snapshot(self, snap: GraphSnapshot) -> None:
        with self._lock:
            if len(self._snapshots) == self._snapshots.maxlen:
                self.counters.add("snapshots_dropped")
            self._snapshots.append(snap)
        self.counters.add("snapshots_in")
        self._wake.set()

    def on_delta(self, sample: zenoh.Sample) -> None:
        delta = self._decode(sample, GraphDelta)
        if delta is None:
            return
        with self._lock:
            if len(self._deltas) == self._deltas.maxlen:
                self.counters.add("deltas_dropped")
                self._deltas.clear()  # the follower sees the gap and re-queries the snapshot
            self._deltas.append(delta)
        self.counters.add("deltas_in")
        self._wake.set()

    def on_map(self, sample: zenoh.Sample) -> None:
        pm = self._decode(sample, PointMap)
        if pm is not None:
            with self._lock:
                self.point_map = pm
            self.counters.add("maps_in")

    def _robot_id(self, sample: zenoh.Sample) -> str | None:
        try:
            return self.keys.parse_robot(str(sample.key_expr))[0]
        except ValueError:
            self.counters.add("bad_keys")
            return None

    def _robot_message(self, sample: zenoh.Sample, cls: type[R], what: str) -> tuple[str, R] | None:
        """A robot's message with the robot its key names, or None (counted) when bad or naming another robot."""
        msg = self._decode(sample, cls)
        rid = self._robot_id(sample)
        if msg is None or rid is None:
            return None
        if msg.robot_id != rid:
            self.counters.add("decode_errors")
            self.bad_input.warning("wrong_robot", "%s on %s names robot %r; ignored", what, sample.key_expr,
                                   msg.robot_id)
            return None
        return rid, msg

    def _hold(self, table: dict[str, R], rid: str, msg: R, gone: str | None = None) -> None:
        """Keep ``msg`` as robot ``rid``'s newest (for at most MAX_ROBOTS robots) and wake the planning thread;
        with ``gone`` (a counter), not for a robot whose token went away."""
        with self._lock:
            if gone is not None and rid in self._gone:
                self.counters.add(gone)
                return
            if rid not in table and len(table) >= MAX_ROBOTS:
                self.counters.add("robots_refused")
                return
            table[rid] = msg
        self._wake.set()

    def on_state(self, sample: zenoh.Sample) -> None:
        got = self._robot_message(sample, RobotState, "state")
        if got is not None:
            self._hold(self.states, *got, gone="states_of_gone_robots")
            with self._lock:
                if got[0] in self.states:
                    self._heard[got[0]] = time.monotonic()

    def unannounced(self) -> list[str]:
        """Robots the planner holds a state of that have no liveliness token."""
        with self._lock:
            return [rid for rid in self.states if rid not in self._alive]

    def expire_unannounced(self, now_s: float) -> list[str]:
        """Forget the robots without a liveliness token that sent no state for ``unannounced_expire_s`` (a
        phantom id must not take goals, and planning time, from real robots for ever); returns them."""
        limit = self.config.unannounced_expire_s
        with self._lock:
            stale = [rid for rid in self.states
                     if rid not in self._alive and now_s - self._heard.get(rid, now_s) > limit]
        for rid in stale:
            self.forget_robot(rid, gone=False)
            self.counters.add("robots_expired")
            log.warning("robot %s has no liveliness token and sent no state for %.0f s: forgotten", rid, limit)
        return stale

    def on_viewpoints(self, sample: zenoh.Sample) -> None:
        got = self._robot_message(sample, ViewpointSet, "viewpoints")
        if got is not None:
            self._hold(self.viewpoints, *got)

    def on_alive(self, sample: zenoh.Sample) -> None:
        """Robot liveliness: a robot whose token goes away (it stopped, crashed or lost its link) is
        forgotten (state, viewpoints, pending goal, claim), so the others are planned without it; when it
        comes back its state and viewpoints arrive afresh."""
        try:
            role, rid = self.keys.parse_alive(str(sample.key_expr))
        except ValueError:
            self.counters.add("bad_keys")
            return
        if role != ROBOT_ROLE:
            return
        if str(sample.kind).endswith("DELETE"):
            with self._lock:
                self._alive.discard(rid)
            self.forget_robot(rid)
        else:
            with self._lock:
                self._gone.discard(rid)
                if len(self._alive) < MAX_ROBOTS:
                    self._alive.add(rid)
            self.counters.add("robots_joined")
            log.info("robot %s is alive", rid)

    def forget_robot(self, rid: str, gone: bool = True) -> None:
        """Forget everything of robot ``rid``; ``gone``: its token went away, so its samples still on their way
        are ignored until it is back (an expired robot without a token is taken again when it speaks)."""
        with self._lock:
            if gone and len(self._gone) < MAX_ROBOTS:
                self._gone.add(rid)  # its last samples may still be on their way: ignored until it is back
            self._heard.pop(rid, None)
            known = self.states.pop(rid, None) is not None
            self.viewpoints.pop(rid, None)
            self.pending.pop(rid, None)
            self.fusion_wait.forget(rid)
            self.planner.release(rid)
        if known and gone:
            self.counters.add("robots_lost")
            log.warning("robot %s went away (liveliness); planning for the remaining robots", rid)
        self._wake.set()

    def _follow_graph(self) -> None:
        with self._lock:
            snaps = list(self._snapshots)
            self._snapshots.clear()
            deltas = list(self._deltas)
            self._deltas.clear()
        f = self.follower
        adopted = False
        for snap in snaps:
            held = f.graph.version
            outcome = f.offer_snapshot(snap)
            adopted = adopted or outcome != "stale"
            if outcome == "resynced":
                log.warning("%d snapshots in a row were older than the graph held (v%d): following v%d of epoch %s",
                            f.resync_after, held, f.graph.version, f.graph.epoch or "''")
        for d in sorted(deltas, key=lambda d: d.version):
            if adopted and d.epoch == f.graph.epoch and d.version <= f.graph.version:
                continue  # covered by the snapshot just adopted: not a sign of a stale graph
            if f.offer_delta(d) in ("gap", "other_epoch"):
                break
        for name, value in f.counters.items():
            self.counters.set(name, value)
