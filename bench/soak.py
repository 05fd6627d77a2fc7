"""``argus bench soak``: the whole stack under sustained load for a long time, memory, sizes and latency sampled.

The demo stack (router, mapper, planner, one simulated robot exploring with no step budget, one
simulated overhead camera) runs as real processes through :class:`deploy.up.Stack`, with ``--workers``
``argus worker`` processes beside it (the mapper's own local worker, ``[workers] local``, runs in every case and
is sampled as ``mapper.child0``), and this process adds ``--cameras``
simulated cameras at ``--fps`` each (pre-rendered frames replayed in a loop, every frame re-stamped), enough to
saturate the mapper. Every ``--sample-s`` seconds it records, per process, resident memory (``VmRSS``); from
the processes' Status: the mapper's counters (frames in / processed / dropped, keyframes) and the sizes of what
must stay bounded (graph nodes and edges, keyframes stored, point-map voxels, the worker keyframe store's JPEGs,
buffered frame bytes; the planner's containers); the capture-to-delta latency of the window (p50 / p99); and the
machine's load average (the machine is shared: latency is measured under that load).

Reported per process: RSS at the start, its resting level after the warm-up and at the end (the 10th
percentile of a window of samples: a process's RSS spikes while it works, e.g. the planner during a decision,
and a leak is the resting level rising), the peak, and the growth of the resting level in percent (the bar:
< 10 % after the first 5 minutes); each size after the warm-up, at the end and its maximum; frames dropped per
reason; latency p50 / p99 over the run; the load average; whether any process exited.
Writes ``soak.json``, ``soak.md`` and ``soak.png`` (RSS, sizes and latency over time).

Example::

    argus bench soak --minutes 30 --cameras 4 --fps 2 --workers 1 --out bench_out/soak
    argus bench soak --quick
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.report import markdown_table, write_report
from bench.scaling import child_pids
from bench.system import CameraPlayer, GraphWatch, _pct, proc_mem_mb, render_cameras, stop_load, worker_procs
from protocol.keys import Keys

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "deploy" / "launch" / "demo.toml"
DROP_COUNTERS = ("frames_dropped", "sources_refused", "decode_errors", "header_errors", "pose_errors",
                 "keyframes_dropped", "jobs_dropped_full")
MAPPER_SIZES = ("nodes", "edges", "keyframes_stored", "pointmap_voxels", "keyframe_store_jpegs",
                "frame_bytes_buffered")
"""Mapper Status counters that must stay bounded (sampled as ``mapper.<name>``)."""
PLANNER_SIZES = ("graph_nodes", "point_map_points", "history_views", "blacklisted_viewpoints", "hypotheses",
                 "frontier_points")
"""Planner Status counters that must stay bounded (sampled as ``planner.<name>`` where the planner reports them)."""
REST_PERCENTILE = 10.0
"""A window's resting RSS: this percentile of its samples (spikes while a process works are not a leak)."""


def soak_launch(endpoint: str, max_steps: int = 100_000, workers: int = 0) -> Any:
    """The demo launch file on ``endpoint`` with the robot's step budget lifted (it explores all run) and
    ``workers`` ``argus worker`` processes beside it (they compute geometry; ORACLE masks stay in the mapper)."""
    from deploy.demo import DemoConfig, prepare_launch
    from deploy.up import ProcessSpec, with_endpoint

    launch = with_endpoint(prepare_launch(DemoConfig(launch=DEMO, steps=max_steps,
                                                     free_port=False)), endpoint)
    if not workers:
        return launch
    extra = [ProcessSpec.model_validate(p) for p in worker_procs(endpoint, launch.site, workers)]
    return launch.model_copy(update={"process": [*launch.process, *extra]})


def resting_mb(values: list[float]) -> float:
    """The resting level of a window of RSS samples (:data:`REST_PERCENTILE`)."""
    return float(np.percentile(values, REST_PERCENTILE))


def _windows(series: list[float], warmup_samples: int) -> tuple[list[float], list[float]] | None:
    """The first and the last window of the samples after the warm-up (a fifth of them each, at least 3 when
    there are 6), or None with fewer than 2 samples."""
    after = [v for v in series[warmup_samples:] if v == v]
    if len(after) < 2:
        return None
    w = max(min(3, len(after) // 2), len(after) // 5)
    return after[:w], after[-w:]


def growth_pct(series: list[float], warmup_samples: int) -> float | None:
    """RSS growth after the warm-up, in percent: the resting level (:func:`resting_mb`) of the last fifth of
    the samples after the warm-up against that of the first fifth. Not the median: a process that spikes in
    more than half of the samples early (the planner deciding often while the map is new) and less later
    would show a negative growth while its resting level rises."""
    win = _windows(series, warmup_samples)
    if win is None:
        return None
    base = resting_mb(win[0])
    return 100.0 * (resting_mb(win[1]) - base) / base if base > 0 else None


def process_row(name: str, series: list[float], warmup_samples: int) -> dict[str, Any]:
    """One process's row: RSS at the start, resting after the warm-up and at the end, peak, growth."""
    win = _windows(series, warmup_samples)
    return {"process": name, "rss_start_mb": series[0],
            "rss_rest_after_warmup_mb": resting_mb(win[0]) if win else None,
            "rss_rest_end_mb": resting_mb(win[1]) if win else None,
            "rss_last_mb": series[-1], "rss_peak_mb": float(np.nanmax(series)),
            "growth_after_warmup_pct": growth_pct(series, warmup_samples)}


def size_rows(samples: list[dict[str, Any]], warmup_samples: int) -> list[dict[str, Any]]:
    """Each sampled size (``sizes`` of the samples): after the warm-up, at the end, its maximum."""
    names = sorted({k for s in samples for k in s.get("sizes", {})})
    rows = []
    for name in names:
        series = [s["sizes"][name] for s in samples if name in s.get("sizes", {})]
        after = [s["sizes"][name] for s in samples[warmup_samples:] if name in s.get("sizes", {})]
        rows.append({"size": name, "after_warmup": after[0] if after else None, "end": series[-1],
                     "max": max(series)})
    return rows


def sizes_of(mapper: dict[str, float], others: dict[str, dict[str, float]]) -> dict[str, float]:
    """The bounded sizes from the processes' Status counters, named ``<process>.<counter>``."""
    out = {f"mapper.{k}": float(mapper[k]) for k in MAPPER_SIZES if k in mapper}
    for name, counters in others.items():
        if name.startswith("planner/"):
            out.update({f"planner.{k}": float(counters[k]) for k in PLANNER_SIZES if k in counters})
    return out


def _plot(samples: list[dict[str, Any]], warmup_s: float, out: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    t = [s["t_s"] / 60.0 for s in samples]
    fig, (ax1, ax3, ax2) = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for name in samples[0]["rss_mb"]:
        ax1.plot(t, [s["rss_mb"].get(name, float("nan")) for s in samples], label=name)
    ax1.axvline(warmup_s / 60.0, color="grey", linestyle=":", label="end of warm-up")
    ax1.set_ylabel("RSS (MiB)")
    ax1.legend(fontsize=7)
    for name in sorted({k for s in samples for k in s.get("sizes", {})}):
        series = [s.get("sizes", {}).get(name, float("nan")) for s in samples]
        top = np.nanmax(series) if any(v == v for v in series) else 0.0
        if top > 0:  # each size relative to its maximum: one axis for counts of very different scales
            ax3.plot(t, [v / top for v in series], label=f"{name} (max {top:.0f})")
    ax3.set_ylabel("size / its max")
    ax3.legend(fontsize=6)
    ax2.plot(t, [s["latency_p50_ms"] or float("nan") for s in samples], label="p50")
    ax2.plot(t, [s["latency_p99_ms"] or float("nan") for s in samples], label="p99")
    ax2.set_ylabel("capture -> delta (ms)")
    ax2.set_xlabel("minutes")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    path = out / "soak.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _sample(t_s: float, stack: Any, players: list[CameraPlayer], watch: GraphWatch,
            all_latencies: list[float]) -> dict[str, Any]:
    """One sample: RSS per live process, the window's latency, the counters and sizes, the load average."""
    lat, n_deltas, status = watch.take()
    all_latencies += lat
    rss = {c.spec.name: proc_mem_mb(c.pid)["rss_mb"] for c in stack.children
           if c.pid is not None and c.poll() is None}
    for c in stack.children:  # the mapper's local workers
        if c.pid is not None:
            for i, pid in enumerate(child_pids(c.pid)):
                try:
                    rss[f"{c.spec.name}.child{i}"] = proc_mem_mb(pid)["rss_mb"]
                except OSError:  # it exited meanwhile
                    continue
    return {
        "t_s": t_s, "rss_mb": rss, "deltas": n_deltas,
        "latency_p50_ms": _pct(lat, 50), "latency_p99_ms": _pct(lat, 99),
        "sent": sum(p.sent for p in players), "load_avg_1m": os.getloadavg()[0],
        "sizes": sizes_of(status, watch.other_status()),
        **{k: status.get(k) for k in ("frames_in", "frames_processed", "keyframes", "nodes", "work_results_accepted",
                                      *DROP_COUNTERS)},
    }


def summarize(samples: list[dict[str, Any]], warmup_min: float) -> dict[str, Any]:
    """Per-process RSS rows, size rows, drops and load average of a run's samples."""
    warmup_n = sum(1 for s in samples if s["t_s"] <= warmup_min * 60.0)
    names = list(dict.fromkeys(k for s in samples for k in s["rss_mb"]))
    rows = [process_row(n, [s["rss_mb"].get(n, float("nan")) for s in samples], warmup_n) for n in names]
    last = samples[-1] if samples else {}
    loads = [s["load_avg_1m"] for s in samples if s.get("load_avg_1m") is not None]
    return {"processes": rows, "sizes": size_rows(samples, warmup_n),
            "frames_offered": last.get("sent"), "frames_in": last.get("frames_in"),
            "frames_processed": last.get("frames_processed"), "keyframes": last.get("keyframes"),
            "work_results_accepted": last.get("work_results_accepted"),
            "drops": {k: last[k] for k in DROP_COUNTERS if last.get(k) is not None},
            "load_avg_1m_mean": float(np.mean(loads)) if loads else None,
            "load_avg_1m_max": float(np.max(loads)) if loads else None}


def run(minutes: float, warmup_min: float, cameras: int, fps: float, sample_s: float, width: int, height: int,
        out: Path, workers: int = 0) -> dict[str, Any]:
    from deploy.demo import free_endpoint
    from deploy.up import Stack
    from protocol.session import client, open_session

    def log(msg: str) -> None:
        print(f"[bench soak] {msg}", flush=True)

    launch = soak_launch(free_endpoint(), workers=workers)
    keys = Keys(launch.site)
    world = launch.world
    assert world is not None
    cams = render_cameras(cameras, 24, width, height, world.family, world.seed, oracle=True)  # the demo: ORACLE masks
    lines: list[str] = []
    stack = Stack(launch, DEMO.parent, emit=lines.append)
    samples: list[dict[str, Any]] = []
    exits: list[str] = []
    players: list[CameraPlayer] = []
    session = watch = None
    all_latencies: list[float] = []
    try:
        stack.start()
        if not stack.wait_healthy(240):
            raise RuntimeError("stack did not come up:\n" + "\n".join(lines[-30:]))
        session = open_session(client(launch.endpoint))
        watch = GraphWatch(session, keys)
        players = [CameraPlayer(session, keys, cam, fps) for cam in cams]
        for p in players:
            p.start()
        log(f"{len(stack.children)} processes ({workers} workers) + {cameras} cameras at {fps:g} fps for "
            f"{minutes:g} min (warm-up {warmup_min:g} min), sampling every {sample_s:g}s")
        t0 = time.monotonic()
        while time.monotonic() - t0 < minutes * 60.0:
            time.sleep(sample_s)
            if not stack.step():
                exits = list(stack.failed)
                log(f"process(es) ended: {exits}")
                break
            sample = _sample(time.monotonic() - t0, stack, players, watch, all_latencies)
            samples.append(sample)
            log(f"{sample['t_s'] / 60:5.1f} min: rss " + ", ".join(f"{k} {v:.0f}" for k, v in sample["rss_mb"].items())
                + f" MiB; sizes {sample['sizes']}; delta p99 {sample['latency_p99_ms'] or float('nan'):.0f} ms;"
                f" dropped {sample['frames_dropped']}; load {sample['load_avg_1m']:.1f}")
    finally:
        stop_load(players, watch, session, stack)
    results = {
        "minutes": minutes, "warmup_min": warmup_min, "cameras": cameras, "fps": fps, "sample_s": sample_s,
        "workers": workers, "width": width, "height": height, "exits": exits,
        "latency_p50_ms": _pct(all_latencies, 50), "latency_p99_ms": _pct(all_latencies, 99),
        **summarize(samples, warmup_min), "samples": samples,
    }
    _, md = write_report(out, "soak", results, results["processes"],
                 title=f"Soak: demo stack + {workers} workers + {cameras} cameras at {fps:g} fps for {minutes:g} min "
                       f"(latency p50 {_fmt(results['latency_p50_ms'])} ms, p99 {_fmt(results['latency_p99_ms'])} ms "
                       f"under load avg {_fmt(results['load_avg_1m_mean'], '.1f')} (max "
                       f"{_fmt(results['load_avg_1m_max'], '.1f')}) on {os.cpu_count()} cores; "
                       f"drops {results['drops']};"
                       f" exits {exits or 'none'})")
    md.write_text(md.read_text() + "\nSizes (from the processes' Status):\n\n" + markdown_table(results["sizes"]))
    if samples:
        _plot(samples, warmup_min * 60.0, out)
    return results


def _fmt(v: float | None, spec: str = ".0f") -> str:
    return "n/a" if v is None else format(v, spec)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="argus bench soak", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=30.0, help="length of the run")
    p.add_argument("--warmup-min", type=float, default=5.0, help="minutes before RSS growth is measured")
    p.add_argument("--cameras", type=int, default=4, help="extra simulated cameras (plus the demo's robot and camera)")
    p.add_argument("--fps", type=float, default=2.0, help="frames per second per extra camera")
    p.add_argument("--sample-s", type=float, default=10.0, help="seconds between samples")
    p.add_argument("--width", type=int, default=320, help="extra cameras' image width")
    p.add_argument("--height", type=int, default=240, help="extra cameras' image height")
    p.add_argument("--workers", type=int, default=0,
                   help="argus worker processes beside the stack (then the RGB-only demo: ORACLE inputs stay local)")
    p.add_argument("--quick", action="store_true", help="2 minutes, 1 minute warm-up, 2 cameras, 5 s samples")
    p.add_argument("--out", type=Path, default=Path("bench_out/soak"))
    a = p.parse_args(argv)
    if a.quick:
        a.minutes, a.warmup_min, a.cameras, a.sample_s = 2.0, 1.0, 2, 5.0
    res = run(a.minutes, a.warmup_min, a.cameras, a.fps, a.sample_s, a.width, a.height, a.out, a.workers)
    print((a.out / "soak.md").read_text())
    return 1 if res["exits"] else 0


if __name__ == "__main__":
    sys.exit(main())
