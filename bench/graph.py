"""``argus bench graph``: scene-graph quality against the simulator's ground truth, update and query time.

For each scene family a scripted robot tour (a lattice of navigable viewpoints, four headings each,
visited in a nearest-neighbour walk) plus the fixed cameras is rendered once; the frames go through an
in-process :class:`mapper.core.MapperCore` with ORACLE 2D perception (the simulator's semantic camera)
and each geometry backend: ``oracle`` (true depth and poses, the paper's CG) and ``mvs`` (RGB only,
CG-RGB). Nodes and edges are scored with :mod:`sim.scoring`. Query latency is measured on a 150-node
graph served by a real mapper node over Zenoh on loopback.

Example::

    argus bench graph --quick --out bench_out/graph
    argus bench graph --families furnished_room --geometries oracle mvs
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

BARS = {
    "node_f1_oracle_furnished_room": (">=", 0.80),
    "node_f1_oracle_apartment": (">=", 0.70),
    "parity_gap_furnished_room": ("<=", 0.03),
    "parity_gap_apartment": ("<=", 0.03),
    "edge_precision_oracle_furnished_room": (">=", 0.80),
    "edge_precision_oracle_apartment": (">=", 0.80),
    "update_s_per_keyframe_mvs_p95": ("<=", 3.0),
    "query_p99_ms": ("<=", 20.0),
}


# --- frames ---------------------------------------------------------------------------------------
def tour_poses(scene: Any, spacing_m: float, n_headings: int, max_views: int | None = None) -> list[np.ndarray]:
    """Camera poses of a scripted robot tour: lattice viewpoints in a nearest-neighbour walk."""
    from protocol.poses import camera_pose_from_base
    from sim.nav import NavMap

    nav = NavMap(scene)
    spots = sorted({(v.x, v.y) for v in nav.viewpoints(spacing_m=spacing_m, n_headings=1)})
    if not spots:
        raise RuntimeError(f"scene {scene.family}/{scene.seed} has no navigable viewpoint")
    pts = np.array(spots)
    order = [0]
    left = set(range(1, len(pts)))
    while left:
        cur = pts[order[-1]]
        nxt = min(left, key=lambda i: (float(np.linalg.norm(pts[i] - cur)), i))
        order.append(nxt)
        left.remove(nxt)
    poses = []
    for k, i in enumerate(order):
        x, y = pts[i]
        for h in range(n_headings):
            # Alternate the turning direction so consecutive stops face alike (stereo neighbours).
            yaw = 2 * math.pi * h / n_headings * (1 if k % 2 == 0 else -1)
            poses.append(camera_pose_from_base(float(x), float(y), yaw, 1.0, -15.0))
    return poses[:max_views] if max_views else poses


def render_views(scene: Any, poses: list[np.ndarray], intr: Any, source_id: str, posed: list[bool],
                 renderer: Any, stamp0_ns: int = 0) -> tuple[list[Any], dict[int, int]]:
    """Mapper views (with ORACLE data) of ``poses``; also the max visible pixel count per object."""
    from mapper.geometry.contract import OracleData, View

    labels = scene.labels()
    views: list[View] = []
    seen: dict[int, int] = {}
    for i, (T, known) in enumerate(zip(poses, posed, strict=True)):
        out = renderer.render(intr, T)
        ids, counts = np.unique(out.instance_id[out.instance_id > 0], return_counts=True)
        for k, c in zip(ids.tolist(), counts.tolist(), strict=True):
            seen[k] = max(seen.get(k, 0), c)
        oracle = OracleData(depth_m=out.depth_m, T_world_cam_true=np.asarray(T), instance_id=out.instance_id,
                            labels=labels)
        views.append(View(image=out.rgb, source_id=source_id, intrinsics=intr,
                          T_world_cam=np.asarray(T) if known else None, pose_trusted=False,
                          stamp_ns=stamp0_ns + (i + 1) * 100_000_000, seq=i, oracle=oracle))
    return views, seen


# --- one run ---------------------------------------------------------------------------------------
def run_mapping(views: list[Any], geometry: str, threads: int) -> tuple[Any, dict[str, Any]]:
    import torch

    from bench.explore import core_config
    from mapper.core import MapperCore

    torch.set_num_threads(threads)
    core = MapperCore(core_config(geometry, "sim", threads))
    t0 = time.perf_counter()
    for v in views:
        # Every tour frame is a keyframe by construction (>= 45 deg or >= spacing apart); forcing it keeps
        # the fixed cameras' single frames in too.
        core.ingest(v, force_keyframe=True)
    wall = time.perf_counter() - t0
    times = np.array(core.update_times_s) if core.update_times_s else np.zeros(1)
    stats = {
        "keyframes": int(core.counters.get("keyframes", 0)),
        "keyframe_errors": int(core.counters.get("keyframe_errors", 0)),
        "views_unposed_skipped": int(core.counters.get("views_unposed_skipped", 0)),
        "detections": int(core.counters.get("detections", 0)),
        "detections_dropped_no_depth": int(core.counters.get("detections_dropped_no_depth", 0)),
        "detections_dropped_noise": int(core.counters.get("detections_dropped_noise", 0)),
        "keyframes_rejected_depth": int(core.counters.get("keyframes_rejected_depth", 0)),
        "update_s_mean": float(times.mean()),
        "update_s_p50": float(np.percentile(times, 50)),
        "update_s_p95": float(np.percentile(times, 95)),
        "update_s_max": float(times.max()),
        "wall_s": wall,
    }
    return core, stats


def score_run(core: Any, scene: Any, visible_ids: list[int]) -> dict[str, Any]:
    from sim.scoring import score_edges, score_nodes

    snap = core.snapshot()
    ns = score_nodes(snap.nodes, scene)
    vis = score_nodes(snap.nodes, scene, obj_ids=visible_ids)
    es = score_edges(snap.edges, ns.node_to_obj, scene.relations)
    missed = [scene.object_by_id(i).label for i in ns.unmatched_true]
    false_pos = [n.label for n in snap.nodes if n.node_id in set(ns.unmatched_pred)]
    return {
        "node": {k: v for k, v in ns.summary().items() if k not in ("unmatched_pred", "unmatched_true")},
        "node_visible": {"precision": vis.precision, "recall": vis.recall, "f1": vis.f1, "n_true": vis.n_true},
        "missed_labels": sorted(missed),
        "false_positive_labels": sorted(false_pos),
        "edge": {
            "precision": es.precision, "recall": es.recall, "f1": es.f1, "n_pred_judged": es.n_pred_judged,
            "n_true_judged": es.n_true_judged, "n_correct": es.n_correct, "strict_precision": es.strict_precision,
            "strict_recall": es.strict_recall, "unscored_predicates": es.unscored_predicates,
            "per_predicate": es.per_predicate, "wrong_examples": [list(t) for t in es.wrong[:10]],
        },
        "n_edges": len(snap.edges),
    }


# --- query latency ---------------------------------------------------------------------------------
def synthetic_nodes(n: int, seed: int = 0) -> list[Any]:
    from protocol.messages import GraphNode, OrientedBox, vec3

    rng = np.random.default_rng(seed)
    names = ["chair", "table", "lamp", "sofa", "mug", "book", "plant", "tv", "bed", "shelf"]
    out = []
    for i in range(n):
        c = vec3(rng.uniform([0, 0, 0], [10, 8, 2]))
        out.append(GraphNode(
            node_id=f"n{i + 1:06d}", label=names[i % len(names)], label_confidence=0.9, centroid=c,
            box=OrientedBox(center=c, extent=(0.5, 0.5, 0.5)), point_count=500, observation_count=3,
            sources=["robot1"], first_seen_ns=1, last_seen_ns=2,
            embedding=rng.normal(size=128).astype(np.float32),
        ))
    return out


def query_latency(n_nodes: int = 150, n_queries: int = 400) -> dict[str, Any]:
    """p50/p99 of Zenoh graph queries answered by a MapperNode holding ``n_nodes`` nodes (loopback)."""
    import socket

    import zenoh

    from mapper.config import MapperConfig
    from mapper.core import MapperCore
    from mapper.node import MapperNode
    from mapper.relations import compute_edges
    from protocol.keys import Keys
    from protocol.query import GraphQuery
    from protocol.session import ZenohSettings, open_session

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tcp/127.0.0.1:{port}"
    cfg = MapperConfig.model_validate({
        "site": "benchquery", "geometry": {"backend": "oracle"},
        "perception": {"segmenter": "sim", "embedder": "sim"},
        "zenoh": {"mode": "peer", "connect": [], "listen": [ep]}, "status_period_s": 5.0,
    })
    core = MapperCore(cfg)
    nodes = synthetic_nodes(n_nodes)
    core.store.commit(nodes, [], compute_edges({n.node_id: n.box for n in nodes}), time.time_ns())
    node = MapperNode(cfg, core)
    stop = threading.Event()
    th = threading.Thread(target=node.run, args=(stop,), daemon=True)
    th.start()
    keys = Keys("benchquery")
    selectors = [
        ("label", keys.graph_nodes, GraphQuery(label="chair").to_parameters()),
        ("near", keys.graph_nodes, GraphQuery(near=(5.0, 4.0, 1.0), radius=1.5).to_parameters()),
        ("id", keys.graph_nodes, GraphQuery(id="n000042").to_parameters()),
        ("snapshot", keys.graph_snapshot, ""),
    ]
    times: dict[str, list[float]] = {name: [] for name, _, _ in selectors}
    try:
        with open_session(ZenohSettings(mode="peer", connect=[ep])) as session:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                if any(r.ok is not None for r in session.get(keys.graph_snapshot, timeout=1.0)):
                    break
            for i in range(n_queries):
                name, key, params = selectors[i % len(selectors)]
                sel = zenoh.Selector(key, params) if params else key
                t0 = time.perf_counter()
                replies = [r for r in session.get(sel, timeout=2.0) if r.ok is not None]
                dt = (time.perf_counter() - t0) * 1e3
                if replies:
                    times[name].append(dt)
    finally:
        stop.set()
        th.join(timeout=10)
    all_t = np.array([t for v in times.values() for t in v]) if any(times.values()) else np.array([np.inf])
    return {
        "n_nodes": n_nodes,
        "n_answered": int(sum(len(v) for v in times.values())),
        "n_queries": n_queries,
        "p50_ms": float(np.percentile(all_t, 50)),
        "p99_ms": float(np.percentile(all_t, 99)),
        "per_selector_p99_ms": {k: float(np.percentile(v, 99)) if v else None for k, v in times.items()},
    }


# --- main ------------------------------------------------------------------------------------------
def run(args: argparse.Namespace, log: Any = print) -> dict[str, Any]:
    from protocol.messages import Intrinsics
    from sim.cameras import place_fixed_cameras
    from sim.render import Renderer
    from sim.scene import generate_scene

    intr = Intrinsics.from_fov(args.width, args.height, 90.0)
    results: dict[str, Any] = {"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                               "perception": "ORACLE 2D perception (sim semantic camera)", "families": {}}
    for family in args.families:
        scene = generate_scene(family, args.seed)
        renderer = Renderer(scene)
        t0 = time.perf_counter()
        poses = tour_poses(scene, args.spacing, args.headings, args.max_views)
        views, seen = render_views(scene, poses, intr, "robot1", [True] * len(poses), renderer)
        cams = place_fixed_cameras(scene, args.fixed_cameras, args.seed, intrinsics=intr) if args.fixed_cameras else []
        for c in cams:
            cv, cs = render_views(scene, [np.asarray(c.T_world_cam)], c.intrinsics, c.camera_id, [c.pose_known],
                                  renderer, stamp0_ns=10**12)
            views += cv
            for k, v in cs.items():
                seen[k] = max(seen.get(k, 0), v)
        visible = sorted(k for k, v in seen.items() if v >= args.min_visible_px)
        log(f"{family}/{args.seed}: {len(scene.objects)} objects ({len(visible)} visible >= {args.min_visible_px} px), "
            f"{len(scene.relations)} relations, {len(views)} frames ({len(cams)} fixed) rendered in "
            f"{time.perf_counter() - t0:.1f}s")
        fam: dict[str, Any] = {"n_objects": len(scene.objects), "n_visible": len(visible), "n_frames": len(views),
                               "n_relations": len(scene.relations), "geometries": {}}
        for geometry in args.geometries:
            core, stats = run_mapping(views, geometry, args.threads)
            sc = score_run(core, scene, visible)
            fam["geometries"][geometry] = {**sc, "timing": stats}
            n, e = sc["node"], sc["edge"]
            log(f"  {geometry:>6}: nodes P {n['precision']:.3f} R {n['recall']:.3f} F1 {n['f1']:.3f} "
                f"({n['n_pred']} pred / {n['n_true']} true); edges P {e['precision']:.3f} R {e['recall']:.3f}; "
                f"update mean {stats['update_s_mean']:.2f}s p95 {stats['update_s_p95']:.2f}s "
                f"({stats['keyframes']} keyframes, {stats['keyframe_errors']} errors)")
        g = fam["geometries"]
        if "oracle" in g and "mvs" in g:
            fam["parity_gap"] = g["oracle"]["node"]["f1"] - g["mvs"]["node"]["f1"]
        results["families"][family] = fam
    if not args.skip_query:
        results["query"] = query_latency(args.query_nodes, args.queries)
        q = results["query"]
        log(f"query: {q['n_answered']}/{q['n_queries']} answered, p50 {q['p50_ms']:.2f} ms, p99 {q['p99_ms']:.2f} ms "
            f"({q['n_nodes']} nodes)")
    results["bars"] = evaluate_bars(results)
    return results


def evaluate_bars(results: dict[str, Any]) -> dict[str, Any]:
    values: dict[str, float] = {}
    mvs_p95 = []
    for fam, r in results["families"].items():
        g = r["geometries"]
        if "oracle" in g:
            values[f"node_f1_oracle_{fam}"] = g["oracle"]["node"]["f1"]
            values[f"edge_precision_oracle_{fam}"] = g["oracle"]["edge"]["precision"]
        if "parity_gap" in r:
            values[f"parity_gap_{fam}"] = r["parity_gap"]
        if "mvs" in g:
            mvs_p95.append(g["mvs"]["timing"]["update_s_p95"])
    if mvs_p95:
        values["update_s_per_keyframe_mvs_p95"] = max(mvs_p95)
    if "query" in results:
        values["query_p99_ms"] = results["query"]["p99_ms"]
    out = {}
    for name, (op, bar) in BARS.items():
        if name in values:
            v = values[name]
            ok = v >= bar if op == ">=" else v <= bar
            out[name] = {"value": v, "bar": f"{op} {bar}", "pass": bool(ok)}
    return out


def markdown(results: dict[str, Any]) -> str:
    from bench.report import machine, markdown_table

    lines = ["# argus bench graph", "",
             f"2D perception: {results['perception']}. Config: `{json.dumps(results['config'])}`", ""]
    rows = []
    for fam, r in results["families"].items():
        for geometry, g in r["geometries"].items():
            n, e, t = g["node"], g["edge"], g["timing"]
            rows.append({
                "family": fam, "geometry": geometry, "frames": r["n_frames"], "node P": n["precision"],
                "node R": n["recall"], "node F1": n["f1"], "F1 (visible GT)": g["node_visible"]["f1"],
                "pred/true": f"{n['n_pred']}/{n['n_true']}", "edge P": e["precision"], "edge R": e["recall"],
                "update mean s": t["update_s_mean"], "update p95 s": t["update_s_p95"],
            })
    lines += ["## Quality and update time", "", markdown_table(rows)]
    if "query" in results:
        q = results["query"]
        lines += ["## Query latency (Zenoh loopback)", "",
                  f"{q['n_nodes']} nodes, {q['n_answered']}/{q['n_queries']} answered: p50 {q['p50_ms']:.2f} ms, "
                  f"p99 {q['p99_ms']:.2f} ms; per selector p99: {q['per_selector_p99_ms']}", ""]
    lines += ["## Bars", "", markdown_table([
        {"bar": k, "value": v["value"], "target": v["bar"], "pass": "yes" if v["pass"] else "**MISS**"}
        for k, v in results["bars"].items()
    ])]
    for fam, r in results["families"].items():
        for geometry, g in r["geometries"].items():
            lines += [f"- {fam}/{geometry}: missed objects {g['missed_labels']}; "
                      f"false positives {g['false_positive_labels']}; "
                      f"wrong edges (obj ids) {g['edge']['wrong_examples']}"]
    lines += ["", f"Machine: {machine()}", ""]
    return "\n".join(lines)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus bench graph",
        description="Scene-graph node/edge quality vs the simulator's ground truth, update time and query latency.",
        epilog="example:\n  argus bench graph --quick --out bench_out/graph",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--quick", action="store_true", help="small frames, sparse tour: a minute or two")
    p.add_argument("--families", nargs="+", default=["furnished_room", "apartment"], help="scene families")
    p.add_argument("--geometries", nargs="+", default=["oracle", "mvs"], help="reconstructor backends")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--width", type=int, default=640, help="frame width")
    p.add_argument("--height", type=int, default=480, help="frame height")
    p.add_argument("--spacing", type=float, default=0.9, help="tour lattice spacing, metres")
    p.add_argument("--headings", type=int, default=4, help="headings per tour stop")
    p.add_argument("--max-views", type=int, default=None, help="cap on tour frames")
    p.add_argument("--fixed-cameras", type=int, default=2, help="fixed cameras (0..3)")
    p.add_argument("--min-visible-px", type=int, default=200, help="'visible' ground truth: pixels in some frame")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--query-nodes", type=int, default=150, help="graph size of the query benchmark")
    p.add_argument("--queries", type=int, default=400, help="queries timed")
    p.add_argument("--skip-query", action="store_true", help="skip the query latency benchmark")
    p.add_argument("--out", type=Path, default=Path("bench_out/graph"), help="output directory")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.quick:
        args.width, args.height = min(args.width, 320), min(args.height, 240)
        args.spacing = max(args.spacing, 1.3)
        args.queries = min(args.queries, 200)
        args.min_visible_px = min(args.min_visible_px, 50)
    results = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    from bench.report import machine

    (args.out / "graph.json").write_text(json.dumps({"benchmark": "graph", "machine": machine(), **results},
                                                    indent=2, default=float) + "\n")
    (args.out / "graph.md").write_text(markdown(results))
    print(f"wrote {args.out / 'graph.json'} and {args.out / 'graph.md'}")
    misses = [k for k, v in results["bars"].items() if not v["pass"]]
    if misses:
        print(f"bars missed: {', '.join(misses)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
