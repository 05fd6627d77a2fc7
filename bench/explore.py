"""``argus explore``: closed-loop active exploration in the simulator, in-process, per-step JSON.

One episode: a simulated robot (sim.robot.SimRobot) starts at a seeded pose in a generated scene,
optional fixed cameras (sim.cameras) give one frame each at step 0, an in-process
mapper.core.MapperCore builds the graph, and planner.core.Planner picks each next view from the
robot's navigable viewpoints. After every step (one image at the reached viewpoint, as in the
paper) the graph is scored against the ground truth (sim.scoring.score_nodes).

Both strategies get the same candidates, travel costs (geodesic), perception, geometry and number
of steps (the budget); distance driven is reported too.

Several robots (``--robots N``): the team starts at a common dock (``team_starts``: robot 0 at the
seeded start, the others at the nearest navigable positions, headings spread around) and moves in
rounds. One wall step = one round: the planner assigns every robot a goal in one decision (its
multi-robot claims keep the goals apart), each robot drives there and maps its frames. Each robot's
goals, frames and metres are counted; the team's steps are the goals issued (N per wall step), so
recall is reported against wall steps, team steps and team metres, with steps to 50 % / 80 % recall.
The simulated robots do not block each other (no inter-robot collisions).

Example::

    argus explore --strategy see asp --steps 30 --seeds 0 --starts 3 --out explore.json
    argus explore --strategy asp --ext-cams 1 --geometry oracle --perception sim --steps 10
    argus explore --geometry mvs --move-frames 2 --steps 30 --starts 2   # RGB-only geometry needs baselines
    argus explore --robots 1 2 --geometry oracle --seeds 3,4 --starts 2 --out ex/team.json  # + team.md, team.png
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

import numpy as np

from sim.config import Family

if TYPE_CHECKING:
    from mapper.config import MapperCoreConfig

log = logging.getLogger("argus.explore")
ROBOT_ID = "robot0"
REPORT_STEPS = (0, 10, 20, 30)
RECALL_LEVELS = (0.5, 0.8)
DOCK_GAP_M = 0.6


def start_pose(viewpoints: list[Any], seed: int, start_index: int) -> tuple[float, float, float]:
    """A deterministic start pose (a navigable viewpoint position, random heading) per (seed, start)."""
    xy = sorted({(v.x, v.y) for v in viewpoints})
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(start_index), 0x57A7])
    x, y = xy[int(rng.integers(len(xy)))]
    return float(x), float(y), float(rng.uniform(-math.pi, math.pi))


def robot_ids(n: int) -> list[str]:
    """``robot0`` .. ``robot{n-1}`` (robot0 is the single robot of a one-robot episode)."""
    return [f"robot{k}" for k in range(n)]


def team_starts(
    first: tuple[float, float, float], xy: np.ndarray, geodesic_m: np.ndarray, n: int, gap_m: float = DOCK_GAP_M
) -> list[tuple[float, float, float]]:
    """Start poses of an ``n``-robot team at a common dock: robot 0 at ``first``; each further robot at the
    navigable position (rows of ``xy``) nearest to it along the floor (``geodesic_m``, inf: unreachable)
    that is at least ``gap_m`` from every robot already placed; headings spread evenly around ``first``'s."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    geo = np.asarray(geodesic_m, dtype=np.float64).reshape(-1)
    out = [(float(first[0]), float(first[1]), float(first[2]))]
    order = np.lexsort((xy[:, 1], xy[:, 0], geo))
    for k in range(1, n):
        placed = np.array([p[:2] for p in out])
        pick = next((int(i) for i in order if np.isfinite(geo[i])
                     and np.min(np.hypot(*(xy[i] - placed).T)) >= gap_m), None)
        if pick is None:
            raise ValueError(f"no room for robot {k} of {n} near the start (fewer free positions than robots)")
        yaw = (first[2] + 2.0 * math.pi * k / n + math.pi) % (2.0 * math.pi) - math.pi
        out.append((float(xy[pick, 0]), float(xy[pick, 1]), float(yaw)))
    return out


def travel_costs(nav: Any, xy: tuple[float, float], vp_xy: np.ndarray) -> np.ndarray:
    """Geodesic distance (metres) from ``xy`` to every viewpoint (inf: unreachable)."""
    field = nav.distances_from(xy)
    i = np.floor((vp_xy[:, 0] - field.origin_xy[0]) / field.cell_m).astype(int)
    j = np.floor((vp_xy[:, 1] - field.origin_xy[1]) / field.cell_m).astype(int)
    ok = (j >= 0) & (j < field.grid.shape[0]) & (i >= 0) & (i < field.grid.shape[1])
    out = np.full(vp_xy.shape[0], np.inf)
    out[ok] = field.grid[j[ok], i[ok]]
    return out


def _merged(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``update``'s leaves written over it (nested tables merged, not replaced)."""
    out = dict(base)
    for k, v in update.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def core_config(geometry: str, perception: str, torch_threads: int = 2) -> MapperCoreConfig:
    """The in-process mapper of the benchmarks: reconstructor ``geometry``, segmenter ``perception`` with its
    usual embedder (sim: sim, sam: clip, else classical). ``probe:<truth_at>`` names the ORACLE diagnostic
    ``probe`` backend with that option (e.g. ``probe:objects``)."""
    from mapper.config import MapperCoreConfig

    embedder = "sim" if perception == "sim" else ("clip" if perception == "sam" else "classical")
    backend, _, truth_at = geometry.partition(":")
    geo: dict[str, Any] = {"backend": backend}
    if truth_at:
        if backend != "probe":
            raise ValueError(f"geometry {geometry!r}: only probe takes an option after ':'")
        geo["options"] = {"truth_at": truth_at}
    return MapperCoreConfig.model_validate({
        "geometry": geo,
        "perception": {"segmenter": perception, "embedder": embedder},
        "torch_threads": torch_threads,
    })


def mapper_config(geometry: str, perception: str, torch_threads: int,
                  overrides: dict[str, Any] | None) -> MapperCoreConfig:
    """The episode's mapper configuration: :func:`core_config` with ``overrides`` (nested tables) written
    over it; pydantic's ValidationError on a bad override."""
    cfg = core_config(geometry, perception, torch_threads)
    return type(cfg).model_validate(_merged(cfg.model_dump(exclude_unset=True), overrides)) if overrides else cfg


@dataclass(frozen=True)
class Episode:
    """The parameters of one closed-loop episode (:func:`run_episode`'s keywords)."""

    family: str = "apartment"  # scene family (sim.config.Family)
    seed: int = 0  # scene seed; also seeds the start pose, the planner and the robots' odometry
    strategy: str = "asp"  # planner strategy: see or asp
    external_cameras: int = 0  # fixed cameras giving one frame each at step 0
    steps: int = 30  # wall steps (rounds of one goal per robot): the budget
    start_index: int = 0  # which seeded start pose
    geometry: str = "oracle"  # mapper reconstructor
    perception: str = "sim"  # mapper segmenter (its usual embedder with it)
    sampler: str = "prior"  # asp completion sampler
    torch_threads: int = 1
    odometry_noise: bool = False  # drifting odometry (default: exact poses)
    viewpoint_spacing_m: float = 0.6  # candidate viewpoint grid spacing
    n_headings: int = 8  # candidate headings per viewpoint position
    planner_overrides: dict[str, Any] | None = None  # nested PlannerConfig fields written over the defaults
    mapper_overrides: dict[str, Any] | None = None  # nested MapperCoreConfig fields written over core_config's
    score_every: int = 1  # score the graph every this many steps (and at the last)
    move_frames: int = 0  # also map the last n poses passed on the way to each goal (stereo for mvs)
    goal_capture_m: float = 0.0  # at each goal also map the views this far to the left and right
    robots: int = 1  # robots in the team


@dataclass
class _Bot:
    """One robot of the episode: its body, viewpoints and what it has cost and contributed."""

    rid: str
    robot: Any
    vps: Any
    capture_m: float = 0.0  # metres of goal-capture sidesteps (out and back)
    frames: int = 0  # frames it gave the mapper
    goals: int = 0  # goals it reached (drove to)

    @property
    def distance_m(self) -> float:
        return float(self.robot.distance_m) + self.capture_m


@dataclass
class _World:
    """The episode's simulated world: scene, renderer, floor map and the robots' candidate viewpoints."""

    scene: Any
    renderer: Any
    nav: Any
    intr: Any
    vps: Any  # ViewpointSet (robot0's; each robot gets a copy under its own id)
    vp_xy: np.ndarray  # (V, 2) viewpoint positions

    @classmethod
    def build(cls, ep: Episode) -> _World:
        from protocol.messages import Intrinsics, ViewpointSet
        from sim.nav import NavMap
        from sim.render import Renderer
        from sim.scene import generate_scene

        scene = generate_scene(ep.family, ep.seed)
        renderer = Renderer(scene)
        nav = NavMap(scene, renderer=renderer)
        intr = Intrinsics.from_fov(640, 480, 90.0)
        vps = ViewpointSet(
            robot_id=ROBOT_ID,
            camera_height_m=1.0,
            camera_pitch_deg=-15.0,
            intrinsics=intr,
            max_range_m=6.0,
            viewpoints=nav.viewpoints(ep.viewpoint_spacing_m, ep.n_headings),
        )
        vp_xy = np.array([[v.x, v.y] for v in vps.viewpoints], dtype=np.float64).reshape(-1, 2)
        return cls(scene, renderer, nav, intr, vps, vp_xy)

    def start_poses(self, ep: Episode) -> list[tuple[float, float, float]]:
        """The team's start poses: the seeded start, and for a team the dock around it (:func:`team_starts`)."""
        start = start_pose(self.vps.viewpoints, ep.seed, ep.start_index)
        if ep.robots == 1:
            return [start]
        dock_xy = np.array(sorted({(v.x, v.y) for v in self.vps.viewpoints}), dtype=np.float64)
        return team_starts(start, dock_xy, travel_costs(self.nav, start[:2], dock_xy), ep.robots)


class _Run:
    """An episode in progress: the robots, the in-process mapper and planner, and the step records."""

    def __init__(self, ep: Episode, world: _World, starts: list[tuple[float, float, float]]) -> None:
        from mapper.core import MapperCore
        from planner.config import PlannerConfig
        from planner.core import Planner
        from sim.robot import OdometryNoise, SimRobot

        self.ep, self.world = ep, world
        noise = None if ep.odometry_noise else OdometryNoise.none()
        self.bots = [
            _Bot(rid, SimRobot(world.scene, world.nav, xyyaw, world.intr, noise=noise, seed=ep.seed + 7919 * k,
                               renderer=world.renderer),
                 world.vps.model_copy(update={"robot_id": rid}))
            for k, (rid, xyyaw) in enumerate(zip(robot_ids(ep.robots), starts, strict=True))
        ]
        self.mapper = MapperCore(mapper_config(ep.geometry, ep.perception, ep.torch_threads, ep.mapper_overrides))
        self.planner = Planner(PlannerConfig.model_validate({
            "strategy": ep.strategy,
            "seed": ep.seed * 1000 + ep.start_index,
            "sampler": {"kind": ep.sampler},
            **(ep.planner_overrides or {}),
        }))
        self.labels = world.scene.labels()
        self.seq = 0
        self.records: list[dict[str, Any]] = []
        self.last_score = {"recall": 0.0, "precision": 0.0}
        from mapper.inbox import PriorAccuracy

        # The robots' odometry covariance becomes their views' prior accuracy as the mapper's intake makes it.
        self.accuracy = PriorAccuracy(max_sources=64)

    # -- frames into the mapper ---------------------------------------------------------------
    def ingest(self, rgb_out: Any, T_true: np.ndarray, T_prior: np.ndarray | None, source: str,
               trusted: bool = False, pose_covariance: np.ndarray | None = None) -> None:
        """Map one rendered view; ``trusted``: its pose is surveyed (a calibrated fixed camera), not odometry;
        ``pose_covariance``: the accuracy its header would declare (read as the mapper's intake reads it)."""
        from mapper.geometry.contract import OracleData, View

        oracle = OracleData(
            depth_m=rgb_out.depth_m.astype(np.float32),
            T_world_cam_true=np.asarray(T_true, float),
            instance_id=rgb_out.instance_id,
            labels=self.labels,
        )
        self.seq += 1
        accuracy = self.accuracy.fields(source, pose_covariance) if T_prior is not None else {}
        view = View(image=rgb_out.rgb, source_id=source, intrinsics=self.world.intr, T_world_cam=T_prior,
                    pose_trusted=trusted, stamp_ns=self.seq * 100_000_000, seq=self.seq, oracle=oracle,
                    **accuracy)  # type: ignore[arg-type]
        self.mapper.ingest(view, force_keyframe=True)

    def ingest_bot(self, bot: _Bot, rgb_out: Any, T_true: np.ndarray, T_odom: np.ndarray,
                   cov: np.ndarray | None = None) -> None:
        """Map one of ``bot``'s views; ``cov``: its odometry covariance when it was taken (default: now)."""
        self.ingest(rgb_out, T_true, T_odom, bot.rid,
                    pose_covariance=bot.robot.odometry_covariance() if cov is None else cov)
        bot.frames += 1

    def add_fixed_cameras(self) -> list[str]:
        """The external cameras' one frame each (before the robots' first); their ids."""
        if self.ep.external_cameras <= 0:
            return []
        from sim.cameras import place_fixed_cameras

        w = self.world
        ids = []
        for cam in place_fixed_cameras(w.scene, int(self.ep.external_cameras), self.ep.seed, w.intr,
                                       renderer=w.renderer):
            T = np.asarray(cam.T_world_cam, float)
            self.ingest(w.renderer.render(cam.intrinsics, T), T, T if cam.pose_known else None, cam.camera_id,
                        trusted=cam.pose_known)  # calibrated, as the edge camera marks it: single-view geometry
            if cam.pose_known:  # a surveyed camera's view is known to the planner (both strategies)
                self.planner.record_view(T, cam.intrinsics, w.vps.max_range_m)
            ids.append(cam.camera_id)
        return ids

    # -- one robot's moves --------------------------------------------------------------------
    def drive(self, bot: _Bot) -> None:
        """Drive to the goal; with ``move_frames`` > 0 also map the last n poses passed on the way (every
        0.3 m or 20 deg) before the arrival view: stereo baselines for RGB-only geometry."""
        n_frames = self.ep.move_frames
        robot = bot.robot
        passed: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        last = np.asarray(robot.T_world_cam_true())
        t = 0.0
        while robot.status == "moving" and t < 600.0:
            robot.step(0.1)
            t += 0.1
            T = np.asarray(robot.T_world_cam_true())
            moved = np.linalg.norm(T[:3, 3] - last[:3, 3])
            turned = np.degrees(np.arccos(np.clip(float(T[:3, 2] @ last[:3, 2]), -1.0, 1.0)))
            if n_frames > 0 and robot.status == "moving" and (moved >= 0.3 or turned >= 20.0):
                passed = [*passed, (T, np.asarray(robot.T_world_cam_odom()), robot.odometry_covariance())][-n_frames:]
                last = T
        for T_true, T_odom, cov in passed:
            self.ingest_bot(bot, self.world.renderer.render(self.world.intr, T_true), T_true, T_odom, cov)

    def capture(self, bot: _Bot) -> None:
        """At the goal, also map the views from the camera moved ``goal_capture_m`` to its left and to its
        right (where the robot can stand): a stereo baseline at the goal for RGB-only geometry. The
        sidesteps, out and back, count in the distance driven."""
        step_m, w = self.ep.goal_capture_m, self.world
        T_true, T_odom = np.asarray(bot.robot.T_world_cam_true()), np.asarray(bot.robot.T_world_cam_odom())
        side = T_true[:3, 0].copy()
        side[2] = 0.0
        side /= max(float(np.linalg.norm(side)), 1e-9)
        for sign in (-1.0, 1.0):
            off = sign * step_m * side
            if not w.nav.is_free(float(T_true[0, 3] + off[0]), float(T_true[1, 3] + off[1])):
                continue
            Tt, To = T_true.copy(), T_odom.copy()
            Tt[:3, 3] += off
            To[:3, 3] += off
            self.ingest_bot(bot, w.renderer.render(w.intr, Tt), Tt, To)
            bot.capture_m += 2.0 * step_m

    def arrive(self, bot: _Bot) -> None:
        """The view at the reached pose (one image per step, as in the paper)."""
        self.ingest_bot(bot, bot.robot.render(), bot.robot.T_world_cam_true(), bot.robot.T_world_cam_odom())

    # -- planning -----------------------------------------------------------------------------
    def state_of(self, bot: _Bot, step: int) -> Any:
        """What the planner knows of a robot: its odometry pose and geodesic travel costs to every viewpoint."""
        from protocol.messages import RobotState, rows

        x, y, yaw = bot.robot.pose_odom()
        return RobotState(
            robot_id=bot.rid,
            stamp_ns=time.time_ns(),
            status="arrived",
            x=x,
            y=y,
            yaw_rad=yaw,
            T_world_cam=rows(bot.robot.T_world_cam_odom()),
            distance_m=bot.robot.distance_m,
            steps=step - 1,
            travel_cost_m=travel_costs(self.world.nav, bot.robot.pose_true()[:2], self.world.vp_xy),
        )

    def assign(self, step: int) -> tuple[dict[str, Any], float, float]:
        """One round's goals: every robot planned in one decision; a robot whose goal it cannot drive to
        gets that viewpoint blacklisted and is planned again alone (the others' goals stay claimed).
        Each robot given a goal starts driving; returns the goals by robot and the planner's wall and CPU seconds."""
        by_id = {b.rid: b for b in self.bots}
        pending = list(by_id)
        chosen: dict[str, Any] = {}
        decision_s = decision_cpu_s = 0.0
        for _attempt in range(5):
            if not pending:
                break
            plan = {rid: (self.state_of(by_id[rid], step), by_id[rid].vps) for rid in pending}
            goals = {g.robot_id: g for g in self.planner.plan(self.mapper.snapshot(), self.mapper.point_map(), plan)}
            decision_s += self.planner.info.decision_s
            decision_cpu_s += self.planner.info.decision_cpu_s
            retry = []
            for rid in pending:
                g = goals.get(rid)
                if g is None:
                    continue  # nothing to do for this robot this round
                if by_id[rid].robot.drive_to(g.x, g.y, g.yaw_rad):
                    chosen[rid] = g
                    by_id[rid].goals += 1
                else:
                    self.planner.mark_failed(rid, g.vp_id)
                    retry.append(rid)
            pending = retry
        return chosen, decision_s, decision_cpu_s

    # -- the loop -----------------------------------------------------------------------------
    def start(self) -> None:
        """Step 0: each robot's view at its start pose, then the first record."""
        for b in self.bots:
            self.arrive(b)
        self.record(0, {}, 0.0, 0.0)

    def step(self, step: int) -> float:
        """One wall step: goals for the team, each robot drives (mapping on the way and at the goal), record;
        returns the planner's seconds."""
        chosen, decision_s, decision_cpu_s = self.assign(step)
        for b in self.bots:
            if b.rid in chosen:
                self.drive(b)
                if self.ep.goal_capture_m > 0:
                    self.capture(b)
            self.arrive(b)
        self.record(step, chosen, decision_s, decision_cpu_s)
        return decision_s

    def record(self, step: int, chosen: dict[str, Any], decision_s: float, decision_cpu_s: float) -> None:
        """The step's record: graph size, recall / precision (scored every ``score_every`` steps and at the
        last), the team's metres and each robot's goal, gain, reason, metres, frames and goals."""
        from sim.scoring import score_nodes

        snap = self.mapper.snapshot()
        if step % max(1, self.ep.score_every) == 0 or step == self.ep.steps:
            s = score_nodes(snap.nodes, self.world.scene)
            self.last_score.update(recall=float(s.recall), precision=float(s.precision))
        per = {
            b.rid: {
                "goal": _goal_xyyaw(chosen.get(b.rid)),
                "gain": round(float(chosen[b.rid].expected_gain), 4) if b.rid in chosen else 0.0,
                "reason": chosen[b.rid].reason if b.rid in chosen else ("start" if step == 0 else "no goal"),
                "distance_m": round(b.distance_m, 3),
                "frames": b.frames,
                "goals": b.goals,
            }
            for b in self.bots
        }
        first = per[self.bots[0].rid]
        self.records.append({
            "step": step,
            "team_steps": step * len(self.bots),
            "n_nodes": len(snap.nodes),
            "recall": self.last_score["recall"],
            "precision": self.last_score["precision"],
            "distance_m": round(sum(b.distance_m for b in self.bots), 3),
            "decision_s": round(decision_s, 4),
            "decision_cpu_s": round(decision_cpu_s, 4),
            "gain": first["gain"],
            "goal": first["goal"],
            "reason": first["reason"],
            "robots": per,
        })


def steps_to(recall: Sequence[float], level: float) -> int | None:
    """The first step at which ``recall`` reaches ``level`` (None: never)."""
    return next((i for i, v in enumerate(recall) if v >= level), None)


def run_episode(
    episode: Episode | None = None, /, *, log_fn: Callable[[str], None] | None = None, **params: Any
) -> dict[str, Any]:
    """One closed-loop episode; returns ``{"steps": [{step, team_steps, n_nodes, recall, ...}], ...}``.

    ``episode`` (default :class:`Episode`'s defaults) with ``params`` (Episode's fields by name) written
    over it. Step 0 is the state after the start views (and the fixed cameras' frames); step k (a wall
    step) after k rounds in which each of the ``robots`` robots got a goal. ``distance_m`` is the team's
    metres; ``goal`` / ``gain`` / ``reason`` are robot0's, ``robots`` has each robot's goal, metres and frames.
    """
    import torch

    ep = replace(episode or Episode(), **params)
    if ep.robots < 1:
        raise ValueError("robots must be >= 1")
    torch.set_num_threads(max(1, int(ep.torch_threads)))
    say = log_fn or (lambda s: log.info("%s", s))
    t_start = time.perf_counter()
    world = _World.build(ep)
    starts = world.start_poses(ep)
    run = _Run(ep, world, starts)
    external_ids = run.add_fixed_cameras()
    run.start()
    say(
        f"{ep.strategy} seed {ep.seed} start {ep.start_index}: {len(world.scene.objects)} objects, "
        f"{len(world.vps.viewpoints)} candidates, {len(run.bots)} robot(s); step 0 nodes "
        f"{run.records[0]['n_nodes']} recall {run.records[0]['recall']:.3f}"
    )
    for step in range(1, ep.steps + 1):
        decision_s = run.step(step)
        r = run.records[-1]
        say(
            f"  step {step:2d}: nodes {r['n_nodes']:3d} recall {r['recall']:.3f} dist {r['distance_m']:.1f} m "
            f"decide {decision_s:.2f} s (CPU {r['decision_cpu_s']:.2f}) | "
            + " | ".join(f"{rid}: {p['reason']}" for rid, p in r["robots"].items())
        )
    return {
        "family": ep.family,
        "seed": ep.seed,
        "strategy": ep.strategy,
        "external_cameras": int(ep.external_cameras),
        "robots": len(run.bots),
        "start_index": ep.start_index,
        "start": list(starts[0]),
        "starts": [list(p) for p in starts],
        "geometry": ep.geometry,
        "perception": ep.perception,
        "sampler": ep.sampler,
        "n_true": len(world.scene.objects),
        "n_rooms": len(world.scene.rooms),
        "n_candidates": len(world.vps.viewpoints),
        "external_ids": external_ids,
        "seconds": round(time.perf_counter() - t_start, 2),
        "steps": run.records,
    }


def _goal_xyyaw(goal: Any) -> list[float] | None:
    return None if goal is None else [round(goal.x, 3), round(goal.y, 3), round(goal.yaw_rad, 3)]


def _team_steps(ep: dict[str, Any], rec: dict[str, Any]) -> int:
    """The team's steps (goals issued) at a step record; older records without the field: one robot."""
    return int(rec.get("team_steps", rec["step"] * int(ep.get("robots", 1))))


def recall_at_team_steps(ep: dict[str, Any], k: int) -> float | None:
    """Recall after the team has taken ``k`` steps (the last wall step within them); None past the episode."""
    recs = ep["steps"]
    if not recs or _team_steps(ep, recs[-1]) < k:
        return None
    return float([r for r in recs if _team_steps(ep, r) <= k][-1]["recall"])


def reach(ep: dict[str, Any], level: float) -> dict[str, Any] | None:
    """When an episode's recall first reaches ``level``: wall step, team steps and team metres (None: never)."""
    recs = ep["steps"]
    i = steps_to([r["recall"] for r in recs], level)
    if i is None:
        return None
    return {"wall": int(recs[i]["step"]), "team": _team_steps(ep, recs[i]), "metres": float(recs[i]["distance_m"])}


def summarize(
    episodes: list[dict[str, Any]], at_steps: tuple[int, ...] = REPORT_STEPS
) -> list[dict[str, Any]]:
    """Per method (strategy, external cameras, robots): mean and std over episodes of node count, recall and
    the team's metres at the given wall steps, recall at the same numbers of team steps, when each episode
    reached 50 % / 80 % recall, and each robot's metres and frames at the end."""

    groups: dict[tuple[str, int, int], list[dict[str, Any]]] = {}
    for ep in episodes:
        groups.setdefault((ep["strategy"], ep["external_cameras"], int(ep.get("robots", 1))), []).append(ep)
    rows = []
    for (strategy, ext, n_robots), eps in sorted(groups.items()):
        row: dict[str, Any] = {
            "strategy": strategy,
            "external_cameras": ext,
            "robots": n_robots,
            "episodes": len(eps),
            "n_true_mean": float(np.mean([e["n_true"] for e in eps])),
        }
        for k in at_steps:
            recs = [e["steps"][min(k, len(e["steps"]) - 1)] for e in eps]
            for key in ("n_nodes", "recall", "distance_m"):
                v = np.array([r[key] for r in recs], float)
                row[f"{key}@{k}"] = [float(v.mean()), float(v.std())]
            team = [recall_at_team_steps(e, k) for e in eps]
            known = [t for t in team if t is not None]
            row[f"recall@team{k}"] = (
                None if len(known) < len(team) else [float(np.mean(known)), float(np.std(known))]
            )
        n_steps = min(len(e["steps"]) for e in eps)
        mean_curve = np.mean([[r["recall"] for r in e["steps"][:n_steps]] for e in eps], axis=0)
        row["recall_mean"] = [float(v) for v in mean_curve]
        row["distance_mean"] = [float(np.mean([e["steps"][i]["distance_m"] for e in eps])) for i in range(n_steps)]
        for level in RECALL_LEVELS:
            tag = f"{int(round(100 * level))}%"
            row[f"to{tag}"] = {
                "mean_curve_wall": steps_to(mean_curve, level),
                "runs": [reach(e, level) for e in eps],
            }
        per = [e["steps"][-1].get("robots") for e in eps]
        if all(per):
            rids = sorted(per[0])
            row["robot_distance_m"] = {rid: float(np.mean([p[rid]["distance_m"] for p in per])) for rid in rids}
            row["robot_frames"] = {rid: float(np.mean([p[rid]["frames"] for p in per])) for rid in rids}
        elif n_robots == 1:  # records written before per-robot counts: the one robot drove the team's metres
            row["robot_distance_m"] = {ROBOT_ID: float(np.mean([e["steps"][-1]["distance_m"] for e in eps]))}
        row.update(decision_stats(eps))
        rows.append(row)
    return rows


def decision_stats(eps: list[dict[str, Any]]) -> dict[str, float | None]:
    """The planner's seconds per wall step (its decisions of the round, goal retries included) over the episodes'
    steps after the first: wall mean / p50 / p95 / max and CPU mean / p95 (None in records without CPU)."""
    recs = [r for e in eps for r in e["steps"][1:]]
    dec = np.array([r["decision_s"] for r in recs], float)
    cpu = np.array([r["decision_cpu_s"] for r in recs if "decision_cpu_s" in r], float)
    out: dict[str, float | None] = {
        "decision_s_mean": float(dec.mean()) if dec.size else 0.0,
        "decision_s_p50": float(np.percentile(dec, 50)) if dec.size else 0.0,
        "decision_s_p95": float(np.percentile(dec, 95)) if dec.size else 0.0,
        "decision_s_max": float(dec.max()) if dec.size else 0.0,
    }
    full = cpu.size == dec.size and cpu.size > 0
    out["decision_cpu_s_mean"] = float(cpu.mean()) if full else None
    out["decision_cpu_s_p95"] = float(np.percentile(cpu, 95)) if full else None
    return out


def _decide_text(r: dict[str, Any]) -> str:
    """The decide column: wall mean (p95, max) and, where recorded, CPU mean (p95)."""
    p95 = r.get("decision_s_p95", r["decision_s_max"])  # rows summarised before p95 was kept: the max
    text = f"{r['decision_s_mean']:.2f} (p95 {p95:.2f}, max {r['decision_s_max']:.2f})"
    if r.get("decision_cpu_s_mean") is not None:
        text += f"; CPU {r['decision_cpu_s_mean']:.2f} (p95 {r['decision_cpu_s_p95']:.2f})"
    return text


def _reach_text(row: dict[str, Any], tag: str, key: str) -> str:
    """``k/n`` runs that reached the level, and the range of steps (or metres) they needed."""
    runs = row[f"to{tag}"]["runs"]
    got = sorted(r[key] for r in runs if r is not None)
    if not got:
        return f"0/{len(runs)}"
    fmt = (lambda v: f"{v:.0f}") if key == "metres" else str
    span = fmt(got[0]) if got[0] == got[-1] else f"{fmt(got[0])}-{fmt(got[-1])}"
    return f"{len(got)}/{len(runs)}: {span}"


def markdown(rows: list[dict[str, Any]], at_steps: tuple[int, ...] = REPORT_STEPS) -> str:
    """Two tables: node count and recall per wall step; then the team view (recall per team step, steps and
    metres to 50 % / 80 % recall, each robot's metres and frames)."""
    head = (
        "| method | "
        + " | ".join(f"nodes@{k}" for k in at_steps)
        + " | "
        + " | ".join(f"recall@{k}" for k in at_steps)
        + f" | dist@{at_steps[-1]} m | decide s: mean (p95, max); CPU s |"
    )
    out = [head, "|" + "---|" * (2 + 2 * len(at_steps) + 1)]
    for r in rows:
        nodes = " | ".join("{:.1f} ± {:.1f}".format(*r[f"n_nodes@{k}"]) for k in at_steps)
        rec = " | ".join("{:.3f} ± {:.3f}".format(*r[f"recall@{k}"]) for k in at_steps)
        dist = "{:.1f} ± {:.1f}".format(*r[f"distance_m@{at_steps[-1]}"])
        out.append(
            f"| {_method(r)} (n={r['episodes']}, GT {r['n_true_mean']:.0f}) | {nodes} | {rec} | {dist} | "
            f"{_decide_text(r)} |"
        )
    team_k = [k for k in at_steps if k > 0]
    out += [
        "",
        "| method | "
        + " | ".join(f"recall@team {k}" for k in team_k)
        + " | wall steps to 50 % | to 80 % | team steps to 50 % | to 80 % | team m to 50 % | to 80 % "
        "| m per robot | frames per robot |",
        "|" + "---|" * (1 + len(team_k) + 8),
    ]
    for r in rows:
        team = " | ".join(
            "-" if r.get(f"recall@team{k}") is None else "{:.3f} ± {:.3f}".format(*r[f"recall@team{k}"])
            for k in team_k
        )
        reached = " | ".join(_reach_text(r, tag, key) for key in ("wall", "team", "metres") for tag in ("50%", "80%"))
        dist = ", ".join(f"{v:.0f}" for v in r.get("robot_distance_m", {}).values()) or "-"
        frames = ", ".join(f"{v:.0f}" for v in r.get("robot_frames", {}).values()) or "-"
        out.append(f"| {_method(r)} | {team} | {reached} | {dist} | {frames} |")
    out += [
        "",
        "Steps to a recall level: runs that reached it / runs, and the range over those runs. A wall step is one "
        "round (one goal per robot); team steps count every robot's goals; metres are the team's (goal-capture "
        "sidesteps included).",
    ]
    return "\n".join(out)


def _method(r: dict[str, Any]) -> str:
    n = int(r.get("robots", 1))
    return r["strategy"].upper() + (" + Ext" if r["external_cameras"] else "") + (f" x{n} robots" if n > 1 else "")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Mean recall against wall steps, the team's steps and the team's metres, one curve per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    colours = {s: f"C{i}" for i, s in enumerate(dict.fromkeys(r["strategy"] for r in rows))}
    for r in rows:
        m = np.array(r["recall_mean"])
        wall = np.arange(len(m))
        style = ["-", "--", ":", "-."][(int(r.get("robots", 1)) - 1) % 4]
        kw = {"color": colours[r["strategy"]], "linestyle": style, "label": _method(r),
              "alpha": 0.6 if r["external_cameras"] else 1.0}
        axes[0].plot(wall, m, **kw)
        axes[1].plot(wall * int(r.get("robots", 1)), m, **kw)
        axes[2].plot(r["distance_mean"], m, **kw)
    for ax, xl in zip(axes, ("wall step (one goal per robot)", "team steps (goals issued)",
                             "team metres driven"), strict=True):
        ax.set_xlabel(xl)
        ax.set_ylabel("recall")
        ax.xaxis.get_major_locator().set_params(integer=True)
        ax.set_ylim(0, 1)
        for level in RECALL_LEVELS:
            ax.axhline(level, color="0.8", linewidth=0.8, zorder=0)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(data: dict[str, Any], out: Path, at_steps: tuple[int, ...], command: str = "") -> list[Path]:
    """``out`` (JSON with ``summary`` and ``episodes``), and beside it ``.md`` and ``.png``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1))
    eps = data["episodes"]

    def values(key: str) -> str:
        return ", ".join(sorted({str(e.get(key, "?")) for e in eps}))

    head = (f"# argus explore\n\n`{command}`\n\n" if command else "# argus explore\n\n") + (
        f"Family {values('family')}; seeds {values('seed')}; geometry {values('geometry')}; 2D perception "
        f"{values('perception')} (sim: ORACLE masks and labels); objects {values('n_true')}.\n\n"
    )
    md, png = out.with_suffix(".md"), out.with_suffix(".png")
    md.write_text(head + markdown(data["summary"], at_steps) + "\n")
    plot(data["summary"], png)
    return [out, md, png]


def report_steps(steps: int) -> tuple[int, ...]:
    """The wall steps the tables report: those of REPORT_STEPS within the budget, and the last step."""
    return tuple(sorted({k for k in REPORT_STEPS if k <= steps} | {max(0, int(steps))}))


def _ints(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part.strip()[1:]:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part.strip():
            out.append(int(part))
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus explore",
        description="Closed-loop exploration in the simulator (robot, cameras, mapper, planner in-process).",
        epilog="examples:\n  argus explore --strategy see asp --steps 30 --seeds 0 --starts 3 --out ex.json\n"
        "  argus explore --strategy asp --ext-cams 1 --steps 10 --geometry oracle --perception sim\n"
        "  argus explore --robots 1 2 --seeds 3,4 --starts 2 --out ex/team.json   # + ex/team.md, ex/team.png\n"
        "  argus explore --family apartment_large --robots 2 --steps 30 --seeds 0 --starts 1",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--strategy", nargs="+", choices=["see", "asp"], default=["see", "asp"], help="strategies")
    p.add_argument(
        "--ext-cams",
        nargs="+",
        type=int,
        default=[0],
        choices=[0, 1, 2, 3],
        help="fixed external cameras giving one frame at step 0 (several values: one run each)",
    )
    p.add_argument("--steps", type=int, default=30, help="goals per episode (the budget)")
    p.add_argument("--seeds", default="0", help="scene seeds, e.g. 0,1 or 0-2")
    p.add_argument("--starts", type=int, default=3, help="number of start poses (indices 0..N-1)")
    p.add_argument("--start-list", default=None, help="explicit start indices instead, e.g. 0,4,5")
    p.add_argument(
        "--family",
        default="apartment",
        choices=list(get_args(Family)),
        help="scene family (apartment_large: 7-9 rooms, ~150-190 objects; see argus sim)",
    )
    p.add_argument(
        "--robots",
        nargs="+",
        type=int,
        default=[1],
        help="robots in the team (several values: one run each), e.g. --robots 1 2",
    )
    p.add_argument("--geometry", default="oracle", choices=["oracle", "mvs"], help="mapper geometry backend")
    p.add_argument("--perception", default="sim", choices=["sim"], help="2D perception (sim: ORACLE masks)")
    p.add_argument("--sampler", default="prior", choices=["prior", "llm"], help="asp completion sampler")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--odometry-noise", action="store_true", help="drifting odometry (default: exact poses)")
    p.add_argument(
        "--move-frames",
        type=int,
        default=0,
        help="also map the last N poses passed on the way to each goal (stereo for --geometry mvs)",
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="planner config override, e.g. --set asp.travel_weight_per_m=0.03",
    )
    p.add_argument(
        "--goal-capture",
        type=float,
        default=0.0,
        metavar="M",
        help="at each goal also map the views M metres to the left and right (sidesteps, counted in the distance): "
        "a stereo baseline at the goal for --geometry mvs",
    )
    p.add_argument(
        "--mapper-set",
        dest="mapper_overrides",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="mapper config override, e.g. --mapper-set single_view.untrusted_poses=true (see argus mapper --describe)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="write the JSON here, the Markdown tables and the recall plot beside it (.md, .png)",
    )
    p.add_argument(
        "--report",
        type=Path,
        nargs="+",
        default=None,
        metavar="JSON",
        help="run nothing: summarise the episodes of earlier --out JSONs again, together (e.g. a 1-robot and a "
        "2-robot run); writes --out (default: over the first)",
    )
    p.add_argument("--quiet", action="store_true", help="no per-step lines")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    from protocol.tomlconfig import ConfigError, parse_value, set_path

    overrides: dict[str, Any] = {}
    mapper_overrides: dict[str, Any] = {}
    try:
        for target, items in ((overrides, a.overrides), (mapper_overrides, a.mapper_overrides)):
            for item in items:
                path, sep, text = item.partition("=")
                if not sep:
                    raise ConfigError(f"override {item!r} is not of the form path=value")
                set_path(target, path.strip(), parse_value(text.strip()))
    except ConfigError as e:
        print(f"argus explore: {e}", file=sys.stderr)
        return 2
    if mapper_overrides:
        from pydantic import ValidationError

        try:
            mapper_config(a.geometry, a.perception, a.threads, mapper_overrides)
        except ValidationError as e:
            bad = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
            print(f"argus explore: bad --mapper-set: {bad}", file=sys.stderr)
            return 2
    starts = _ints(a.start_list) if a.start_list else list(range(a.starts))
    at_steps = report_steps(a.steps)
    if a.report is not None:
        return _rereport(a.report, a.out or a.report[0], at_steps)
    if any(n < 1 for n in a.robots):
        print("argus explore: --robots must be >= 1", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    def say(s: str) -> None:
        if not a.quiet:
            print(s, flush=True)

    base = Episode(family=a.family, steps=a.steps, geometry=a.geometry, perception=a.perception, sampler=a.sampler,
                   torch_threads=a.threads, odometry_noise=a.odometry_noise, move_frames=a.move_frames,
                   goal_capture_m=a.goal_capture, planner_overrides=overrides, mapper_overrides=mapper_overrides)
    episodes = [
        run_episode(base, seed=seed, external_cameras=ext, robots=n_robots, strategy=strategy, start_index=start,
                    log_fn=say)
        for seed in _ints(a.seeds) for ext in a.ext_cams for n_robots in a.robots for strategy in a.strategy
        for start in starts
    ]
    rows = summarize(episodes, at_steps)
    print(markdown(rows, at_steps))
    if a.out is not None:
        command = "argus explore " + " ".join(sys.argv[1:] if argv is None else argv)
        for path in write_outputs({"summary": rows, "episodes": episodes}, a.out, at_steps, command):
            print(f"wrote {path}")
    return 0


def _rereport(sources: list[Path], out: Path, at_steps: tuple[int, ...]) -> int:
    """``--report``: the summary, tables and plot of earlier runs' episodes, recomputed together."""
    episodes: list[dict[str, Any]] = []
    try:
        for src in sources:
            episodes += json.loads(src.read_text())["episodes"]
        rows = summarize(episodes, at_steps)
    except (OSError, ValueError, KeyError, TypeError) as e:
        print(f"argus explore: cannot read episodes from {', '.join(map(str, sources))}: {e}", file=sys.stderr)
        return 2
    print(markdown(rows, at_steps))
    command = "argus explore --report " + " ".join(map(str, sources))
    for path in write_outputs({"summary": rows, "episodes": episodes}, out, at_steps, command):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
