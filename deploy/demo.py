"""``argus demo`` (``make demo``): the whole distributed system on the embedded simulated world.

It runs ``argus up`` on ``deploy/launch/demo.toml`` (router, mapper, planner, one simulated robot,
one overhead simulated camera, an apartment), each its own process, and follows the run as a
consumer would: robot states for the step count, graph snapshots for the node count, scored against
the simulator's ground truth (it knows the scene from the launch file's ``[world]`` table) with
``sim.scoring.score_nodes``. After the exploration steps it prints a table (nodes, precision, recall,
F1, edges, wall time, objects found per room: where the exploration has not reached yet), stops every
process, and leaves a Rerun recording of the run.

Example::

    argus demo                         # 30 steps, writes demo.rrd and demo_logs/
    rerun demo.rrd                     # watch it (or: rerun --serve-web --bind 127.0.0.1 demo.rrd)
    argus demo --steps 10 --launch deploy/launch/demo-oracle.toml
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from deploy.up import LaunchFile, Stack, load_launch, with_endpoint
from protocol.codec import DecodeError, decode
from protocol.keys import Keys
from protocol.messages import GraphSnapshot, PointMap, RobotState
from protocol.transport import decode_frame_sample

DEFAULT_LAUNCH = Path(__file__).resolve().parent / "launch" / "demo.toml"


class DemoConfig(BaseModel):
    """What the demo runs and where it writes."""

    model_config = ConfigDict(extra="forbid")
    launch: Path = Field(default=DEFAULT_LAUNCH, description="launch file of the stack")
    steps: int = Field(default=30, ge=1, description="exploration steps (robot arrivals) before stopping")
    rrd: Path | None = Field(default=Path("demo.rrd"), description="Rerun recording to write (None: none)")
    result_json: Path | None = Field(default=Path("demo_result.json"), description="final figures as JSON")
    log_dir: Path = Field(default=Path("demo_logs"), description="one <process>.log per process")
    time_limit_s: float = Field(default=570.0, gt=0, description="stop here even if the steps are not done")
    health_timeout_s: float = Field(default=240.0, gt=0, description="give up when the stack is not up by then")
    free_port: bool = Field(default=True, description="run the router on a free loopback port, not the file's")
    port: int | None = Field(default=None, ge=1, le=65535,
                             description="run the router on this loopback port (instead of a free or the file's one)")
    score_period_s: float = Field(default=4.0, gt=0, description="seconds between graph scorings")
    settle_s: float = Field(
        default=8.0, ge=0, description="after the last step, wait until no graph delta came for this long..."
    )
    drain_max_s: float = Field(default=60.0, ge=0, description="...but at most this long (the mapper's backlog)")
    verbose: bool = Field(default=False, description="print every process's log lines too")


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def prepare_launch(config: DemoConfig) -> LaunchFile:
    """The demo's launch file with the step budget and (optionally) a free router port applied."""
    launch = load_launch(config.launch)
    if config.port is not None:
        launch = with_endpoint(launch, f"tcp/127.0.0.1:{config.port}")
    elif config.free_port:
        launch = with_endpoint(launch, free_endpoint())
    procs = []
    for p in launch.process:
        if p.command == "robot-agent" and p.settings is not None:
            settings = dict(p.settings)
            budget = dict(settings.get("budget", {}))
            budget["max_steps"] = config.steps
            settings["budget"] = budget
            p = p.model_copy(update={"settings": settings})
        procs.append(p)
    return launch.model_copy(update={"process": procs})


def perception_label(launch: LaunchFile) -> str:
    """Say plainly whether the mapper uses the ORACLE (simulator ground truth) anywhere."""
    mapper = next((p for p in launch.process if p.command == "mapper"), None)
    text = json.dumps(mapper.settings or {}) if mapper is not None else ""
    oracle_2d = '"sim"' in text and "segmenter" in text
    oracle_geo = '"oracle"' in text
    parts = []
    parts.append("ORACLE geometry (sim depth + poses)" if oracle_geo else "RGB-only geometry")
    parts.append("ORACLE 2D perception (sim semantic camera)" if oracle_2d else "RGB-only 2D perception")
    return ", ".join(parts)


class Monitor:
    """The demo's consumer side: robot states, graph, point map and frames from Zenoh."""

    def __init__(self, session: Any, keys: Keys) -> None:
        self.session, self.keys = session, keys
        self._lock = threading.Lock()
        self.states: dict[str, RobotState] = {}
        self.trajectory: dict[str, list[tuple[float, float]]] = {}
        self.point_map: PointMap | None = None
        self.frames: dict[str, tuple[Any, bytes]] = {}  # source -> (header, jpeg), newest only
        self.deltas = 0
        self.last_delta_t = time.monotonic()
        self.frames_seen = 0
        self.bad = 0
        self._subs = [
            session.declare_subscriber(keys.all_robot_states, self._on_state),
            session.declare_subscriber(keys.graph_delta, self._on_delta),
            session.declare_subscriber(keys.map_points, self._on_map),
            session.declare_subscriber(keys.all_frames, self._on_frame),
        ]

    def _on_state(self, sample: Any) -> None:
        try:
            st = decode(sample.payload.to_bytes(), RobotState)
        except DecodeError:
            self.bad += 1
            return
        with self._lock:
            self.states[st.robot_id] = st
            traj = self.trajectory.setdefault(st.robot_id, [])
            if not traj or math.dist(traj[-1], (st.x, st.y)) > 0.05:
                traj.append((st.x, st.y))
                del traj[:-2000]

    def _on_delta(self, _sample: Any) -> None:
        self.deltas += 1
        self.last_delta_t = time.monotonic()

    def _on_map(self, sample: Any) -> None:
        try:
            pm = decode(sample.payload.to_bytes(), PointMap)
        except DecodeError:
            self.bad += 1
            return
        with self._lock:
            self.point_map = pm

    def _on_frame(self, sample: Any) -> None:
        try:
            fr = decode_frame_sample(sample)
        except DecodeError:
            self.bad += 1
            return
        with self._lock:
            self.frames[fr.header.source_id] = (fr.header, fr.jpeg)
            self.frames_seen += 1

    def steps(self) -> int:
        with self._lock:
            return max((s.steps for s in self.states.values()), default=0)

    def exhausted(self) -> bool:
        with self._lock:
            return bool(self.states) and all(s.status == "budget_exhausted" for s in self.states.values())

    def take(self) -> tuple[dict[str, RobotState], dict[str, list[tuple[float, float]]], PointMap | None,
                            dict[str, tuple[Any, bytes]]]:
        with self._lock:
            frames, self.frames = self.frames, {}
            pm, self.point_map = self.point_map, None
            return dict(self.states), {k: list(v) for k, v in self.trajectory.items()}, pm, frames

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - closing at shutdown
                pass


class Recorder:
    """Writes the run to a Rerun ``.rrd`` file (graph boxes, edges, point map, cameras, metrics)."""

    def __init__(self, path: Path, max_parts: int = 32) -> None:
        import rerun as rr

        self.rr = rr
        self.path = path
        self.rec = rr.RecordingStream("argus_demo")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.rec.save(str(path))
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        from mapper.rerun_log import PointParts

        # The point map arrives whole at every scoring period; the recording gets only the voxels it lacks.
        self.points = PointParts(max_parts)

    def _time(self, step: int, wall_s: float) -> None:
        self.rec.set_time("step", sequence=step)
        self.rec.set_time("wall", duration=wall_s)

    def log_graph(self, step: int, wall_s: float, snap: GraphSnapshot) -> None:
        rr = self.rr
        self._time(step, wall_s)
        if snap.nodes:
            centers = np.array([n.box.center for n in snap.nodes], dtype=np.float32)
            sizes = np.array([n.box.extent for n in snap.nodes], dtype=np.float32)
            half = np.array([n.box.yaw_rad / 2.0 for n in snap.nodes])
            quats = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)], axis=1)
            self.rec.log("world/objects", rr.Boxes3D(centers=centers, sizes=sizes, quaternions=quats,
                                                     labels=[n.label for n in snap.nodes], show_labels=True))
        else:
            self.rec.log("world/objects", rr.Clear(recursive=False))
        pos = {n.node_id: n.centroid for n in snap.nodes}
        strips = [[pos[e.subject_id], pos[e.object_id]] for e in snap.edges
                  if e.subject_id in pos and e.object_id in pos]
        if strips:
            self.rec.log("world/edges", rr.LineStrips3D(strips, labels=[e.predicate for e in snap.edges
                                                                        if e.subject_id in pos and e.object_id in pos],
                                                        colors=[200, 200, 60]))

    def log_metrics(self, step: int, wall_s: float, nodes: int, recall: float | None, precision: float | None) -> None:
        rr = self.rr
        self._time(step, wall_s)
        self.rec.log("metrics/nodes", rr.Scalars(float(nodes)))
        if recall is not None:
            self.rec.log("metrics/recall", rr.Scalars(float(recall)))
        if precision is not None:
            self.rec.log("metrics/precision", rr.Scalars(float(precision)))

    def log_world(self, step: int, wall_s: float, states: dict[str, RobotState],
                  traj: dict[str, list[tuple[float, float]]], pm: PointMap | None,
                  frames: dict[str, tuple[Any, bytes]]) -> None:
        rr = self.rr
        self._time(step, wall_s)
        if pm is not None and len(pm.points):
            self.log_points(pm)
        for rid, xy in traj.items():
            if len(xy) >= 2:
                self.rec.log(f"world/robots/{rid}/path", rr.LineStrips3D([[(x, y, 0.02) for x, y in xy]],
                                                                        colors=[60, 160, 255]))
        for sid, (header, jpeg) in frames.items():
            base = f"world/cameras/{sid}"
            if header.T_world_cam is not None:
                T = np.asarray(header.T_world_cam)
                self.rec.log(base, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            if header.intrinsics is not None:
                K = header.intrinsics.K()
                self.rec.log(base, rr.Pinhole(image_from_camera=K, resolution=[header.width, header.height],
                                              image_plane_distance=0.3))
            self.rec.log(base, rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))

    def log_points(self, pm: PointMap) -> None:
        """Log the voxels of ``pm`` the recording does not hold yet, as one more part of ``world/points``."""
        from mapper.fusion import voxel_keys

        rr = self.rr
        pts = np.asarray(pm.points, dtype=np.float32)
        new, refresh = self.points.take(voxel_keys(pts, pm.voxel_m))
        if not new.any():
            return
        if refresh:
            self.rec.log("world/points", rr.Clear(recursive=True))
        colors = np.asarray(pm.colors)[new] if pm.colors is not None and len(pm.colors) == len(pts) else None
        self.rec.log(f"world/points/{self.points.part_name}", rr.Points3D(pts[new], colors=colors,
                                                                          radii=pm.voxel_m / 2))

    def close(self) -> None:
        self.rec.flush()
        try:
            self.rec.disconnect()
        except Exception:  # noqa: BLE001 - older SDKs flush on drop
            pass


def _bar(done: int, total: int, width: int = 20) -> str:
    k = min(width, int(round(width * done / max(total, 1))))
    return "[" + "#" * k + "." * (width - k) + "]"


def format_table(rows: list[tuple[str, str]]) -> str:
    w = max(len(k) for k, _ in rows)
    wv = max(24, *(len(v) for _, v in rows))
    line = "+" + "-" * (w + 2) + "+" + "-" * (wv + 2) + "+"
    out = [line]
    out += [f"| {k.ljust(w)} | {v.ljust(wv)} |" for k, v in rows]
    out.append(line)
    return "\n".join(out)


SERVER_NEEDS = ("torch", "gtsam", "open3d", "scipy", "rerun")
"""What the demo's processes (mapper, planner, simulator) and its recording import: checked before anything starts."""


def require_server_install() -> None:
    """Raise ModuleNotFoundError naming the first server dependency this install lacks (``argus`` turns it into
    its one-line "needs the server install"), without importing any of them."""
    for name in SERVER_NEEDS:
        if importlib.util.find_spec(name) is None:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)


def run(config: DemoConfig) -> int:
    """Run the demo; returns 0 when the steps were done and the graph is non-empty."""
    from deploy.query import QueryError, get_snapshot
    from protocol.runtime import install_stop_handlers
    from protocol.session import ZenohSettings, open_session

    require_server_install()
    t0 = time.monotonic()
    launch = prepare_launch(config)
    mode = perception_label(launch)
    print(f"argus demo: {config.steps} exploration steps on the simulated "
          f"{launch.world.family if launch.world else '?'} (seed {launch.world.seed if launch.world else '?'}); "
          f"{mode}", flush=True)
    print(f"argus demo: stack from {config.launch} on {launch.endpoint}; process logs in {config.log_dir}/",
          flush=True)

    def emit(line: str) -> None:
        low = line.lower()
        if config.verbose or line.startswith("[up]") or "error" in low or "traceback" in low:
            print(line, flush=True)

    stop = install_stop_handlers()
    stack = Stack(launch, config.launch.parent, emit=emit, log_dir=config.log_dir)
    scorer = _Scorer(launch)
    if scorer.position_only:
        print("argus demo: class-agnostic 2D perception: nodes are scored by position only (any label)", flush=True)
    recorder = Recorder(config.rrd) if config.rrd is not None else None
    monitor: Monitor | None = None
    session: Any = None
    final: dict[str, Any] = {}
    code = 1
    try:
        stack.start()
        threading.Thread(target=scorer.warm_up, daemon=True).start()  # scene + MiniLM load in parallel
        if not stack.wait_healthy(config.health_timeout_s, stop):
            print(f"argus demo: stack not healthy (missing: {', '.join(stack.missing()) or '-'};"
                  f" failed: {', '.join(stack.failed) or '-'}); see {config.log_dir}/", flush=True)
            return 1
        session = open_session(ZenohSettings(mode="client", connect=[launch.endpoint]))
        monitor = Monitor(session, Keys(launch.site))
        t_up = time.monotonic() - t0
        last_score_t, last_steps = 0.0, -1
        snap: GraphSnapshot | None = None
        score: Any = None
        tty = sys.stdout.isatty()
        while not stop.is_set():
            if not stack.step():
                print(f"\nargus demo: process(es) failed: {', '.join(stack.failed)}; see {config.log_dir}/")
                break
            steps = monitor.steps()
            now = time.monotonic()
            done = steps >= config.steps or monitor.exhausted()
            if steps != last_steps or now - last_score_t > config.score_period_s or done:
                try:
                    snap = get_snapshot(session, Keys(launch.site), timeout_s=3.0)
                except QueryError:
                    pass  # keep the previous snapshot
                if snap is not None:
                    score = scorer.score(snap)
                last_score_t, last_steps = now, steps
                wall = now - t0
                if recorder is not None:
                    states, traj, pm, frames = monitor.take()
                    recorder.log_world(steps, wall, states, traj, pm, frames)
                    if snap is not None:
                        recorder.log_graph(steps, wall, snap)
                        recorder.log_metrics(steps, wall, len(snap.nodes), getattr(score, "recall", None),
                                             getattr(score, "precision", None))
                n_nodes = len(snap.nodes) if snap is not None else 0
                rec = f"{score.recall:.2f}" if score is not None else "  - "
                line = (f"{_bar(steps, config.steps)} step {steps:2d}/{config.steps} | nodes {n_nodes:3d} | "
                        f"recall {rec} | {wall:5.0f} s")
                print(("\r" + line) if tty else line, end="" if tty else "\n", flush=True)
            if done:
                break
            if now - t0 > config.time_limit_s:
                print(f"\nargus demo: time limit of {config.time_limit_s:.0f}s reached at step {steps}")
                break
            stop.wait(0.3)
        if tty:
            print()
        if not stop.is_set() and config.settle_s > 0:
            # The planner sends the next goal on arrival, while the mapper may still be working through
            # the last frames: let it finish its (bounded) backlog before the final score.
            t_drain = time.monotonic()
            print(f"argus demo: steps done; letting the mapper finish its last frames (until {config.settle_s:.0f}s "
                  f"without a graph change, at most {config.drain_max_s:.0f}s)", flush=True)
            while (not stop.is_set() and time.monotonic() - monitor.last_delta_t < config.settle_s
                   and time.monotonic() - t_drain < config.drain_max_s and time.monotonic() - t0 < config.time_limit_s):
                stack.step()
                stop.wait(0.5)
            try:
                snap = get_snapshot(session, Keys(launch.site), timeout_s=3.0)
                score = scorer.score(snap)
            except QueryError:
                pass
            if recorder is not None and snap is not None:
                wall = time.monotonic() - t0
                recorder.log_graph(monitor.steps(), wall, snap)
                recorder.log_metrics(monitor.steps(), wall, len(snap.nodes), getattr(score, "recall", None),
                                     getattr(score, "precision", None))
        wall = time.monotonic() - t0
        steps = monitor.steps()
        final = {
            "steps": steps, "steps_target": config.steps, "wall_s": round(wall, 1), "startup_s": round(t_up, 1),
            "perception": mode, "nodes": len(snap.nodes) if snap else 0, "edges": len(snap.edges) if snap else 0,
            "graph_version": snap.version if snap else 0, "deltas_seen": monitor.deltas,
            "frames_seen": monitor.frames_seen,
        }
        rooms = scorer.rooms(score)
        if score is not None:
            final.update(precision=score.precision, recall=score.recall, f1=score.f1, n_true=score.n_true)
        if rooms:
            final["rooms"] = {r: {"found": f, "objects": n} for r, (f, n) in rooms.items()}
        rows = [("steps", f"{steps} / {config.steps}"), ("nodes", str(final["nodes"])),
                ("ground-truth objects", str(final.get("n_true", "-"))),
                ("precision", _f(final.get("precision"))), ("recall", _f(final.get("recall"))),
                ("F1", _f(final.get("f1"))), ("edges", str(final["edges"])),
                ("graph version", str(final["graph_version"])), ("wall time", f"{wall:.0f} s (startup {t_up:.0f} s)"),
                *((f"objects found in {r}", f"{f} / {n}") for r, (f, n) in rooms.items()),
                ("geometry", "ORACLE (sim)" if mode.startswith("ORACLE") else "RGB-only (mvs)"),
                ("2D perception", "ORACLE (sim semantic)" if "ORACLE 2D" in mode else "RGB-only (position-only score)")]
        print(format_table(rows))
        code = 0 if (steps >= config.steps or monitor.exhausted()) and final["nodes"] > 0 else 1
    except Exception as e:  # noqa: BLE001 - whatever fails, every process is still stopped below
        print(f"\nargus demo: error: {type(e).__name__}: {e}", flush=True)
        code = 1
    finally:
        if monitor is not None:
            monitor.close()
        if session is not None:
            session.close()
        stack.stop()
        alive = [c.spec.name for c in stack.children if c.group_alive()]
        print("argus demo: all processes stopped" if not alive else f"argus demo: still running: {alive}",
              flush=True)
        if recorder is not None:
            recorder.close()
            print(f"recording: {config.rrd}  (watch: rerun {config.rrd}; in a browser, offline: "
                  f"rerun --serve-web --bind 127.0.0.1 {config.rrd})")
        if config.result_json is not None and final:
            config.result_json.write_text(json.dumps(final, indent=2) + "\n")
    return code


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


class _Scorer:
    """Scores graph nodes against the simulated scene (loaded lazily: sim/ and MiniLM are heavy)."""

    def __init__(self, launch: LaunchFile) -> None:
        self.world = launch.world
        # Class-agnostic perception labels every node "object": score positions only, and say so.
        self.position_only = "ORACLE 2D" not in perception_label(launch)
        self._scene: Any = None
        self._lock = threading.Lock()
        self.error: str | None = None

    def warm_up(self) -> None:
        try:
            self._load()
        except Exception as e:  # noqa: BLE001 - no scoring is not fatal for the demo
            self.error = f"{type(e).__name__}: {e}"

    def _load(self) -> Any:
        with self._lock:
            if self._scene is None and self.world is not None:
                from sim.scene import generate_scene

                self._scene = generate_scene(self.world.family, self.world.seed)
            return self._scene

    def rooms(self, score: Any) -> dict[str, tuple[int, int]]:
        """Per room of the scene, (objects found, objects): where the exploration has not reached yet."""
        if score is None or self._scene is None:
            return {}
        from sim.scoring import found_by_room

        return found_by_room(score, self._scene)

    def score(self, snap: GraphSnapshot) -> Any:
        if self.world is None or self.error is not None:
            return None
        try:
            from sim.scoring import score_nodes

            if self.position_only:
                return score_nodes(list(snap.nodes), self._load(), label_threshold=-1.0)
            return score_nodes(list(snap.nodes), self._load())
        except Exception as e:  # noqa: BLE001 - a broken scene file or scorer: the demo runs on unscored
            self.error = f"{type(e).__name__}: {e}"
            print(f"\nargus demo: scoring unavailable: {self.error}", flush=True)
            return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus demo",
        description="Run the whole distributed system on the embedded simulated world and score it live.",
        epilog="examples: argus demo --steps 30 --rrd demo.rrd   (then: rerun demo.rrd) | "
        "argus demo --port 7447   (then, from another shell: argus query snapshot)",
    )
    p.add_argument("--launch", type=Path, default=DEFAULT_LAUNCH, help="launch file (default: deploy/launch/demo.toml)")
    p.add_argument("--steps", type=int, default=30, help="exploration steps")
    p.add_argument("--rrd", type=Path, default=Path("demo.rrd"), help="Rerun recording to write")
    p.add_argument("--no-rrd", action="store_true", help="do not write a recording")
    p.add_argument("--json", type=Path, default=Path("demo_result.json"), help="final figures as JSON")
    p.add_argument("--log-dir", type=Path, default=Path("demo_logs"), help="per-process log files")
    p.add_argument("--time-limit", type=float, default=570.0, help="seconds before stopping regardless")
    port = p.add_mutually_exclusive_group()
    port.add_argument("--port", type=int, default=None,
                      help="run the router on tcp/127.0.0.1:PORT (default: a free port, printed at start)")
    port.add_argument("--keep-port", action="store_true", help="use the launch file's router port, not a free one")
    p.add_argument("--verbose", action="store_true", help="print every process's log lines")
    a = p.parse_args(argv)
    try:
        config = DemoConfig(launch=a.launch, steps=a.steps, rrd=None if a.no_rrd else a.rrd, result_json=a.json,
                            log_dir=a.log_dir, time_limit_s=a.time_limit, free_port=not a.keep_port,
                            port=a.port, verbose=a.verbose)
    except ValueError as e:  # pydantic's ValidationError included: one line per field
        from protocol.exits import USAGE, one_line

        print(f"argus demo: {one_line(e)}", file=sys.stderr)
        return USAGE
    return run(config)


if __name__ == "__main__":
    sys.exit(main())
