"""``argus bench system``: N simulated cameras at F fps into one ``argus mapper`` process.

A real router and a real mapper run as their own processes (through :class:`deploy.up.Stack`); this
process plays the cameras (frames pre-rendered by the simulator along navigable paths, so every frame
is new to the mapper, JPEG-encoded once, re-stamped at each put) and the consumers. Three phases of
equal length measure, with 0, 1 and 10 concurrent query consumers:

- offered and sustained ingest (frames the mapper received / turned into keyframes per second, from
  its Status counters), frames dropped (sent but never processed);
- end-to-end latency capture -> graph delta: delta receipt time minus the capture stamp of the keyframe whose
  processing made the delta (``GraphDelta.stamp_ns``), over deltas that changed nodes, p50 / p99;
- mapper CPU (cores used, from ``/proc/<pid>/stat``) and peak memory (``VmHWM`` of
  ``/proc/<pid>/status``; psutil is not needed);
- query latency (``graph/nodes?label=...`` and ``graph/snapshot`` gets), p50 / p99;
- with ``--workers``: CPU-seconds per keyframe done per role (the mapper's main thread and its other threads,
  the router, the cameras, each worker), the transfer cost per job (bytes; seconds the worker takes to get the
  window's images: source fetches and JPEG decoding; the mapper's seconds decoding a result) and the scaling
  model's predicted keyframes/s for N workers here and on their own machines (:mod:`bench.scaling`), under the
  table of ``system.md``. Give it more keyframes than two workers finish (e.g. ``--cameras 4``) to measure
  scaling.

Example::

    argus bench system --cameras 2 --fps 2 --phase-s 30 --out bench_out/system
    argus bench system --quick
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.report import write_report
from bench.scaling import stat_cpu_s, workers_cpu_s
from protocol.codec import DecodeError, decode, encode
from protocol.keys import Keys
from protocol.messages import FrameHeader, GraphDelta, OracleFrame, SourceKind, Status, rows


# --- /proc sampling ------------------------------------------------------------------------------
def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux ``/proc/<pid>/stat``)."""
    return stat_cpu_s(Path(f"/proc/{pid}/stat"))


def proc_mem_mb(pid: int) -> dict[str, float]:
    """Resident (``VmRSS``) and peak resident (``VmHWM``) memory in MiB."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            name, value = line.split(":", 1)
            out[name] = int(value.split()[0]) / 1024.0
    return {"rss_mb": out.get("VmRSS", 0.0), "peak_rss_mb": out.get("VmHWM", 0.0)}


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


# --- frames --------------------------------------------------------------------------------------
@dataclass
class CameraFrames:
    """Pre-encoded frames of one simulated camera, replayed in a loop."""

    source_id: str
    kind: SourceKind
    jpegs: list[bytes]
    poses: list[np.ndarray]
    intrinsics: Any
    oracle: list[tuple[bytes, bytes]] = field(default_factory=list)  # (ids PNG, depth PNG) per frame
    labels: dict[str, str] = field(default_factory=dict)


def render_cameras(n: int, frames_per_camera: int, width: int, height: int, family: str, seed: int,
                   oracle: bool = False) -> list[CameraFrames]:
    """Frames of ``n`` cameras walking different navigable paths of one simulated scene."""
    from protocol.jpeg import encode_jpeg
    from protocol.messages import Intrinsics
    from protocol.oracle import depth_to_png, ids_to_png
    from protocol.poses import camera_pose_from_base
    from sim.nav import NavMap
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene(family, seed)
    nav = NavMap(scene)
    renderer = Renderer(scene)
    intr = Intrinsics.from_fov(width, height, 90.0)
    vps = nav.viewpoints(spacing_m=0.6, n_headings=8)
    rng = np.random.default_rng(seed)
    cams: list[CameraFrames] = []
    for i in range(n):
        # A slow sweep: consecutive frames turn 15 degrees and step along a random walk of viewpoints,
        # so each frame is a new keyframe for the mapper (the worst case for ingest).
        start = vps[int(rng.integers(len(vps)))]
        x, y, yaw = start.x, start.y, start.yaw_rad
        jpegs, poses, oracles = [], [], []
        for _k in range(frames_per_camera):
            T = camera_pose_from_base(x, y, yaw, 1.0, -15.0)
            out = renderer.render(intr, T)
            jpegs.append(encode_jpeg(out.rgb, 85))
            poses.append(T)
            if oracle:  # ORACLE ground truth, for the oracle / sim backends only
                oracles.append((ids_to_png(out.instance_id), depth_to_png(out.depth_m)))
            yaw += np.radians(15.0)
            nx, ny = x + 0.15 * np.cos(yaw), y + 0.15 * np.sin(yaw)
            if nav.is_free(nx, ny):
                x, y = nx, ny
        cams.append(CameraFrames(f"simcam{i}", "robot", jpegs, poses, intr, oracles,
                                 {str(k): v for k, v in scene.labels().items()}))
    return cams


def cached_cameras(cache: Path | None, n: int, frames_per_camera: int, width: int, height: int, family: str,
                   seed: int, oracle: bool) -> list[CameraFrames]:
    """:func:`render_cameras`, or its earlier output kept under ``cache`` (a pickle this bench wrote; the
    rendering is deterministic for these arguments and the simulator's code, so delete the folder when that
    changes). Rendering 8 cameras takes minutes on a busy machine; repeated runs need not pay it again."""
    import pickle

    path = None
    if cache is not None:
        path = cache / f"cams_{n}x{frames_per_camera}_{width}x{height}_{family}_{seed}_{int(oracle)}.pkl"
        if path.exists():
            with path.open("rb") as f:
                cams: list[CameraFrames] = pickle.load(f)  # noqa: S301 - written by this function
            return cams
    cams = render_cameras(n, frames_per_camera, width, height, family, seed, oracle=oracle)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        with tmp.open("wb") as f:
            pickle.dump(cams, f)
        tmp.replace(path)
    return cams


class CameraPlayer:
    """Publishes one camera's frames at ``fps`` on its frame key, stamped at the put."""

    def __init__(self, session: Any, keys: Keys, cam: CameraFrames, fps: float) -> None:
        from protocol.transport import declare_frame_publisher

        self.cam, self.fps = cam, fps
        self.pub = declare_frame_publisher(session, keys.frame(cam.kind, cam.source_id))
        self.oracle_pub = None
        if cam.oracle:
            from protocol.transport import declare_message_publisher

            self.oracle_pub = declare_message_publisher(
                session, keys.oracle(cam.kind, cam.source_id), important=False)
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"cam-{cam.source_id}")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        from protocol.transport import put_frame

        period = 1.0 / self.fps
        next_t = time.monotonic()
        cam = self.cam
        while not self._stop.is_set():
            k = self.sent % len(cam.jpegs)
            header = FrameHeader(
                source_id=cam.source_id, source_kind=cam.kind, seq=self.sent, stamp_ns=time.time_ns(),
                width=cam.intrinsics.width, height=cam.intrinsics.height, intrinsics=cam.intrinsics,
                T_world_cam=rows(cam.poses[k]), pose_trusted=False,
            )
            if self.oracle_pub is not None:
                ids_png, depth_png = cam.oracle[k]
                self.oracle_pub.put(encode(OracleFrame(
                    source_id=cam.source_id, seq=self.sent, stamp_ns=header.stamp_ns,
                    T_world_cam_true=rows(cam.poses[k]), ids_png=ids_png, depth_png=depth_png, labels=cam.labels)))
            put_frame(self.pub, header, cam.jpegs[k])
            self.sent += 1
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()


class Consumer:
    """A graph consumer with its own session, issuing queries back to back (up to ``rate_hz``)."""

    def __init__(self, endpoint: str, keys: Keys, rate_hz: float = 10.0) -> None:
        from protocol.session import ZenohSettings, open_session

        self.session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        self.keys, self.rate_hz = keys, rate_hz
        self.latencies_ms: list[float] = []
        self.failures = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="consumer")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.session.close()

    def _run(self) -> None:
        from deploy.query import QueryError, get_nodes, get_snapshot
        from protocol.query import GraphQuery

        i = 0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            try:
                if i % 2 == 0:
                    get_nodes(self.session, self.keys, GraphQuery(label="chair"), timeout_s=5.0)
                else:
                    get_snapshot(self.session, self.keys, timeout_s=5.0)
                self.latencies_ms.append((time.perf_counter() - t0) * 1000.0)
            except QueryError:
                self.failures += 1
            i += 1
            self._stop.wait(max(0.0, 1.0 / self.rate_hz - (time.perf_counter() - t0)))


def delta_latency_ms(delta: GraphDelta, now_ns: int) -> float | None:
    """Capture-to-graph latency of a delta that changed nodes: from the capture stamp of the keyframe whose
    processing made it (``delta.stamp_ns``) to ``now_ns``; None for a delta that changed no node. (The newest
    ``last_seen_ns`` of its nodes is not that: a delta that only re-sends older nodes, merged or pruned by
    maintenance, would read as their age.)"""
    if not delta.upserted or delta.stamp_ns <= 0:
        return None
    return (now_ns - delta.stamp_ns) / 1e6


class GraphWatch:
    """Delta latencies, the graph's newest version and when it last changed, and the Status counters of the
    mapper, its workers and the other processes (with their last error)."""

    def __init__(self, session: Any, keys: Keys) -> None:
        self._lock = threading.Lock()
        self.latencies_ms: list[float] = []
        self.deltas = 0
        self.version = 0
        self.last_change_t = time.monotonic()
        self.status: dict[str, float] = {}
        self.status_pid: int | None = None
        self.workers: dict[str, dict[str, float]] = {}  # worker id -> its latest Status counters
        self.others: dict[str, dict[str, float]] = {}  # "<role>/<id>" of other roles -> its latest Status counters
        self.other_errors: dict[str, str | None] = {}  # the same -> its Status's last_error
        self._subs = [session.declare_subscriber(keys.graph_delta, self._on_delta),
                      session.declare_subscriber(keys.all_status, self._on_status)]

    def _on_delta(self, sample: Any) -> None:
        now = time.time_ns()
        try:
            d = decode(sample.payload.to_bytes(), GraphDelta)
        except DecodeError:
            return
        with self._lock:
            self.deltas += 1
            self.version = max(self.version, d.version)
            self.last_change_t = time.monotonic()
            if (ms := delta_latency_ms(d, now)) is not None:
                self.latencies_ms.append(ms)
                self._latency(d, ms)

    def _latency(self, delta: GraphDelta, ms: float) -> None:
        """Called (under the lock) with each latency sample and its delta; for subclasses."""

    def _on_status(self, sample: Any) -> None:
        try:
            st = decode(sample.payload.to_bytes(), Status)
        except DecodeError:
            return
        with self._lock:
            if st.role == "mapper":
                self.status = dict(st.counters)
            elif st.role == "worker" and (st.node_id in self.workers or len(self.workers) < 64):
                self.workers[st.node_id] = dict(st.counters)
            elif (name := f"{st.role}/{st.node_id}") in self.others or len(self.others) < 64:
                self.others[name] = dict(st.counters)
                self.other_errors[name] = st.last_error

    def take(self) -> tuple[list[float], int, dict[str, float]]:
        with self._lock:
            lat, self.latencies_ms = self.latencies_ms, []
            n, self.deltas = self.deltas, 0
            return lat, n, dict(self.status)

    def worker_status(self) -> dict[str, dict[str, float]]:
        with self._lock:
            return {k: dict(v) for k, v in self.workers.items()}

    def other_status(self) -> dict[str, dict[str, float]]:
        """The latest Status counters of every other process (planner, robots, ...), by ``<role>/<id>``."""
        with self._lock:
            return {k: dict(v) for k, v in self.others.items()}

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


def work_model(diff: Any, workers: dict[str, dict[str, float]]) -> dict[str, Any]:
    """The scaling model's inputs, measured: a worker's seconds per job (its mean job time: fetch, geometry,
    perception, encoding) and the bytes one job moves (job + result + source fetches); and what they predict
    for N workers on N free cores or machines: ``N / job_s`` keyframes/s, capped by what the mapper's thread
    can finish (``1 / update_s`` per keyframe it fuses)."""
    done = diff("work_results_accepted", 0.0)
    job_s = [w["job_s_mean"] for w in workers.values() if "job_s_mean" in w]
    moved = diff("work_job_bytes", 0.0) + diff("work_result_bytes", 0.0) + diff("work_fetched_bytes", 0.0)
    out: dict[str, Any] = {"worker_job_s": float(np.mean(job_s)) if job_s else None,
                           "bytes_per_job": moved / done if done > 0 else None,
                           "job_roundtrip_s": None}
    rt = diff("work_roundtrip_s_sum", 0.0)
    if done > 0 and rt > 0:
        out["job_roundtrip_s"] = rt / done
    if out["worker_job_s"]:
        out["model_kf_per_s_per_worker"] = 1.0 / out["worker_job_s"]
    return out


def stop_load(players: list[CameraPlayer], watch: GraphWatch | None, session: Any, stack: Any) -> None:
    """Stop the cameras, the watcher, the bench's own session and the stack (in that order)."""
    for p in players:
        p.stop()
    if watch is not None:
        watch.close()
    if session is not None:
        session.close()
    stack.stop()


def _log(msg: str) -> None:
    print(f"[bench system] {msg}", flush=True)


def run(cameras: int, fps: float, phase_s: float, warmup_s: float, width: int, height: int,
        frames_per_camera: int, consumers: list[int], mapper_settings: dict[str, Any], out: Path,
        family: str = "apartment", seed: int = 0, consumer_rate_hz: float = 10.0,
        workers: list[int] | None = None, frames_cache: Path | None = None) -> dict[str, Any]:
    """Run the benchmark and write ``system.json`` / ``system.md`` under ``out``. With ``workers`` (counts of
    ``argus worker`` processes, one fresh stack each, the same frames): the scaling curve, one row per count."""
    from mapper.geometry.registry import ORACLE_RECONSTRUCTORS

    t_render = time.monotonic()
    geo = mapper_settings.get("geometry", {}).get("backend", "mvs")
    per = mapper_settings.get("perception", {})
    oracle = geo in ORACLE_RECONSTRUCTORS or "sim" in (per.get("segmenter"), per.get("embedder"))
    cams = cached_cameras(frames_cache, cameras, frames_per_camera, width, height, family, seed, oracle)
    _log(f"rendered {cameras} x {frames_per_camera} frames at {width}x{height} in "
         f"{time.monotonic() - t_render:.1f}s")
    results: dict[str, Any] = {"cameras": cameras, "fps": fps, "width": width, "height": height,
                               "consumer_rate_hz": consumer_rate_hz,
                               "phase_s": phase_s, "mapper_settings": mapper_settings, "phases": []}
    counts = workers or [0]
    for n in counts:
        phases = _run_stack(cams, fps, phase_s, warmup_s, consumers, mapper_settings, consumer_rate_hz, n)
        results["phases"] += [{"workers": n, **ph} for ph in phases]
    rows = [{k: v for k, v in ph.items() if k not in ("mapper_status", "model_curve", "job_cpu_s")}
            for ph in results["phases"]]
    if workers is None:
        rows = [{k: v for k, v in r.items() if k != "workers"} for r in rows]
    write_report(out, "system", results, rows,
                 title=f"System: {cameras} simulated cameras at {fps:g} fps into one mapper "
                       f"({width}x{height}, {mapper_settings}; consumers query at {consumer_rate_hz:g} Hz each"
                       + (f"; argus worker processes: {counts}" if workers else "") + ")")
    with_headline(out / "system.md", headline(results["phases"], cameras, fps, curve=workers is not None))
    if workers:
        append_model(out / "system.md", results["phases"])
    return results


def job_profile(before: dict[str, dict[str, float]], after: dict[str, dict[str, float]]) -> dict[str, float]:
    """CPU-seconds per keyframe job by stage over all workers between two worker-status snapshots (worker id ->
    its counters): the growth of each ``cpu_s.<stage>`` counter (``mapper.work.worker``) over the growth of
    ``jobs_done``; ``total`` is their sum. Empty when no job was done. A worker first seen in ``after`` counts
    from its start, both in its CPU and in its jobs, so the ratio stays a per-job figure."""
    spent: dict[str, float] = {}
    jobs = 0.0
    for wid, c1 in after.items():
        c0 = before.get(wid, {})
        jobs += c1.get("jobs_done", 0.0) - c0.get("jobs_done", 0.0)
        for k, v in c1.items():
            if k.startswith("cpu_s."):
                stage = k.removeprefix("cpu_s.")
                spent[stage] = spent.get(stage, 0.0) + v - c0.get(k, 0.0)
    if jobs <= 0:
        return {}
    out = {k: v / jobs for k, v in sorted(spent.items(), key=lambda kv: -kv[1])}
    out["total"] = sum(out.values())
    return out


def cameras_per_core(cpu_s_per_kf: float | None, keyframes_per_s: float, cameras: int) -> float | None:
    """How many such cameras one core carries: one core's second over what one camera's keyframes cost per
    second (``keyframes_per_s`` offered by all ``cameras``, times ``cpu_s_per_kf`` of every process)."""
    if not cpu_s_per_kf or cameras <= 0 or keyframes_per_s <= 0:
        return None
    return 1.0 / (cpu_s_per_kf * keyframes_per_s / cameras)


def headline(phases: list[dict[str, Any]], cameras: int, fps: float, curve: bool = False) -> list[str]:
    """The report's first lines: per phase, CPU-seconds per keyframe (every process, workers included) with the
    latency beside it and the cameras one core carries; then where a worker's job spends its CPU. ``curve``: the
    phases are a scaling curve's (``argus worker`` processes counted per phase) rather than the mapper as deployed
    (its own local worker)."""
    from bench.report import markdown_table

    text = ["## CPU per keyframe", ""]
    for ph in phases:
        label = (f"{ph.get('workers', 0)} argus worker processes, " if curve else "") + \
            f"{ph.get('consumers', 0)} consumers"
        all_s = ph.get("cpu_s_per_kf.all")
        if not all_s:
            text.append(f"- {label}: no keyframe done")
            continue
        kf_per_cam = ph.get("keyframes_per_s", 0.0) / max(cameras, 1)
        per_core = cameras_per_core(all_s, ph.get("keyframes_per_s", 0.0), cameras)
        carries = (f"one core carries {per_core:.2f} such cameras ({fps:g} fps, {kf_per_cam:.2f} keyframes/s each)"
                   if per_core else "no keyframes offered")
        p50, p99 = (ph.get(k) or math.nan for k in ("latency_p50_ms", "latency_p99_ms"))
        text.append(f"- {label}: **{all_s:.3f} CPU-s per keyframe** (all processes, workers included); capture -> "
                    f"graph p50 {p50 / 1000:.2f} s, p99 {p99 / 1000:.2f} s; load {ph.get('load_avg_1m', math.nan):.1f}"
                    f"; {carries}")
    for ph in phases:
        jp = ph.get("job_cpu_s") or {}
        if not jp:
            continue
        total = jp["total"]
        rows = [{"stage": k, "CPU s per job": round(v, 4), "share": f"{100 * v / total:.0f} %" if total > 0 else "-"}
                for k, v in jp.items() if k != "total"]
        rows.append({"stage": "total (worker)", "CPU s per job": round(total, 4), "share": "100 %"})
        text += ["", f"Where a worker's keyframe job spends its CPU ({ph.get('consumers', 0)} consumers; the workers' "
                 "`cpu_s.<stage>` status counters):", "", markdown_table(rows)]
    return text


def with_headline(md: Path, lines: list[str]) -> None:
    """``lines`` put under the first line (the title) of the Markdown report ``md``."""
    text = md.read_text().splitlines()
    md.write_text("\n".join(text[:1] + [""] + lines + text[1:]) + "\n")


def append_model(md: Path, phases: list[dict[str, Any]]) -> None:
    """The scaling model under the report's table: per phase, CPU-seconds per keyframe per role, measured and
    predicted keyframes/s; then the curve each worker phase's costs predict for N workers."""
    from bench.report import markdown_table

    roles = sorted({k for ph in phases for k in ph if k.startswith(("cpu_s_per_kf.", "cpu_s_per_job."))})
    cols = ["workers", "consumers", "load_avg_1m", "keyframes_per_s", "keyframes_done_per_s", "model_kf_per_s_here",
            "latency_p50_ms", "latency_p99_ms", *roles, "bytes_per_job", "transfer_fetch_s_per_job",
            "result_decode_s_per_job", "job_roundtrip_s"]
    text = ["", "## Scaling model", "",
            "CPU-seconds per keyframe done, per role (bench/scaling.py); model_kf_per_s_here: "
            "min(N / w, 1 / c, cores / (c + o + w), keyframes offered).", "",
            markdown_table([{c: ph.get(c) for c in cols} for ph in phases], cols)]
    for ph in phases:
        if ph.get("model_curve"):
            costs = f"c {ph['model_c_s']:.3f} s, o {ph['model_o_s']:.3f} s, w {ph['model_w_s']:.3f} s per keyframe"
            text += [f"Predicted from the {ph['workers']}-worker phase ({ph['consumers']} consumers): {costs}", "",
                     markdown_table(ph["model_curve"])]
            pred = ", ".join(f"{r['workers']}: {r['model_kf_per_s_separate_machines']:.2f} / "
                             f"{r['model_kf_per_s_this_machine']:.2f}" for r in ph["model_curve"])
            _log(f"model from {ph['workers']} workers: {costs}; kf/s (separate machines / here) {pred}")
    with md.open("a") as f:
        f.write("\n".join(text) + "\n")


def _launch(endpoint: str, site: str, mapper_settings: dict[str, Any], n_workers: int,
            torch_threads: int | None) -> Any:
    """Router, mapper and ``n_workers`` ``argus worker`` processes (each with ``torch_threads``)."""
    from deploy.up import LaunchFile

    zenoh = {"mode": "client", "connect": [endpoint]}
    settings = {"site": site, "zenoh": zenoh, **mapper_settings}
    procs: list[dict[str, Any]] = [
        {"name": "router", "command": "router", "args": ["--listen", endpoint, "--site", site]},
        {"name": "mapper", "command": "mapper", "settings": settings},
        *worker_procs(endpoint, site, n_workers, torch_threads)]
    return LaunchFile.model_validate({"site": site, "endpoint": endpoint, "stop_timeout_s": 10, "process": procs})


def worker_procs(endpoint: str, site: str, n_workers: int, torch_threads: int | None = None) -> list[dict[str, Any]]:
    """Launch-file entries of ``n_workers`` ``argus worker`` processes (ids w0, w1, ...) joining ``endpoint``."""
    procs: list[dict[str, Any]] = []
    for i in range(n_workers):
        ws: dict[str, Any] = {"id": f"w{i}", "site": site, "zenoh": {"mode": "client", "connect": [endpoint]}}
        if torch_threads is not None:
            ws["torch_threads"] = torch_threads
        procs.append({"name": f"worker{i}", "command": "worker", "node_id": f"w{i}", "settings": ws})
    return procs


DROP_REASONS = ("superseded", "stale", "full", "shed", "given_up")
"""Why the mapper dropped keyframe jobs (``keyframes_dropped.<reason>.<source>`` in its status)."""


def drops_by_reason(status0: dict[str, float], status1: dict[str, float]) -> dict[str, float]:
    """Keyframes dropped during a phase per reason, summed over sources: ``dropped.<reason>``."""
    out = {f"dropped.{r}": 0.0 for r in DROP_REASONS}
    for name, v in status1.items():
        parts = name.split(".", 2)
        if len(parts) == 3 and parts[0] == "keyframes_dropped":
            key = f"dropped.{parts[1]}"
            out[key] = out.get(key, 0.0) + float(v) - float(status0.get(name, 0.0))
    return out


def _keyframes_done(diff: Any) -> float:
    """Keyframes whose work finished: done in the mapper's thread, or sent out and back (or done by the mapper)."""
    return (diff("keyframes") - diff("keyframes_offloaded", 0.0) + diff("work_results_accepted", 0.0)
            + diff("work_jobs_done_locally", 0.0))


LOCAL_WORKER_MODULE = "mapper.work.local"
"""What the command line of the mapper's local worker processes runs (``python -m mapper.work.local``)."""


def role_clock(stack: Any, mapper_pid: int) -> Any:
    """CPU clocks of the stack's roles (:class:`bench.scaling.RoleClock`): mapper, router, each worker (the mapper's
    local workers too, as ``mapper-local<i>``: looked up at each sample, they start after the mapper is up), this
    process."""
    from bench.scaling import ChildClock, RoleClock

    router = next((c.pid for c in stack.children if c.spec.command == "router"), None)
    workers = {(c.spec.node_id or c.spec.name): c.pid for c in stack.children
               if c.spec.command == "worker" and c.pid is not None}
    return RoleClock(mapper_pid, router, workers, local=ChildClock(mapper_pid, "mapper-local", LOCAL_WORKER_MODULE))


def phase_model(diff: Any, roles0: dict[str, float], roles1: dict[str, float], phase: dict[str, Any],
                n_workers: int) -> dict[str, Any]:
    """A phase's CPU-seconds per keyframe per role, transfer cost per job and the scaling model's predictions
    from them (:mod:`bench.scaling`): for ``n_workers`` here (next to the measured keyframes/s) and for N workers
    on their own machines."""
    from bench.scaling import curve, model_inputs, predict, role_costs

    done = _keyframes_done(diff)
    ids = [k.split(".", 1)[1] for k in roles1 if k.startswith("worker.")]
    jobs = {w: diff(f"worker_jobs_done.{w}", 0.0) for w in ids}
    out: dict[str, Any] = dict(role_costs(roles0, roles1, done, jobs))
    out["load_avg_1m"] = os.getloadavg()[0]  # the machine's load at the phase's end: wall-clock figures depend on it
    accepted = diff("work_results_accepted", 0.0)
    out["transfer_fetch_s_per_job"] = diff("work_fetch_s_sum", 0.0) / accepted if accepted > 0 else None
    out["result_decode_s_per_job"] = diff("work_decode_s_sum", 0.0) / accepted if accepted > 0 else None
    inputs = model_inputs(out, n_workers)
    if inputs is None:
        return out
    cores = os.cpu_count() or 1
    offered = phase["keyframes_per_s"]  # keyframes selected per second: what the cameras' frames offer
    p = predict(inputs["c"], inputs["o"], inputs["w"], n_workers, cores, phase.get("bytes_per_job"), offered=offered)
    out.update({"model_c_s": inputs["c"], "model_o_s": inputs["o"], "model_w_s": inputs["w"],
                "model_kf_per_s_here": p["shared"],
                "model_curve": curve(inputs, cores, phase.get("bytes_per_job"), None)})
    return out


def _run_stack(cams: list[CameraFrames], fps: float, phase_s: float, warmup_s: float, consumers: list[int],
               mapper_settings: dict[str, Any], consumer_rate_hz: float, n_workers: int) -> list[dict[str, Any]]:
    """One stack (router, mapper, ``n_workers`` workers) under the cameras' load: one phase per consumer count."""
    from deploy.demo import free_endpoint
    from deploy.up import Stack
    from protocol.session import ZenohSettings, open_session

    log = _log
    endpoint = free_endpoint()
    site = "benchsys"
    keys = Keys(site)
    launch = _launch(endpoint, site, mapper_settings, n_workers, mapper_settings.get("torch_threads"))
    lines: list[str] = []
    stack = Stack(launch, Path.cwd(), emit=lines.append)
    cameras = len(cams)
    phases: list[dict[str, Any]] = []
    players: list[CameraPlayer] = []
    session = None
    watch = None
    try:
        stack.start()
        if not stack.wait_healthy(120):
            raise RuntimeError("mapper did not come up:\n" + "\n".join(lines[-30:]))
        mapper_pid = next(c.pid for c in stack.children if c.spec.name == "mapper")
        assert mapper_pid is not None
        clock = role_clock(stack, mapper_pid)
        session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        watch = GraphWatch(session, keys)
        players = [CameraPlayer(session, keys, cam, fps) for cam in cams]
        for p in players:
            p.start()
        log(f"{cameras} cameras at {fps:g} fps into the mapper (pid {mapper_pid}, {n_workers} workers); "
            f"warm-up {warmup_s:.0f}s")
        time.sleep(warmup_s)
        for n_consumers in consumers:
            cons = [Consumer(endpoint, keys, consumer_rate_hz) for _ in range(n_consumers)]
            for c in cons:
                c.start()
            watch.take()
            sent0 = sum(p.sent for p in players)
            cpu0, t0 = proc_cpu_s(mapper_pid), time.monotonic()
            self_cpu0 = proc_cpu_s(os.getpid())
            roles0 = clock.sample()
            status0 = watch.take()[2]
            workers0 = watch.worker_status()
            time.sleep(phase_s)
            dt = time.monotonic() - t0
            cpu1, sent1 = proc_cpu_s(mapper_pid), sum(p.sent for p in players)
            self_cpu1 = proc_cpu_s(os.getpid())
            roles1 = clock.sample()
            lat, n_deltas, status1 = watch.take()
            for c in cons:
                c.stop()
            qlat = [x for c in cons for x in c.latencies_ms]
            def diff(name: str, default: float = float("nan"), s0: dict[str, float] = status0,
                     s1: dict[str, float] = status1) -> float:
                return float(s1.get(name, default)) - float(s0.get(name, default))

            received, processed, keyframes = diff("frames_in"), diff("frames_processed"), diff("keyframes")
            dropped = diff("frames_dropped")
            mem = proc_mem_mb(mapper_pid)
            phase = {
                "consumers": n_consumers,
                "offered_fps": (sent1 - sent0) / dt,
                "received_fps": received / dt,
                "processed_fps": processed / dt,
                "keyframes_per_s": keyframes / dt,
                "keyframes_done_per_s": _keyframes_done(diff) / dt,
                "keyframes_dropped": diff("keyframes_dropped", 0.0),
                **drops_by_reason(status0, status1),
                "keyframes_deferred": diff("keyframes_deferred"),
                "dropped": dropped,
                "dropped_frac": dropped / max(received, 1.0),
                "deltas": n_deltas,
                "latency_p50_ms": _pct(lat, 50), "latency_p99_ms": _pct(lat, 99),
                "query_p50_ms": _pct(qlat, 50), "query_p99_ms": _pct(qlat, 99),
                "queries": len(qlat), "query_failures": sum(c.failures for c in cons),
                "mapper_cpu_cores": (cpu1 - cpu0) / dt,
                "workers_cpu_cores": workers_cpu_s(roles0, roles1) / dt,  # the mapper's local workers too
                **work_model(diff, watch.worker_status()),
                "job_cpu_s": job_profile(workers0, watch.worker_status()),
                "bench_cpu_cores": (self_cpu1 - self_cpu0) / dt,  # cameras + consumers share the machine
                "mapper_rss_mb": mem["rss_mb"], "mapper_peak_rss_mb": mem["peak_rss_mb"],
                "mapper_status": status1,
            }
            phase.update(phase_model(diff, roles0, roles1, phase, n_workers))
            phases.append(phase)
            log(f"{n_consumers:2d} consumers: offered {phase['offered_fps']:.1f} fps, keyframes "
                f"{phase['keyframes_per_s']:.2f}/s, delta p50 {phase['latency_p50_ms'] or float('nan'):.0f} ms, "
                f"query p50 {phase['query_p50_ms'] or float('nan'):.1f} ms, cpu {phase['mapper_cpu_cores']:.2f}, "
                f"peak {mem['peak_rss_mb']:.0f} MiB")
    finally:
        stop_load(players, watch, session, stack)
    return phases


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench system",
        description="N simulated cameras at F fps into one argus mapper process: ingest, drops, "
        "capture->delta latency, mapper CPU and memory, query latency with 0/1/10 consumers.",
        epilog="example: argus bench system --cameras 2 --fps 2 --phase-s 30 --out bench_out/system",
    )
    p.add_argument("--cameras", type=int, default=2, help="simulated cameras")
    p.add_argument("--fps", type=float, default=2.0, help="frames per second per camera")
    p.add_argument("--phase-s", type=float, default=30.0, help="seconds per measured phase")
    p.add_argument("--warmup-s", type=float, default=15.0, help="seconds before measuring")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--frames-per-camera", type=int, default=24, help="distinct frames per camera (looped)")
    p.add_argument("--consumers", default="0,1,10", help="consumer counts, one phase each")
    p.add_argument("--consumer-rate", type=float, default=10.0, help="queries per second per consumer")
    p.add_argument("--geometry", default="mvs", help="mapper geometry backend")
    p.add_argument("--segmenter", default="classical",
                   help="mapper segmenter: classical, or sim (ORACLE: the cameras then also publish ground truth)")
    p.add_argument("--workers", default=None,
                   help="scaling curve: comma-separated counts of argus worker processes, one fresh stack each "
                   "(e.g. 0,1,2), with CPU-seconds per keyframe per role and the model's predictions; the mapper "
                   "then starts no local worker (workers.local=0 unless --mapper-set says otherwise). Default: no "
                   "worker column, the mapper as deployed (its local worker included)")
    p.add_argument("--torch-threads", type=int, default=None,
                   help="torch threads of the mapper and of each worker (1: one core each, for scaling curves)")
    p.add_argument("--quick", action="store_true", help="short run (1 camera, 10 s phases)")
    p.add_argument("--out", type=Path, default=Path("bench_out/system"))
    p.add_argument("--mapper-set", dest="mapper_set", action="append", default=[], metavar="PATH=VALUE",
                   help="mapper setting, e.g. --mapper-set workers.max_frame_age_s=1.0 (argus mapper --describe)")
    p.add_argument("--frames-cache", type=Path, default=None,
                   help="folder keeping the rendered frames between runs (same cameras, size, frames and seed: "
                   "not rendered again; delete it when the simulator changes)")
    a = p.parse_args(argv)
    if a.quick:
        a.cameras, a.phase_s, a.warmup_s, a.frames_per_camera = min(a.cameras, 2), 10.0, 8.0, 8
    consumers = [int(c) for c in a.consumers.split(",") if c.strip()]
    mapper_settings: dict[str, Any] = {"geometry": {"backend": a.geometry},
                                       "perception": {"segmenter": a.segmenter, "embedder": a.segmenter}}
    if a.torch_threads is not None:
        mapper_settings["torch_threads"] = a.torch_threads
    for item in a.mapper_set:
        from protocol.tomlconfig import ConfigError, parse_value, set_path

        path, sep, text = item.partition("=")
        try:
            if not sep:
                raise ConfigError("not PATH=VALUE")
            set_path(mapper_settings, path.strip(), parse_value(text.strip()))
        except ConfigError as e:
            print(f"argus bench system: --mapper-set {item!r}: {e}", file=sys.stderr)
            return 2
    workers = None if a.workers is None else [int(w) for w in a.workers.split(",") if w.strip()]
    if workers is not None:  # the curve counts argus worker processes: the mapper starts none of its own
        mapper_settings.setdefault("workers", {}).setdefault("local", 0)
    try:
        run(a.cameras, a.fps, a.phase_s, a.warmup_s, a.width, a.height, a.frames_per_camera, consumers,
            mapper_settings, a.out, consumer_rate_hz=a.consumer_rate, workers=workers, frames_cache=a.frames_cache)
    except Exception as e:  # noqa: BLE001 - a failed run is one message and exit 1
        print(f"argus bench system: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
