"""The I/O shell of ``argus planner``: graph, map, robot states and viewpoints in; one goal per robot out.

What comes in is held by :class:`planner.inbox.PlannerInbox` (bounded, fed by Zenoh callbacks). The planning
thread follows the graph, decides which robots need a goal (:func:`planner.schedule.goal_due`: arrived,
failed or refused on their goal; idle; or a large graph change while moving; an arrived robot once the graph
covers its arrival frame), calls the pure :class:`~planner.core.Planner` and publishes :class:`NbvGoal`\\ s
with BLOCK and high priority.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

from planner.config import PlannerNodeConfig
from planner.core import Planner
from planner.inbox import MAX_ROBOTS, ROBOT_ROLE, PlannerInbox, log
from planner.schedule import Pending, goal_due
from protocol.codec import DecodeError, M, decode, encode
from protocol.messages import GraphSnapshot, NbvGoal, RobotState, ViewpointSet
from protocol.node import Node, Process
from protocol.rooms import RoomLayer
from protocol.runtime import release_free_heap

if TYPE_CHECKING:
    import zenoh

ROLE = "planner"


class PlannerNode(PlannerInbox, Process):
    """One planner process. ``run(stop)`` blocks until ``stop`` is set; tests may call it directly."""

    def __init__(self, config: PlannerNodeConfig, planner: Planner | None = None) -> None:
        super().__init__(config, planner)
        self._pubs: dict[str, Any] = {}
        self._rooms_version = -1  # the graph version the planner last asked for rooms at
        self.node = Node(config.zenoh, self.keys, ROLE, config.node_id, counters=self.counters,
                         status_period_s=config.status_period_s, logger=log)

    # --- planning thread ---------------------------------------------------------------------
    def robots_to_plan(self, now_s: float) -> dict[str, tuple[RobotState, ViewpointSet]]:
        """Robots that need a (new) goal now, with their state and viewpoints."""
        out = {}
        n_nodes, cfg = len(self.graph.nodes), self.config
        self.fusion_wait.note(self.graph.frames, now_s)  # waits covered since, run out or not: the mapper's pace
        self.counters.set("fusion_wait_limit_s", self.fusion_wait.limit_s())
        with self._lock:
            items = [(rid, st, self.viewpoints.get(rid)) for rid, st in self.states.items()]
        for rid, st, vps in items:
            if vps is None or not vps.viewpoints or st.status == "budget_exhausted":
                continue
            p = self.pending.get(rid)
            due = goal_due(st, p, n_nodes, now_s, cfg.resend_s, cfg.replan_new_nodes)
            if due == "failed" and p is not None:
                self.planner.mark_failed(rid, p.vp_id)
                self.counters.add("goals_failed")
            elif due == "graph_change":
                self.counters.add("replans_graph_change")
            if due is not None and self._arrival_fused(rid, st, now_s):
                out[rid] = (st, vps)
        return out

    def _arrival_fused(self, rid: str, st: RobotState, now_s: float) -> bool:
        ready, event = self.fusion_wait.ready(rid, st, self.graph.frames.get(rid, -1), now_s)
        if event is not None:
            self.counters.add(event)
        if event == "fusion_wait_timeouts":
            log.warning("robot %s: no graph version covers its arrival frame %d after %.1f s; planning anyway",
                        rid, st.last_frame_seq, self.fusion_wait.waited_s)
        return ready

    def plan_once(self, now_s: float | None = None) -> list:
        """Follow the graph, plan for the robots that need it, publish; returns the goals sent."""
        now_s = time.monotonic() if now_s is None else now_s
        self._follow_graph()
        self.expire_unannounced(time.monotonic())
        robots = self.robots_to_plan(now_s)
        if not robots:
            return []
        with self._lock:
            pm = self.point_map
        try:
            goals = self.planner.plan(self.graph, pm, robots)
        except Exception as e:  # noqa: BLE001 - a planning bug must not take the planner down
            self.counters.add("plan_errors")
            log.exception("planning failed")
            self._reporter_error(f"planning failed: {e}")
            for rid in robots:  # back off instead of retrying in a tight loop
                self.pending[rid] = Pending("", None, now_s, len(self.graph.nodes))
            return []
        finally:
            self._release_heap()
        info = self.planner.info
        if info.hypotheses_error:
            self.counters.add("plan_hypotheses_errors")
            self._reporter_error(f"asp's completions failed, planned by frontiers: {info.hypotheses_error}")
        self.counters.add("decisions")
        self.counters.set("decision_ms_last", info.decision_s * 1e3)
        self.counters.set("decision_cpu_ms_last", info.decision_cpu_s * 1e3)
        self.counters.set("decision_ms_max", max(self.counters.get("decision_ms_max"), info.decision_s * 1e3))
        self.counters.set("graph_version", self.graph.version)
        self.counters.set("frontier_points", info.n_frontier)
        self.counters.set("hypotheses", info.n_hypotheses)
        if info.sampler_fallback:
            self.counters.add("sampler_fallbacks")
        sent = []
        for g in goals:
            p = self.pending.get(g.robot_id)
            st = robots[g.robot_id][0]
            if st.status == "moving" and p is not None and p.vp_id == g.vp_id:
                p.n_nodes = len(self.graph.nodes)  # same goal after the graph change: keep going
                continue
            self._publish_goal(g)
            self.pending[g.robot_id] = Pending(g.goal_id, g.vp_id, now_s, len(self.graph.nodes))
            self.counters.set("gain_last", g.expected_gain)
            sent.append(g)
        for rid in robots.keys() - {g.robot_id for g in goals}:
            self.pending[rid] = Pending("", None, now_s, len(self.graph.nodes))  # nothing to do: back off
        return sent

    def _extra_counters(self) -> dict[str, float]:
        """Status extras: the robots and the graph followed, and the sizes that must stay bounded (a soak samples
        them): remembered views (``max_history``), points of the held map, blacklisted viewpoints."""
        pm = self.point_map
        return {"robots": len(self.states), "robots_unannounced": len(self.unannounced()),
                "graph_nodes": len(self.graph.nodes), "graph_version": self.graph.version,
                "history_views": len(self.planner.history),
                "point_map_points": 0 if pm is None else int(pm.points.shape[0]),
                "blacklisted_viewpoints": sum(len(b) for b in list(self.planner.blacklist.values()))}

    def _release_heap(self) -> None:
        """After a decision's burst of temporary arrays, its freed memory back to the system (the resting RSS
        stays flat: ``protocol.runtime.release_free_heap``)."""
        if self.config.release_heap_after_plan and release_free_heap() is not None:
            self.counters.add("heap_releases")

    def _reporter_error(self, msg: str) -> None:
        self.node.error(msg)

    def _publish_goal(self, goal: Any) -> None:
        pub = self._pubs.get(goal.robot_id)
        if pub is None and self.node.is_open:
            pub = self._pubs[goal.robot_id] = self.node.publisher(self.keys.robot_goal(goal.robot_id), message=NbvGoal)
        if pub is None:
            return
        try:
            pub.put(encode(goal))
            self.counters.add("goals_sent")
            log.info("goal %s -> (%.2f, %.2f) gain %.2f: %s (%.0f ms)", goal.goal_id, goal.x, goal.y,
                     goal.expected_gain, goal.reason, self.planner.info.decision_s * 1e3)
        except Exception as e:  # noqa: BLE001 - a closing session must not kill the loop
            self.counters.add("publish_errors")
            log.warning("goal publish failed: %s", e)

    # --- start-up queries --------------------------------------------------------------------
    def _query(self, session: zenoh.Session, key: str, cls: type[M]) -> list[M]:
        import zenoh

        out: list[M] = []
        try:
            # No reply consolidation: the default keeps one reply per key, so a late peer answering
            # with garbage could hide the mapper's snapshot; every reply is judged here instead.
            replies = session.get(key, timeout=self.config.query_timeout_s,
                                  consolidation=zenoh.ConsolidationMode.NONE)
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    out.append(decode(reply.ok.payload.to_bytes(), cls))
                except DecodeError as e:
                    self.counters.add("decode_errors")
                    self.bad_input.warning("bad_replies", "bad %s reply: %s", cls.KIND, e)
        except Exception as e:  # noqa: BLE001 - nobody answering is normal at start-up
            log.debug("query %s failed: %s", key, e)
        return out

    def _initial_queries(self, session: zenoh.Session) -> None:
        self.counters.add("snapshot_queries")
        for snap in self._query(session, self.keys.graph_snapshot, GraphSnapshot):
            self.offer_snapshot(snap)
        for vps in self._query(session, self.keys.all_robot_viewpoints, ViewpointSet):
            with self._lock:
                if len(self.viewpoints) < MAX_ROBOTS:
                    self.viewpoints.setdefault(vps.robot_id, vps)
        self._wake.set()

    # --- process -----------------------------------------------------------------------------
    def serve(self, node: Node) -> None:
        k = self.keys
        node.on_exit(lambda: log.info("planner stopped (%d goals sent)", int(self.counters.get("goals_sent"))))
        for key, callback in ((k.graph_snapshot, self.on_snapshot), (k.graph_delta, self.on_delta),
                              (k.map_points, self.on_map), (k.all_robot_states, self.on_state),
                              (k.all_robot_viewpoints, self.on_viewpoints)):
            node.subscribe(key, callback)
        node.watch_alive(k.all_alive_of(ROBOT_ROLE), self.on_alive)
        node.status(extra=self._extra_counters)
        c = self.config
        log.info("planner %s up: strategy %s, sampler %s", c.node_id, c.planner.strategy, c.planner.sampler.kind)
        self._initial_queries(node.session)
        node.alive()  # once the start-up queries are answered
        self._loop(node.stop, node.session)

    def _refresh_rooms(self, session: zenoh.Session) -> None:
        """The mapper's newest room layer for the planner, when the graph moved since the last one."""
        version = self.graph.version
        if self._rooms_version == version:
            return
        self._rooms_version = version
        self.counters.add("room_queries")
        layers = self._query(session, self.keys.graph_rooms, RoomLayer)
        if layers:
            best = max(layers, key=lambda r: r.version)
            self.planner.rooms = best
            self.counters.set("rooms", len(best.rooms))

    def _loop(self, stop: threading.Event, session: zenoh.Session) -> None:
        last_query = last_rooms = time.monotonic()
        while not stop.is_set():
            self._wake.wait(0.25)
            self._wake.clear()
            self.bad_input.flush()
            period = self.config.rooms_period_s
            if period > 0 and time.monotonic() - last_rooms >= period:
                last_rooms = time.monotonic()
                self._refresh_rooms(session)
            if self._need_snapshot and time.monotonic() - last_query > 2.0:
                last_query = time.monotonic()
                self.counters.add("snapshot_queries")
                for snap in self._query(session, self.keys.graph_snapshot, GraphSnapshot):
                    self.offer_snapshot(snap)
                self._follow_graph()
            try:
                self.plan_once()
            except Exception as e:  # noqa: BLE001 - the loop must survive anything
                self.counters.add("loop_errors")
                log.exception("planner loop step failed")
                self._reporter_error(str(e))


def run(config: PlannerNodeConfig, stop: threading.Event | None = None) -> int:
    """Run the planner until ``stop`` (default: SIGINT/SIGTERM)."""
    return PlannerNode(config).run(stop)
