"""``argus bench soak``: the whole stack under sustained load for a long time, memory and latency sampled.

The demo stack (router, mapper, planner, one simulated robot exploring with no step budget, one
simulated overhead camera) runs as real processes through :class:`deploy.up.Stack`, and this process
adds ``--cameras`` simulated cameras at ``--fps`` each (pre-rendered frames replayed in a loop, every
frame re-stamped), enough to saturate the mapper. Every ``--sample-s`` seconds it records, per process,
resident memory (``VmRSS``), and, for the mapper, its Status counters (frames in / processed / dropped,
keyframes, nodes) and the capture-to-delta latency of the window (p50 / p99).

Reported: RSS at the end of the warm-up and at the end, growth in percent (the bar: < 10 % after the
first 5 minutes), frames dropped per reason, latency p50 / p99 over the run, whether any process exited.
Writes ``soak.json``, ``soak.md`` and ``soak.png`` (RSS and latency over time).

Example::

    argus bench soak --minutes 30 --cameras 4 --fps 2 --out bench_out/soak
    argus bench soak --quick
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.report import write_report
from bench.system import CameraPlayer, GraphWatch, _pct, proc_mem_mb, render_cameras, stop_load
from protocol.keys import Keys

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "deploy" / "launch" / "demo.toml"
DROP_COUNTERS = ("frames_dropped", "sources_refused", "decode_errors", "header_errors", "pose_errors")


def soak_launch(endpoint: str, max_steps: int = 100_000) -> Any:
    """The demo launch file on ``endpoint`` with the robot's step budget lifted (it explores all run)."""
    from deploy.demo import DemoConfig, prepare_launch
    from deploy.up import with_endpoint

    return with_endpoint(prepare_launch(DemoConfig(launch=DEMO, steps=max_steps, free_port=False)), endpoint)


def growth_pct(series: list[float], warmup_samples: int) -> float | None:
    """RSS growth after the warm-up, in percent: the median of the last fifth of the samples after the
    warm-up against the median of the first fifth (medians, because a process's RSS spikes while it
    works, e.g. the planner during a decision, and a single sample says little about a leak)."""
    after = [v for v in series[warmup_samples:] if v == v]
    if len(after) < 2:
        return None
    w = max(min(3, len(after) // 2), len(after) // 5)
    base = float(np.median(after[:w]))
    return 100.0 * (float(np.median(after[-w:])) - base) / base if base > 0 else None


def _plot(samples: list[dict[str, Any]], warmup_s: float, out: Path) -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    t = [s["t_s"] / 60.0 for s in samples]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for name in samples[0]["rss_mb"]:
        ax1.plot(t, [s["rss_mb"].get(name, float("nan")) for s in samples], label=name)
    ax1.axvline(warmup_s / 60.0, color="grey", linestyle=":", label="end of warm-up")
    ax1.set_ylabel("RSS (MiB)")
    ax1.legend(fontsize=7)
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


def run(minutes: float, warmup_min: float, cameras: int, fps: float, sample_s: float, width: int, height: int,
        out: Path) -> dict[str, Any]:
    from deploy.demo import free_endpoint
    from deploy.up import Stack
    from protocol.session import client, open_session

    def log(msg: str) -> None:
        print(f"[bench soak] {msg}", flush=True)

    launch = soak_launch(free_endpoint())
    keys = Keys(launch.site)
    world = launch.world
    assert world is not None
    cams = render_cameras(cameras, 24, width, height, world.family, world.seed, oracle=True)
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
        log(f"{len(stack.children)} processes + {cameras} cameras at {fps:g} fps for {minutes:g} min "
            f"(warm-up {warmup_min:g} min), sampling every {sample_s:g}s")
        t0 = time.monotonic()
        while time.monotonic() - t0 < minutes * 60.0:
            time.sleep(sample_s)
            if not stack.step():
                exits = list(stack.failed)
                log(f"process(es) ended: {exits}")
                break
            lat, n_deltas, status = watch.take()
            all_latencies += lat
            rss = {}
            for c in stack.children:
                if c.pid is not None and c.poll() is None:
                    rss[c.spec.name] = proc_mem_mb(c.pid)["rss_mb"]
            t_s = time.monotonic() - t0
            sample = {
                "t_s": t_s, "rss_mb": rss, "deltas": n_deltas,
                "latency_p50_ms": _pct(lat, 50), "latency_p99_ms": _pct(lat, 99),
                "sent": sum(p.sent for p in players),
                **{k: status.get(k) for k in ("frames_in", "frames_processed", "keyframes", "nodes",
                                              *DROP_COUNTERS)},
            }
            samples.append(sample)
            log(f"{t_s / 60:5.1f} min: rss " + ", ".join(f"{k} {v:.0f}" for k, v in rss.items())
                + f" MiB; nodes {sample['nodes']}; delta p99 {sample['latency_p99_ms'] or float('nan'):.0f} ms;"
                f" dropped {sample['frames_dropped']}")
    finally:
        stop_load(players, watch, session, stack)
    warmup_n = sum(1 for s in samples if s["t_s"] <= warmup_min * 60.0)
    names = list(samples[0]["rss_mb"]) if samples else []
    rows = []
    for name in names:
        series = [s["rss_mb"].get(name, float("nan")) for s in samples]
        rows.append({"process": name, "rss_start_mb": series[0],
                     "rss_after_warmup_mb": series[warmup_n - 1] if warmup_n else None,
                     "rss_end_mb": series[-1], "rss_peak_mb": float(np.nanmax(series)),
                     "growth_after_warmup_pct": growth_pct(series, warmup_n)})
    last = samples[-1] if samples else {}
    results = {
        "minutes": minutes, "warmup_min": warmup_min, "cameras": cameras, "fps": fps, "sample_s": sample_s,
        "width": width, "height": height, "exits": exits, "processes": rows,
        "latency_p50_ms": _pct(all_latencies, 50), "latency_p99_ms": _pct(all_latencies, 99),
        "frames_offered": last.get("sent"), "frames_in": last.get("frames_in"),
        "frames_processed": last.get("frames_processed"), "keyframes": last.get("keyframes"),
        "drops": {k: last[k] for k in DROP_COUNTERS if last.get(k) is not None}, "samples": samples,
    }
    write_report(out, "soak", results, rows,
                 title=f"Soak: demo stack + {cameras} cameras at {fps:g} fps for {minutes:g} min "
                       f"(latency p50 {results['latency_p50_ms']} ms, p99 {results['latency_p99_ms']} ms; "
                       f"drops {results['drops']}; exits {exits or 'none'})")
    if samples:
        _plot(samples, warmup_min * 60.0, out)
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="argus bench soak", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=30.0, help="length of the run")
    p.add_argument("--warmup-min", type=float, default=5.0, help="minutes before RSS growth is measured")
    p.add_argument("--cameras", type=int, default=4, help="extra simulated cameras (plus the demo's robot and camera)")
    p.add_argument("--fps", type=float, default=2.0, help="frames per second per extra camera")
    p.add_argument("--sample-s", type=float, default=10.0, help="seconds between samples")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--quick", action="store_true", help="2 minutes, 1 minute warm-up, 2 cameras, 5 s samples")
    p.add_argument("--out", type=Path, default=Path("bench_out/soak"))
    a = p.parse_args(argv)
    if a.quick:
        a.minutes, a.warmup_min, a.cameras, a.sample_s = 2.0, 1.0, 2, 5.0
    res = run(a.minutes, a.warmup_min, a.cameras, a.fps, a.sample_s, a.width, a.height, a.out)
    print((a.out / "soak.md").read_text())
    return 1 if res["exits"] else 0


if __name__ == "__main__":
    sys.exit(main())
