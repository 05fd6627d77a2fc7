"""The pure next-best-view planner: candidates in, one goal per robot out (no I/O).

``Planner(config).plan(snapshot, point_map, robots)`` scores every robot's published viewpoints
with the configured strategy and returns an :class:`~protocol.messages.NbvGoal` per robot:

* ``see``: geometric baseline after Surface Edge Explorer: frontier points of the map (measurement
  density), the view that sees most of them (frustum, range, occlusion) wins; travel cost breaks ties.
* ``asp``: semantic: a completion sampler proposes K completions of the unobserved scene; each view
  is scored by the expected information gain I(Y;G|x) of the label multiset it would observe
  (with position jitter); utility = gain - travel_bits_per_m * travel distance.

Both strategies share the candidate set, the view model, the revisit rule, travel costs and the
multi-robot claims (no two robots sent to look at the same region at once).
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planner.completion import (
    SAMPLERS,
    UNEXPLORED,
    CompletionSampler,
    build_context,
    in_polygon,
    room_of_points,
    rooms_from_layer,
    rooms_from_viewpoints,
)
from planner.config import PlannerConfig
from planner.frontier import classify_frontier
from planner.gain import factored_gain, joint_gain
from planner.geometry import (
    Candidates,
    Panoramas,
    candidates_from_viewpoints,
    detect_matrix,
    downsample_occluders,
    in_view_pairs,
)
from planner.hypotheses import Hypotheses, realize
from planner.prior import IndoorPrior, load_prior
from protocol.messages import GraphSnapshot, Intrinsics, NbvGoal, PointMap, RobotState, ViewpointSet
from protocol.rooms import RoomLayer

log = logging.getLogger(__name__)

FLOOR_CELL_M = 0.2
FLOOR_MAX_Z_M = 0.08


@dataclass
class _View:
    T_world_cam: np.ndarray
    K: np.ndarray
    width: int
    height: int
    far_m: float


@dataclass
class PlanInfo:
    """Diagnostics of the last ``plan`` call."""

    decision_s: float = 0.0
    decision_cpu_s: float = 0.0  # CPU seconds of the process (all its threads) during the call
    n_candidates: int = 0
    n_frontier: int = 0
    n_hypotheses: int = 0
    panoramas_reused: int = 0  # z-buffers taken over from the previous decision (no map change in their range)
    sampler: str = ""
    sampler_fallback: bool = False
    per_robot: dict[str, dict[str, Any]] = field(default_factory=dict)
    room_source: str = ""  # where asp's rooms came from: map or viewpoints
    frontier_by_room: dict[str, int] = field(default_factory=dict)  # see's frontier points per mapper room
    hypotheses_by_room: dict[str, int] = field(default_factory=dict)  # asp's hypotheses per room
    hypotheses_error: str = ""  # asp's completions failed this decision (the error): it planned by frontiers


@dataclass
class _PlanContext:
    """What one ``plan`` call works on: the map's finite points, one panorama per distinct camera position
    and each camera's row in it, and the floor cells the map has seen."""

    point_map: PointMap | None
    points: np.ndarray  # (N, 3) the map's finite points
    pano: Panoramas
    cand_rows: dict[str, np.ndarray]  # per robot: each candidate's panorama row
    hist_rows: list[int]  # each remembered view's panorama row
    claim_rows: dict[str, int]  # per robot with a goal: the goal's panorama row (grows as goals are issued)
    floor_cells: np.ndarray  # cell keys (``_cell_keys``) of the floor the map has seen
    frontier: np.ndarray | None = None  # see's targets, computed on first use (``Planner._frontier_targets``)

    def floor_seen(self, xy: np.ndarray) -> np.ndarray:
        """Whether each (x, y) lies on a floor cell the map has seen (no floor-standing hypothesis there)."""
        return np.isin(_cell_keys(xy), self.floor_cells)


class _Positions:
    """Distinct camera positions (to the millimetre) in first-seen order: the panoramas' rows."""

    def __init__(self) -> None:
        self._positions: list[np.ndarray] = []
        self._row: dict[tuple[float, float, float], int] = {}

    def row(self, p: np.ndarray) -> int:
        key = (round(float(p[0]), 3), round(float(p[1]), 3), round(float(p[2]), 3))
        if key not in self._row:
            self._row[key] = len(self._positions)
            self._positions.append(np.asarray(p, dtype=np.float64))
        return self._row[key]

    def array(self) -> np.ndarray:
        return np.array(self._positions).reshape(-1, 3)


def make_sampler(config: PlannerConfig, prior: IndoorPrior) -> CompletionSampler:
    """The configured completion sampler, from the registry (imported lazily)."""
    import importlib

    target = SAMPLERS.get(config.sampler.kind)
    if target is None:
        raise ValueError(f"unknown sampler {config.sampler.kind!r} (known: {', '.join(SAMPLERS)})")
    module, _, attr = target.partition(":")
    return getattr(importlib.import_module(module), attr)(config, prior)


class Planner:
    """Stateful NBV planner: remembers past views, issued goals (claims) and failed viewpoints."""

    def __init__(
        self,
        config: PlannerConfig | None = None,
        sampler: CompletionSampler | None = None,
        prior: IndoorPrior | None = None,
    ) -> None:
        self.config = config or PlannerConfig()
        self.prior = prior or load_prior(self.config.sampler.prior_path)
        self.sampler = sampler or make_sampler(self.config, self.prior)
        self.rng = np.random.default_rng(self.config.seed)
        self.history: list[_View] = []
        self.goals: dict[str, tuple[NbvGoal, np.ndarray]] = {}
        self.blacklist: dict[str, set[int]] = {}
        self.info = PlanInfo()
        # The mapper's room layer (graph/rooms), when the planner has one: asp's rooms, frontier and goal rooms,
        # the focus room. None: rooms come from the viewpoints' names only.
        self.rooms: RoomLayer | None = None
        self._cand_cache: dict[str, tuple[int, Candidates]] = {}
        self._frontier_cache: tuple[tuple[int, int, int], np.ndarray] | None = None
        self._last_pano: Panoramas | None = None  # the last decision's z-buffers, reused where the map did not change
        self._n_goals = 0
        self.last_scores: dict[str, np.ndarray] = {}
        """Per robot, the score of every candidate in the last plan (frontier points or bits)."""

    # -- memory -------------------------------------------------------------------------------
    def record_view(self, T_world_cam: np.ndarray, intrinsics: Intrinsics, max_range_m: float = 6.0) -> None:
        """Remember a view that was (or is being) taken: hypotheses it would have seen are ruled out."""
        T = np.asarray(T_world_cam, dtype=np.float64)
        for v in self.history[-50:]:
            if (
                np.linalg.norm(v.T_world_cam[:3, 3] - T[:3, 3]) < 0.05
                and float(v.T_world_cam[:3, 2] @ T[:3, 2]) > 0.996
            ):
                return
        self.history.append(_View(T, intrinsics.K(), intrinsics.width, intrinsics.height, float(max_range_m)))
        if len(self.history) > self.config.max_history:
            del self.history[0]

    def mark_failed(self, robot_id: str, vp_id: int | None) -> None:
        """A goal on this viewpoint failed or was refused: do not send the robot there again."""
        if vp_id is not None:
            self.blacklist.setdefault(robot_id, set()).add(int(vp_id))

    def release(self, robot_id: str) -> None:
        """Forget a robot's active goal (it arrived, failed or left)."""
        self.goals.pop(robot_id, None)

    # -- helpers ------------------------------------------------------------------------------
    def _candidates(self, vps: ViewpointSet) -> Candidates:
        key = hash(
            (
                vps.robot_id,
                len(vps.viewpoints),
                vps.camera_height_m,
                vps.camera_pitch_deg,
                tuple(
                    (v.vp_id, v.x, v.y, v.yaw_rad)
                    for v in vps.viewpoints[:: max(1, len(vps.viewpoints) // 64)]
                ),
            )
        )
        hit = self._cand_cache.get(vps.robot_id)
        if hit is not None and hit[0] == key:
            return hit[1]
        c = candidates_from_viewpoints(vps)
        self._cand_cache[vps.robot_id] = (key, c)
        return c

    @staticmethod
    def _travel(state: RobotState, cands: Candidates) -> np.ndarray:
        tc = state.travel_cost_m
        if tc is not None and np.asarray(tc).reshape(-1).shape[0] == cands.size:
            return np.asarray(tc, dtype=np.float64).reshape(-1)
        return np.hypot(cands.xy_yaw[:, 0] - state.x, cands.xy_yaw[:, 1] - state.y)

    def _frontier(self, pm: PointMap) -> np.ndarray:
        key = (pm.version, int(pm.points.shape[0]), pm.stamp_ns)
        if self._frontier_cache is not None and self._frontier_cache[0] == key:
            return self._frontier_cache[1]
        counts = None if pm.counts is None else np.asarray(pm.counts).reshape(-1)
        if counts is not None and counts.shape[0] != pm.points.shape[0]:
            counts = None
        mask = classify_frontier(
            np.asarray(pm.points, dtype=np.float64),
            counts,
            pm.voxel_m,
            self.config.see,
            self.config.visibility.threads,
        )
        self._frontier_cache = (key, mask)
        return mask

    def _valid(
        self, rid: str, cands: Candidates, travel: np.ndarray, claimed_xy: list[np.ndarray]
    ) -> np.ndarray:
        ok = np.isfinite(travel)
        bl = self.blacklist.get(rid)
        if bl:
            ok &= ~np.isin(cands.vp_ids, np.fromiter(bl, dtype=np.int64))
        if self.history:
            Hp = np.stack([v.T_world_cam[:3, 3] for v in self.history])
            Hz = np.stack([v.T_world_cam[:3, 2] for v in self.history])
            Cp = cands.T_world_cam[:, :3, 3]
            Cz = cands.T_world_cam[:, :3, 2]
            near = np.linalg.norm(Cp[:, None, :2] - Hp[None, :, :2], axis=2) < self.config.revisit_xy_m
            aligned = Cz @ Hz.T > np.cos(np.radians(self.config.revisit_yaw_deg))
            ok &= ~np.any(near & aligned, axis=1)
        for xy in claimed_xy:
            ok &= (
                np.hypot(cands.xy_yaw[:, 0] - xy[0], cands.xy_yaw[:, 1] - xy[1]) >= self.config.claim_radius_m
            )
        return ok

    def _history_detect(
        self,
        pano: Panoramas,
        rows: list[int],
        targets: np.ndarray,
        sizes: np.ndarray | None,
        min_px: float,
        margin: float,
        far_frac: float = 1.0,
    ) -> np.ndarray:
        """(V, T) detections of ``targets`` by the remembered views (rows: their panorama rows)."""
        out = np.zeros((len(self.history), targets.shape[0]), bool)
        if targets.shape[0] == 0:
            return out
        vcfg = self.config.visibility
        for idx, T, K, w, h, far in self._history_groups():
            det = detect_matrix(
                T,
                np.array([rows[i] for i in idx]),
                pano,
                K,
                w,
                h,
                targets,
                far * far_frac,
                vcfg,
                sizes,
                min_px,
                margin,
            )
            out[idx] = det
        return out

    def _history_groups(self) -> list[tuple[list[int], np.ndarray, np.ndarray, int, int, float]]:
        """The remembered views grouped by camera model: (indices, poses (n, 4, 4), K, width, height, range)."""
        groups: dict[tuple, list[int]] = {}
        for i, v in enumerate(self.history):
            groups.setdefault((v.width, v.height, v.far_m, tuple(v.K.ravel())), []).append(i)
        return [
            (idx, np.stack([self.history[i].T_world_cam for i in idx]), np.array(Kt).reshape(3, 3), w, h, far)
            for (w, h, far, Kt), idx in groups.items()
        ]

    def _history_attempts(
        self, targets: np.ndarray, sizes: np.ndarray | None, min_px: float, far_frac: float, margin: float = 0.1
    ) -> np.ndarray:
        """(T,) how many remembered views had each target well in view: inside the image less ``margin``, within
        ``far_frac`` of their range, at least ``min_px`` big (occlusion not asked)."""
        out = np.zeros(targets.shape[0], np.int64)
        if targets.shape[0] == 0:
            return out
        vcfg = self.config.visibility
        for _, T, K, w, h, far in self._history_groups():
            _, tgts = in_view_pairs(
                T, K, w, h, targets, vcfg.near_m, far * far_frac, margin, sizes, min_px, vcfg.threads
            )
            out += np.bincount(tgts, minlength=targets.shape[0])
        return out

    # -- planning -----------------------------------------------------------------------------
    def plan(
        self,
        snapshot: GraphSnapshot,
        point_map: PointMap | None,
        robots: dict[str, tuple[RobotState, ViewpointSet]],
    ) -> list[NbvGoal]:
        """Next goal for each robot in ``robots`` (goals of other robots stay claimed).

        The steps: forget the planned robots' old goals and remember their current views; build the
        panoramas every visibility test shares; for ``asp``, sample completions of the scene and realise
        them as hypotheses; then per robot (in id order, each goal claimed before the next robot is
        planned) pick a viewpoint and issue its goal."""
        t0, c0 = time.perf_counter(), time.process_time()
        self.info = PlanInfo(sampler=getattr(self.sampler, "name", ""))
        cands = self._begin(robots)
        ctx = self._context(point_map, cands)
        hyps = None
        if self.config.strategy == "asp":
            try:
                hyps = self._hypotheses(snapshot, robots, ctx)
            except Exception as e:  # noqa: BLE001 - a completion bug must not leave the robots without goals
                log.exception("asp's completions failed: this decision plans by frontiers (see)")
                self.info.hypotheses_error = f"{type(e).__name__}: {e}"
        goals: list[NbvGoal] = []
        for rid in sorted(robots):
            state, vps = robots[rid]
            goal = self._plan_robot(rid, state, vps, cands[rid], ctx, hyps, snapshot.version)
            if goal is not None:
                goals.append(goal)
        self.info.decision_s = time.perf_counter() - t0
        self.info.decision_cpu_s = time.process_time() - c0
        return goals

    def _begin(self, robots: dict[str, tuple[RobotState, ViewpointSet]]) -> dict[str, Candidates]:
        """Release the planned robots' goals and remember the views they stand at; their candidates."""
        for rid in robots:
            self.release(rid)
        cands = {rid: self._candidates(vps) for rid, (_, vps) in robots.items()}
        for state, vps in robots.values():
            self.record_view(np.asarray(state.T_world_cam), vps.intrinsics, vps.max_range_m)
        self.info.n_candidates = sum(c.size for c in cands.values())
        return cands

    def _context(self, point_map: PointMap | None, cands: dict[str, Candidates]) -> _PlanContext:
        """The map's occluders and one panorama per distinct camera position (candidates, remembered views,
        claimed goals, in that order), and the floor cells the map has seen."""
        vis = self.config.visibility
        if point_map is not None and point_map.points.size:
            pts = np.asarray(point_map.points, dtype=np.float64).reshape(-1, 3)
            pts = pts[np.all(np.isfinite(pts), axis=1)]
        else:
            pts = np.zeros((0, 3))
        occ = downsample_occluders(pts, vis.occluder_voxel_m, vis.max_occluder_points)
        rows = _Positions()
        cand_rows = {
            rid: np.array([rows.row(p) for p in c.positions], dtype=np.int64)[c.pos_index]
            for rid, c in cands.items()
        }
        hist_rows = [rows.row(v.T_world_cam[:3, 3]) for v in self.history]
        claim_rows = {rid: rows.row(T[:3, 3]) for rid, (_, T) in self.goals.items()}
        far = max([c.max_range_m for c in cands.values()] + [v.far_m for v in self.history] + [0.1])
        pano = Panoramas(rows.array(), occ, vis, far_m=far)
        self.info.panoramas_reused = pano.reuse(self._last_pano)
        self._last_pano = pano
        return _PlanContext(point_map, pts, pano, cand_rows, hist_rows, claim_rows, _floor_cells(pts))

    def _hypotheses(
        self, snapshot: GraphSnapshot, robots: dict[str, tuple[RobotState, ViewpointSet]], ctx: _PlanContext
    ) -> Hypotheses:
        """``asp``'s targets: completions of the unobserved scene sampled from the graph and the rooms the
        viewpoints name, realised as positioned hypotheses (those a past view would have seen, or standing on
        floor the map has seen, ruled out)."""
        acfg = self.config.asp
        all_vps = [vps for _, vps in robots.values()]
        room_names = [v.room for vps in all_vps for v in vps.viewpoints]
        xy = np.array([[v.x, v.y] for vps in all_vps for v in vps.viewpoints]).reshape(-1, 2)
        if self._map_rooms() is not None:
            assert self.rooms is not None
            rooms = rooms_from_layer(self.rooms, xy)
            self.info.room_source = "map"
        else:
            rooms = rooms_from_viewpoints(room_names, xy, self.prior)
            self.info.room_source = "viewpoints"
        scene_ctx = build_context(snapshot.nodes, snapshot.edges, rooms, self.prior, snapshot.version)
        completions = self.sampler.sample(scene_ctx, acfg.n_completions, self.rng)
        info = getattr(self.sampler, "info", None)
        self.info.sampler_fallback = bool(getattr(info, "fallback", False))

        def seen(targets: np.ndarray, sizes: np.ndarray) -> np.ndarray:
            out = np.asarray(
                self._history_detect(ctx.pano, ctx.hist_rows, targets, sizes, acfg.min_pixels, 0.05).any(axis=0)
            )
            if acfg.max_attempts > 0:
                tried = self._history_attempts(targets, sizes, acfg.min_pixels, self.config.see.attempt_range_frac)
                out = out | (tried >= acfg.max_attempts)
            return out

        hyps = realize(
            completions,
            scene_ctx,
            self.prior,
            n_jitter=acfg.n_jitter,
            jitter_m=acfg.jitter_m,
            proposals=acfg.proposals_per_object,
            detect_reject=acfg.detect_reject,
            seen=seen,
            floor_seen=ctx.floor_seen,
            rng=self.rng,
        )
        self.info.n_hypotheses = hyps.size
        self.info.hypotheses_by_room = dict(collections.Counter(r or "" for r in hyps.room))
        return hyps

    def _candidate_rooms(self, c: Candidates) -> tuple[str | None, ...]:
        """The room of each candidate in the rooms asp's hypotheses were placed in: the viewpoints' room names,
        or with the map's rooms (``info.room_source`` map) the map room its position lies in, else
        ``unexplored`` (as :func:`rooms_from_layer` groups viewpoints). The names of one source never match the
        other's: with the map's rooms every hypothesis was out of every candidate's room, and asp found no gain."""
        if self.info.room_source != "map" or self.rooms is None:
            return c.rooms
        return tuple(r or UNEXPLORED for r in room_of_points(c.xy_yaw[:, :2], self.rooms))

    def _map_rooms(self) -> RoomLayer | None:
        """The mapper's room layer when this plan uses it (config ``rooms``), else None."""
        src = self.config.rooms
        if src == "viewpoints" or self.rooms is None or (src == "auto" and not self.rooms.rooms):
            return None
        return self.rooms

    def _focus_mask(self, c: Candidates) -> np.ndarray | None:
        """Candidates inside the focus room (``focus_room``: an id, or a label's most confident room); None when
        there is no focus, no such room, or no candidate in it."""
        want = self.config.focus_room
        if not want or self.rooms is None:
            return None
        room = next((r for r in self.rooms.rooms if r.room_id == want), None)
        if room is None:
            same = [r for r in self.rooms.rooms if r.label == want]
            room = max(same, key=lambda r: (r.label_confidence, r.area_m2)) if same else None
        if room is None:
            return None
        inside = in_polygon(c.xy_yaw[:, :2], room.polygon)
        return inside if inside.any() else None

    def _frontier_targets(self, ctx: _PlanContext) -> np.ndarray:
        """``see``'s targets (computed once per plan, on first use): frontier points of the map that the
        remembered views have not already tried to see ``see.max_attempts`` times."""
        if ctx.frontier is None:
            pm, pts = ctx.point_map, ctx.points
            if pm is None or not pts.shape[0] or pm.points.shape[0] != pts.shape[0]:
                ctx.frontier = np.zeros((0, 3))
            else:
                f = pts[self._frontier(pm)]
                if f.shape[0]:
                    scfg = self.config.see
                    att = self._history_detect(
                        ctx.pano, ctx.hist_rows, f, None, 0.0, 0.1, scfg.attempt_range_frac
                    ).sum(axis=0)
                    f = f[att < scfg.max_attempts]
                ctx.frontier = f
            self.info.n_frontier = int(ctx.frontier.shape[0])
            if self.rooms is not None and ctx.frontier.shape[0]:
                where = room_of_points(ctx.frontier[:, :2], self.rooms)
                self.info.frontier_by_room = dict(collections.Counter(r or UNEXPLORED for r in where))
        return ctx.frontier

    def _plan_robot(
        self,
        rid: str,
        state: RobotState,
        vps: ViewpointSet,
        c: Candidates,
        ctx: _PlanContext,
        hyps: Hypotheses | None,
        graph_version: int,
    ) -> NbvGoal | None:
        """One robot's goal: its valid candidates (reachable, not blacklisted, not revisiting, away from the
        other robots' claims; all reachable ones if none is), the strategy's choice, the goal issued."""
        if c.size == 0:
            return None
        travel = self._travel(state, c)
        claimed = [(g, T) for r, (g, T) in self.goals.items() if r != rid]
        valid = self._valid(rid, c, travel, [np.array([g.x, g.y]) for g, _ in claimed])
        if not valid.any():
            valid = np.isfinite(travel)
            if not valid.any():
                return None
        focus = self._focus_mask(c)
        if focus is not None and (valid & focus).any():
            valid = valid & focus  # look around the focus room: its viewpoints only
        claim_T = np.stack([T for _, T in claimed]) if claimed else np.zeros((0, 4, 4))
        claim_r = np.array([ctx.claim_rows[r] for r in self.goals if r != rid], dtype=np.int64)
        rows = ctx.cand_rows[rid]
        idx: int | None = None
        prefix = ""
        if self.config.strategy == "asp" and hyps is not None:
            idx, gain, reason = self._choose_asp(c, rows, ctx.pano, hyps, travel, valid, claim_T, claim_r, vps)
            prefix = "asp fallback (no semantic gain): "
        if idx is None:
            idx, gain, reason = self._choose_see(
                c, rows, ctx.pano, self._frontier_targets(ctx), travel, valid, claim_T, claim_r, prefix=prefix
            )
        return self._issue(rid, c, idx, gain, reason, travel, ctx, graph_version)

    def _issue(
        self,
        rid: str,
        c: Candidates,
        idx: int,
        gain: float,
        reason: str,
        travel: np.ndarray,
        ctx: _PlanContext,
        graph_version: int,
    ) -> NbvGoal:
        """The goal on candidate ``idx``, claimed (for the robots planned after this one and later plans)."""
        self._n_goals += 1
        goal = NbvGoal(
            goal_id=f"{rid}-{self._n_goals}",
            robot_id=rid,
            stamp_ns=time.time_ns(),
            x=float(c.xy_yaw[idx, 0]),
            y=float(c.xy_yaw[idx, 1]),
            yaw_rad=float(c.xy_yaw[idx, 2]),
            vp_id=int(c.vp_ids[idx]),
            strategy=self.config.strategy,
            expected_gain=float(gain),
            reason=f"{reason}; travel {travel[idx]:.1f} m" + self._room_note(c.xy_yaw[idx, :2]),
            graph_version=graph_version,
        )
        self.goals[rid] = (goal, c.T_world_cam[idx])
        ctx.claim_rows[rid] = int(ctx.cand_rows[rid][idx])
        self.info.per_robot[rid] = {
            "gain": float(gain),
            "travel_m": float(travel[idx]),
            "vp_id": int(c.vp_ids[idx]),
            "reason": goal.reason,
        }
        return goal

    def _room_note(self, xy: np.ndarray) -> str:
        """``; in room3 (kitchen)`` for a goal inside a mapper room, ``; in unexplored space`` outside all."""
        if self.rooms is None or not self.rooms.rooms:
            return ""
        (rid,) = room_of_points(np.asarray(xy).reshape(1, 2), self.rooms)
        room = next((r for r in self.rooms.rooms if r.room_id == rid), None)
        return f"; in {room.room_id} ({room.label})" if room is not None else "; in unexplored space"

    def _claimed_mask(
        self,
        pano: Panoramas,
        claim_T: np.ndarray,
        claim_r: np.ndarray,
        K: np.ndarray,
        w: int,
        h: int,
        targets: np.ndarray,
        far: float,
        sizes: np.ndarray | None = None,
        min_px: float = 0.0,
    ) -> np.ndarray:
        if claim_T.shape[0] == 0 or targets.shape[0] == 0:
            return np.zeros(targets.shape[0], bool)
        return np.asarray(
            detect_matrix(claim_T, claim_r, pano, K, w, h, targets, far, self.config.visibility, sizes, min_px).any(
                axis=0
            )
        )

    def _choose_see(
        self,
        c: Candidates,
        rows: np.ndarray,
        pano: Panoramas,
        targets: np.ndarray,
        travel: np.ndarray,
        valid: np.ndarray,
        claim_T: np.ndarray,
        claim_r: np.ndarray,
        prefix: str = "",
    ) -> tuple[int, float, str]:
        scfg = self.config.see
        if targets.shape[0]:
            targets = targets[
                ~self._claimed_mask(pano, claim_T, claim_r, c.K, c.width, c.height, targets, c.max_range_m)
            ]
        score = np.zeros(c.size)
        if targets.shape[0]:
            sub = np.flatnonzero(valid)
            det = detect_matrix(
                c.T_world_cam[sub],
                rows[sub],
                pano,
                c.K,
                c.width,
                c.height,
                targets,
                c.max_range_m,
                self.config.visibility,
            )
            score[sub] = det.sum(axis=1)
        self.last_scores[c.robot_id] = score
        best = float(score[valid].max()) if valid.any() else 0.0
        if best <= 0.0:
            # No frontier left in reach: go where no view has been taken yet (coverage), nearest first.
            if self.history:
                Hp = np.stack([v.T_world_cam[:3, 3] for v in self.history])
                dist = np.min(np.linalg.norm(c.T_world_cam[:, None, :2, 3] - Hp[None, :, :2], axis=2), axis=1)
            else:
                dist = np.zeros(c.size)
            util = np.where(valid, dist - 0.1 * np.nan_to_num(travel, posinf=1e6), -np.inf)
            i = int(np.argmax(util))
            return (
                i,
                0.0,
                prefix + f"see: no frontier in view; coverage move ({dist[i]:.1f} m from past views)",
            )
        tie = valid & (score >= (1.0 - scfg.tie_tolerance) * best)
        i = int(np.flatnonzero(tie)[np.argmin(travel[tie])])
        return i, float(score[i]), prefix + f"see: {int(score[i])} frontier points in view (best {int(best)})"

    def _choose_asp(
        self,
        c: Candidates,
        rows: np.ndarray,
        pano: Panoramas,
        hyps: Hypotheses,
        travel: np.ndarray,
        valid: np.ndarray,
        claim_T: np.ndarray,
        claim_r: np.ndarray,
        vps: ViewpointSet,
    ) -> tuple[int | None, float, str]:
        acfg = self.config.asp
        if hyps.size == 0 or not valid.any():
            return None, 0.0, ""
        keep = ~self._claimed_mask(
            pano,
            claim_T,
            claim_r,
            c.K,
            c.width,
            c.height,
            hyps.xyz,
            c.max_range_m,
            hyps.size_m,
            acfg.min_pixels,
        )
        sub = np.flatnonzero(valid)
        V = detect_matrix(
            c.T_world_cam[sub],
            rows[sub],
            pano,
            c.K,
            c.width,
            c.height,
            hyps.xyz,
            c.max_range_m,
            self.config.visibility,
            hyps.size_m,
            acfg.min_pixels,
        )
        V &= keep[None, :]
        if not acfg.cross_room_visibility:
            cand_rooms = self._candidate_rooms(c)
            codes = {name: k for k, name in enumerate(sorted({r for r in (*cand_rooms, *hyps.room) if r}), start=1)}
            cand_room = np.array([codes.get(r or "", 0) for r in cand_rooms], dtype=np.int64)[sub]
            hyp_room = np.array([codes.get(r or "", 0) for r in hyps.room], dtype=np.int64)
            V &= (
                (cand_room[:, None] == hyp_room[None, :]) | (cand_room[:, None] == 0) | (hyp_room[None, :] == 0)
            )
        fn = joint_gain if acfg.observation == "joint" else factored_gain
        gain = np.zeros(c.size)  # candidates that are not valid see nothing: no gain (rows are independent)
        gain[sub] = fn(V, hyps.label_idx, hyps.sample_idx, len(hyps.labels), hyps.n_completions, hyps.n_jitter)
        self.last_scores[c.robot_id] = gain
        best = float(gain[valid].max())
        if best < acfg.min_gain_bits:
            return None, 0.0, ""
        penalty = acfg.travel_weight_per_m * best * np.nan_to_num(travel, posinf=1e6)
        util = np.where(valid, gain - penalty, -np.inf)
        i = int(np.argmax(util))
        row = V[int(np.searchsorted(sub, i))]
        seen_labels = sorted({hyps.labels[hyps.label_idx[j]] for j in np.flatnonzero(row)})[:4]
        return (
            i,
            float(gain[i]),
            (
                f"asp: {gain[i]:.2f} bits over {hyps.n_completions} completions"
                f" ({getattr(self.sampler, 'name', '')})"
                f", may see {', '.join(seen_labels)}"
            ),
        )


def _floor_cells(points: np.ndarray) -> np.ndarray:
    """Cell keys of the map points low enough to be floor."""
    floor_pts = points[points[:, 2] < FLOOR_MAX_Z_M] if points.shape[0] else points
    return np.unique(_cell_keys(floor_pts[:, :2])) if floor_pts.shape[0] else np.zeros(0, np.int64)


def _cell_keys(xy: np.ndarray) -> np.ndarray:
    ij = np.floor(np.asarray(xy, dtype=np.float64).reshape(-1, 2) / FLOOR_CELL_M).astype(np.int64) + (1 << 20)
    return (ij[:, 0] << 21) | ij[:, 1]
