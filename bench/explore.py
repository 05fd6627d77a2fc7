"""``argus explore``: closed-loop active exploration in the simulator, in-process, per-step JSON.

One episode: a simulated robot (sim.robot.SimRobot) starts at a seeded pose in a generated scene,
optional fixed cameras (sim.cameras) give one frame each at step 0, an in-process
mapper.core.MapperCore builds the graph, and planner.core.Planner picks each next view from the
robot's navigable viewpoints. After every step (one image at the reached viewpoint, as in the
paper) the graph is scored against the ground truth (sim.scoring.score_nodes).

Both strategies get the same candidates, travel costs (geodesic), perception, geometry and number
of steps (the budget); distance driven is reported too.

Example::

    argus explore --strategy see asp --steps 30 --seeds 0 --starts 3 --out explore.json
    argus explore --strategy asp --ext-cams 1 --geometry oracle --perception sim --steps 10
    argus explore --geometry mvs --move-frames 2 --steps 30 --starts 2   # RGB-only geometry needs baselines
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from mapper.config import MapperCoreConfig

log = logging.getLogger("argus.explore")
ROBOT_ID = "robot0"
REPORT_STEPS = (0, 10, 20, 30)


def start_pose(viewpoints: list[Any], seed: int, start_index: int) -> tuple[float, float, float]:
    """A deterministic start pose (a navigable viewpoint position, random heading) per (seed, start)."""
    xy = sorted({(v.x, v.y) for v in viewpoints})
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(start_index), 0x57A7])
    x, y = xy[int(rng.integers(len(xy)))]
    return float(x), float(y), float(rng.uniform(-math.pi, math.pi))


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
    usual embedder (sim: sim, sam: clip, else classical)."""
    from mapper.config import MapperCoreConfig

    embedder = "sim" if perception == "sim" else ("clip" if perception == "sam" else "classical")
    return MapperCoreConfig.model_validate({
        "geometry": {"backend": geometry},
        "perception": {"segmenter": perception, "embedder": embedder},
        "torch_threads": torch_threads,
    })


def mapper_config(geometry: str, perception: str, torch_threads: int,
                  overrides: dict[str, Any] | None) -> MapperCoreConfig:
    """The episode's mapper configuration: :func:`core_config` with ``overrides`` (nested tables) written
    over it; pydantic's ValidationError on a bad override."""
    cfg = core_config(geometry, perception, torch_threads)
    return type(cfg).model_validate(_merged(cfg.model_dump(exclude_unset=True), overrides)) if overrides else cfg


def run_episode(
    family: str = "apartment",
    seed: int = 0,
    strategy: str = "asp",
    external_cameras: int = 0,
    steps: int = 30,
    start_index: int = 0,
    geometry: str = "oracle",
    perception: str = "sim",
    sampler: str = "prior",
    torch_threads: int = 1,
    odometry_noise: bool = False,
    viewpoint_spacing_m: float = 0.6,
    n_headings: int = 8,
    planner_overrides: dict[str, Any] | None = None,
    mapper_overrides: dict[str, Any] | None = None,
    score_every: int = 1,
    move_frames: int = 0,
    goal_capture_m: float = 0.0,
    log_fn: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """One closed-loop episode; returns ``{"steps": [{step, n_nodes, recall, ...}], ...}``.

    Step 0 is the state after the start view (and the fixed cameras' frames); step k after k goals.
    """
    import torch

    from mapper.core import MapperCore
    from mapper.geometry.contract import OracleData, View
    from planner.config import PlannerConfig
    from planner.core import Planner
    from protocol.messages import Intrinsics, RobotState, ViewpointSet, rows
    from sim.nav import NavMap
    from sim.render import Renderer
    from sim.robot import OdometryNoise, SimRobot
    from sim.scene import generate_scene
    from sim.scoring import score_nodes

    torch.set_num_threads(max(1, int(torch_threads)))
    say = log_fn or (lambda s: log.info("%s", s))
    t_start = time.perf_counter()
    scene = generate_scene(family, seed)
    renderer = Renderer(scene)
    nav = NavMap(scene, renderer=renderer)
    intr = Intrinsics.from_fov(640, 480, 90.0)
    vps = ViewpointSet(
        robot_id=ROBOT_ID,
        camera_height_m=1.0,
        camera_pitch_deg=-15.0,
        intrinsics=intr,
        max_range_m=6.0,
        viewpoints=nav.viewpoints(viewpoint_spacing_m, n_headings),
    )
    vp_xy = np.array([[v.x, v.y] for v in vps.viewpoints], dtype=np.float64).reshape(-1, 2)
    start = start_pose(vps.viewpoints, seed, start_index)
    robot = SimRobot(
        scene,
        nav,
        start,
        intr,
        noise=None if odometry_noise else OdometryNoise.none(),
        seed=seed,
        renderer=renderer,
    )
    mapper = MapperCore(mapper_config(geometry, perception, torch_threads, mapper_overrides))
    pcfg = PlannerConfig.model_validate(
        {
            "strategy": strategy,
            "seed": seed * 1000 + start_index,
            "sampler": {"kind": sampler},
            **(planner_overrides or {}),
        }
    )
    planner = Planner(pcfg)
    labels = scene.labels()
    seq = [0]

    def ingest(rgb_out: Any, T_true: np.ndarray, T_prior: np.ndarray | None, source: str,
               trusted: bool = False) -> None:
        """Map one rendered view; ``trusted``: its pose is surveyed (a calibrated fixed camera), not odometry."""
        oracle = OracleData(
            depth_m=rgb_out.depth_m.astype(np.float32),
            T_world_cam_true=np.asarray(T_true, float),
            instance_id=rgb_out.instance_id,
            labels=labels,
        )
        seq[0] += 1
        view = View(
            image=rgb_out.rgb,
            source_id=source,
            intrinsics=intr,
            T_world_cam=T_prior,
            pose_trusted=trusted,
            stamp_ns=seq[0] * 100_000_000,
            seq=seq[0],
            oracle=oracle,
        )
        mapper.ingest(view, force_keyframe=True)

    def drive(n_frames: int) -> None:
        """Drive to the goal; with ``n_frames`` > 0 also map the last n poses passed on the way (every
        0.3 m or 20 deg) before the arrival view: stereo baselines for RGB-only geometry."""
        passed: list[tuple[np.ndarray, np.ndarray]] = []
        last = np.asarray(robot.T_world_cam_true())
        t = 0.0
        while robot.status == "moving" and t < 600.0:
            robot.step(0.1)
            t += 0.1
            T = np.asarray(robot.T_world_cam_true())
            moved = np.linalg.norm(T[:3, 3] - last[:3, 3])
            turned = np.degrees(np.arccos(np.clip(float(T[:3, 2] @ last[:3, 2]), -1.0, 1.0)))
            if n_frames > 0 and robot.status == "moving" and (moved >= 0.3 or turned >= 20.0):
                passed = [*passed, (T, np.asarray(robot.T_world_cam_odom()))][-n_frames:]
                last = T
        for T_true, T_odom in passed:
            ingest(renderer.render(intr, T_true), T_true, T_odom, ROBOT_ID)

    capture_m = [0.0]  # metres driven by goal captures (sidesteps out and back), counted in distance_m

    def capture(step_m: float) -> None:
        """At the goal, also map the views from the camera moved ``step_m`` to its left and to its right
        (where the robot can stand): a stereo baseline at the goal for RGB-only geometry. The sidesteps,
        out and back, count in the distance driven."""
        T_true, T_odom = np.asarray(robot.T_world_cam_true()), np.asarray(robot.T_world_cam_odom())
        side = T_true[:3, 0].copy()
        side[2] = 0.0
        side /= max(float(np.linalg.norm(side)), 1e-9)
        for sign in (-1.0, 1.0):
            off = sign * step_m * side
            if not nav.is_free(float(T_true[0, 3] + off[0]), float(T_true[1, 3] + off[1])):
                continue
            Tt, To = T_true.copy(), T_odom.copy()
            Tt[:3, 3] += off
            To[:3, 3] += off
            ingest(renderer.render(intr, Tt), Tt, To, ROBOT_ID)
            capture_m[0] += 2.0 * step_m

    records: list[dict[str, Any]] = []
    last_score: dict[str, float] = {"recall": 0.0, "precision": 0.0}

    def record(step: int, extra: dict[str, Any]) -> None:
        snap = mapper.snapshot()
        if step % max(1, score_every) == 0 or step == steps:
            s = score_nodes(snap.nodes, scene)
            last_score.update(recall=float(s.recall), precision=float(s.precision))
        rec = {
            "step": step,
            "n_nodes": len(snap.nodes),
            "recall": last_score["recall"],
            "precision": last_score["precision"],
            "distance_m": round(robot.distance_m + capture_m[0], 3),
            **extra,
        }
        records.append(rec)

    ext_ids: list[str] = []
    if external_cameras > 0:
        from sim.cameras import place_fixed_cameras

        for cam in place_fixed_cameras(scene, int(external_cameras), seed, intr, renderer=renderer):
            T = np.asarray(cam.T_world_cam, float)
            ingest(renderer.render(cam.intrinsics, T), T, T if cam.pose_known else None, cam.camera_id,
                   trusted=cam.pose_known)  # calibrated, as the edge camera marks it: single-view geometry
            if cam.pose_known:  # a surveyed camera's view is known to the planner (both strategies)
                planner.record_view(T, cam.intrinsics, vps.max_range_m)
            ext_ids.append(cam.camera_id)
    ingest(robot.render(), robot.T_world_cam_true(), robot.T_world_cam_odom(), ROBOT_ID)
    record(0, {"decision_s": 0.0, "gain": 0.0, "goal": None, "reason": "start"})
    say(
        f"{strategy} seed {seed} start {start_index}: {len(scene.objects)} objects, {len(vps.viewpoints)} "
        f"candidates; step 0 nodes {records[0]['n_nodes']} recall {records[0]['recall']:.3f}"
    )

    for step in range(1, steps + 1):
        x, y, yaw = robot.pose_odom()
        decision_s, gain, goal, reason = 0.0, 0.0, None, "no goal"
        for _attempt in range(5):
            state = RobotState(
                robot_id=ROBOT_ID,
                stamp_ns=time.time_ns(),
                status="arrived",
                x=x,
                y=y,
                yaw_rad=yaw,
                T_world_cam=rows(robot.T_world_cam_odom()),
                distance_m=robot.distance_m,
                steps=step - 1,
                travel_cost_m=travel_costs(nav, robot.pose_true()[:2], vp_xy),
            )
            goals = planner.plan(mapper.snapshot(), mapper.point_map(), {ROBOT_ID: (state, vps)})
            decision_s += planner.info.decision_s
            if not goals:
                break
            g = goals[0]
            if robot.drive_to(g.x, g.y, g.yaw_rad):
                goal, gain, reason = g, g.expected_gain, g.reason
                break
            planner.mark_failed(ROBOT_ID, g.vp_id)
        if goal is not None:
            drive(move_frames)
            if goal_capture_m > 0:
                capture(goal_capture_m)
        ingest(robot.render(), robot.T_world_cam_true(), robot.T_world_cam_odom(), ROBOT_ID)
        record(
            step,
            {
                "decision_s": round(decision_s, 4),
                "gain": round(float(gain), 4),
                "goal": None
                if goal is None
                else [round(goal.x, 3), round(goal.y, 3), round(goal.yaw_rad, 3)],
                "reason": reason,
            },
        )
        r = records[-1]
        say(
            f"  step {step:2d}: nodes {r['n_nodes']:3d} recall {r['recall']:.3f} "
            f"dist {r['distance_m']:.1f} m "
            f"decide {decision_s:.2f} s | {reason}"
        )

    return {
        "family": family,
        "seed": seed,
        "strategy": strategy,
        "external_cameras": int(external_cameras),
        "start_index": start_index,
        "start": list(start),
        "geometry": geometry,
        "perception": perception,
        "sampler": sampler,
        "n_true": len(scene.objects),
        "n_candidates": len(vps.viewpoints),
        "external_ids": ext_ids,
        "seconds": round(time.perf_counter() - t_start, 2),
        "steps": records,
    }


def summarize(
    episodes: list[dict[str, Any]], at_steps: tuple[int, ...] = REPORT_STEPS
) -> list[dict[str, Any]]:
    """Mean and std over episodes of node count, recall and distance at the given steps, per method."""
    groups: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for ep in episodes:
        groups.setdefault((ep["strategy"], ep["external_cameras"]), []).append(ep)
    rows = []
    for (strategy, ext), eps in sorted(groups.items()):
        row: dict[str, Any] = {
            "strategy": strategy,
            "external_cameras": ext,
            "episodes": len(eps),
            "n_true_mean": float(np.mean([e["n_true"] for e in eps])),
        }
        for k in at_steps:
            recs = [e["steps"][min(k, len(e["steps"]) - 1)] for e in eps]
            for key in ("n_nodes", "recall", "distance_m"):
                v = np.array([r[key] for r in recs], float)
                row[f"{key}@{k}"] = [float(v.mean()), float(v.std())]
        dec = [r["decision_s"] for e in eps for r in e["steps"][1:]]
        row["decision_s_mean"] = float(np.mean(dec)) if dec else 0.0
        row["decision_s_max"] = float(np.max(dec)) if dec else 0.0
        rows.append(row)
    return rows


def markdown(rows: list[dict[str, Any]], at_steps: tuple[int, ...] = REPORT_STEPS) -> str:
    head = (
        "| method | "
        + " | ".join(f"nodes@{k}" for k in at_steps)
        + " | "
        + " | ".join(f"recall@{k}" for k in at_steps)
        + f" | dist@{at_steps[-1]} m | decide s |"
    )
    out = [head, "|" + "---|" * (2 + 2 * len(at_steps) + 1)]
    for r in rows:
        name = r["strategy"].upper() + (" + Ext" if r["external_cameras"] else "")
        nodes = " | ".join("{:.1f} ± {:.1f}".format(*r[f"n_nodes@{k}"]) for k in at_steps)
        rec = " | ".join("{:.3f} ± {:.3f}".format(*r[f"recall@{k}"]) for k in at_steps)
        dist = "{:.1f} ± {:.1f}".format(*r[f"distance_m@{at_steps[-1]}"])
        out.append(
            f"| {name} (n={r['episodes']}, GT {r['n_true_mean']:.0f}) | {nodes} | {rec} | {dist} | "
            f"{r['decision_s_mean']:.2f} (max {r['decision_s_max']:.2f}) |"
        )
    return "\n".join(out)


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
        "  argus explore --strategy asp --ext-cams 1 --steps 10 --geometry oracle --perception sim",
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
        "--family", default="apartment", choices=["apartment", "furnished_room"], help="scene family"
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
        "--out", type=Path, default=None, help="write the JSON here (default: stdout summary only)"
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
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    def say(s: str) -> None:
        if not a.quiet:
            print(s, flush=True)

    episodes = []
    for seed in _ints(a.seeds):
        for ext in a.ext_cams:
            for strategy in a.strategy:
                for start in starts:
                    episodes.append(
                        run_episode(
                            family=a.family,
                            seed=seed,
                            strategy=strategy,
                            external_cameras=ext,
                            steps=a.steps,
                            start_index=start,
                            geometry=a.geometry,
                            perception=a.perception,
                            sampler=a.sampler,
                            torch_threads=a.threads,
                            odometry_noise=a.odometry_noise,
                            move_frames=a.move_frames,
                            goal_capture_m=a.goal_capture,
                            planner_overrides=overrides,
                            mapper_overrides=mapper_overrides,
                            log_fn=say,
                        )
                    )
    rows = summarize(episodes, tuple(k for k in REPORT_STEPS if k <= a.steps) or (0, a.steps))
    print(markdown(rows, tuple(k for k in REPORT_STEPS if k <= a.steps) or (0, a.steps)))
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"summary": rows, "episodes": episodes}, indent=1))
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
