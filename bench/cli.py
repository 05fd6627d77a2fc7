"""``argus bench``: performance and quality benchmarks. Each writes JSON and a Markdown table.

Examples::

    argus bench transport --frames 300
    argus bench geometry --quick --out bench_out/geometry
    argus bench all --quick --out bench_out
"""

from __future__ import annotations

import importlib
import sys

# name -> (module with main(argv) -> int, one-line help)
BENCHES: dict[str, tuple[str, str]] = {
    "transport": ("bench.transport", "640x480 JPEG frames through a router on loopback: fps, MB/s, latency"),
    "edge": ("edge_camera.bench", "edge per-frame cost: grab + encode + put"),
    "robot": ("robot_agent.bench", "robot-agent per-frame cost and a fast-simulation exploration run"),
    "geometry": ("bench.geometry", "RGB-only depth and pose accuracy, seconds per keyframe"),
    "graph": ("bench.graph", "scene-graph node/edge quality vs ground truth, update and query time"),
    "rooms": ("bench.rooms", "room layer update time on a full map with 2,000 objects (quality: argus eval rooms)"),
    "planner": ("bench.planner", "planner decision time for many candidates and completions"),
    "detector": ("bench.detector", "detector segmenter on the real RGB-D frames: labelled boxes, masks, 3D nodes"),
    "perception": ("bench.modeltiming", "seconds per real frame of a segmenter + embedder (sam+clip on a GPU, ...)"),
    "system": ("bench.system", "N cameras into one mapper: ingest, drops, latency, CPU, memory, queries"),
    "soak": ("bench.soak", "the whole stack under load for 30 minutes: RSS per process, latency, drops"),
    "replay": ("bench.replay", "a recorded sequence through camera, router, mapper + worker: map vs its own depth"),
    "bigframes": ("bench.bigframes", "a mapper process's peak memory on streams of large frames, real and padded"),
}

LONG_RUNNING = {"soak", "replay", "bigframes"}  # not part of ``argus bench all`` (replay needs a recording: --sequence)

USAGE = """usage: argus bench <name> [options]   (argus bench <name> --help)
       argus bench all [--quick] [--out DIR]

benchmarks:
{listing}

examples:
  argus bench transport --frames 300 --out bench_out/transport
  argus bench geometry --quick --out bench_out/geometry
  argus bench all --quick --out bench_out        # every benchmark but soak, replay and bigframes

Each writes <name>.json and <name>.md under --out; docs/benchmarks.md lists the figures and their commands.
"""


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        width = max(len(n) for n in BENCHES)
        print(USAGE.format(listing="\n".join(f"  {n.ljust(width)}  {h}" for n, (_, h) in BENCHES.items())))
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name == "all":
        return _run_all(rest)
    if name not in BENCHES:
        print(f"argus bench: unknown benchmark {name!r}", file=sys.stderr)
        return 2
    return int(importlib.import_module(BENCHES[name][0]).main(rest) or 0)


def _run_all(rest: list[str]) -> int:
    out = "bench_out"
    if "--out" in rest:
        i = rest.index("--out")
        out = rest[i + 1]
        rest = rest[:i] + rest[i + 2 :]
    failed = []
    for name, (module, _) in BENCHES.items():
        if name in LONG_RUNNING:
            print(f"== argus bench {name}: skipped by 'all' (run it on its own)", flush=True)
            continue
        print(f"== argus bench {name}", flush=True)
        try:
            rc = int(importlib.import_module(module).main([*rest, "--out", f"{out}/{name}"]) or 0)
        except SystemExit as e:  # argparse errors in one bench must not stop the others
            rc = int(e.code or 0)
        if rc:
            failed.append(name)
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 1 if failed else 0
