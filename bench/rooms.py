"""``argus eval rooms``: the mapper's room layer scored against the simulator's rooms.

A robot tours the whole scene (every navigable spot ``tour_spacing_m`` apart, nearest first, walking the
simulator's paths between them with its head scanning left and right, turning once around at each spot: a full
exploration), an in-process
mapper maps it with true geometry (``oracle``) and RGB-only geometry (``mvs``), and its rooms
(mapper.rooms: built from the map alone, no simulator room names) are scored:

- room count: predicted against true;
- IoU of each true room with its match (one-to-one, by IoU), on the room grid (a true room's cells are those
  whose centre lies inside its walls); a true room with no match counts 0;
- object-to-room assignment: of the mapper's nodes whose centroid lies in a true room, the share whose
  in_room room is that true room's match;
- room-label accuracy: of the true rooms, the share whose match carries the true room's kind.

The simulator's rooms are used only here, for scoring. Example::

    argus eval rooms --out eval_out                      # apartments and furnished rooms, oracle and mvs
    argus eval rooms --scenes 3 --out eval_out
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bench.simdrive import along_path


class RoomsConfig(BaseModel):
    """The room experiment: families x seeds x geometries after a full tour."""

    model_config = ConfigDict(extra="forbid")
    families: list[str] = Field(default_factory=lambda: ["apartment", "furnished_room"], description="families")
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2], description="scene seeds per family (held out: "
                             "the room thresholds were set on seeds 100-102)")
    geometries: list[str] = Field(default_factory=lambda: ["oracle", "mvs"], description="reconstructors")
    perception: str = Field(default="sim", description="2D perception (sim = ORACLE semantic camera)")
    tour_spacing_m: float = Field(default=1.2, gt=0.0, description="spacing of the spots the tour visits")
    step_m: float = Field(default=0.3, gt=0.0, description="distance between consecutive frames")
    look_around: int = Field(default=4, ge=0, description="frames turning once around at each spot (0: none)")
    max_frames: int = Field(default=600, ge=2, description="frames per tour at most")
    width: int = Field(default=320, ge=32, description="image width, px")
    height: int = Field(default=240, ge=24, description="image height, px")
    prior_noise_m: float = Field(default=0.02, ge=0, description="odometry prior noise (std, metres)")
    prior_noise_deg: float = Field(default=1.0, ge=0, description="odometry prior noise (std, degrees yaw)")
    update_every: int = Field(default=20, ge=1, description="update the room layer every this many frames (ids "
                              "carried over as in the running mapper)")


def tour_walk(scene: Any, cfg: RoomsConfig, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """True camera poses of a tour of every navigable spot (nearest unvisited next): frames every ``step_m`` on the
    way, the head scanning left and right, and ``look_around`` frames turning once around at each spot; and the
    odometry priors (true poses with Gaussian noise)."""
    from protocol.poses import camera_pose_from_base
    from sim.nav import NavMap

    rng = np.random.default_rng(seed)
    nav = NavMap(scene)
    spots = np.array([(v.x, v.y) for v in nav.viewpoints(spacing_m=cfg.tour_spacing_m, n_headings=1)])
    if len(spots) == 0:
        raise RuntimeError(f"scene {scene.family}/{scene.seed} has no navigable viewpoint")
    at = int(rng.integers(len(spots)))
    todo = set(range(len(spots))) - {at}
    samples: list[tuple[float, float, float]] = []
    offsets = np.radians([0.0, 50.0, 0.0, -50.0])
    look = np.radians(np.arange(0.0, 360.0, 360.0 / max(cfg.look_around, 1)))
    heading = float(rng.uniform(-math.pi, math.pi))

    def look_around(xy: np.ndarray, heading: float) -> None:
        if cfg.look_around > 0:
            samples.extend((float(xy[0]), float(xy[1]), heading + a) for a in look)

    look_around(spots[at], heading)
    while todo and len(samples) < cfg.max_frames:
        nxt = min(todo, key=lambda k: float(np.linalg.norm(spots[k] - spots[at])))
        todo.discard(nxt)
        path = nav.path(tuple(spots[at]), tuple(spots[nxt]))
        at = nxt
        if path is None or len(path) < 2:
            continue
        for xy, heading in along_path(path, cfg.step_m):
            samples.append((float(xy[0]), float(xy[1]), heading + offsets[len(samples) % 4]))
        look_around(path[-1], heading)  # at each spot the robot turns around once: nothing left unseen
    samples = samples[: cfg.max_frames]
    poses, priors = [], []
    for x, y, yaw in samples:
        poses.append(camera_pose_from_base(x, y, yaw, 1.0, -15.0))
        nx, ny = rng.normal(0.0, cfg.prior_noise_m, 2)
        nyaw = math.radians(rng.normal(0.0, cfg.prior_noise_deg))
        priors.append(camera_pose_from_base(x + nx, y + ny, yaw + nyaw, 1.0, -15.0))
    return poses, priors


def true_room_masks(layer: Any, scene: Any) -> list[np.ndarray]:
    """Each true room's cells on the layer's grid (cell centre inside the room's walls)."""
    g = layer.grid
    ij = np.argwhere(np.ones(g.shape, bool))
    xy = g.xy_of(ij)
    out = []
    for r in scene.rooms:
        inside = ((xy[:, 0] >= r.xy_min[0]) & (xy[:, 0] <= r.xy_max[0])
                  & (xy[:, 1] >= r.xy_min[1]) & (xy[:, 1] <= r.xy_max[1]))
        out.append(inside.reshape(g.shape))
    return out


def score_rooms(layer: Any, in_room: dict[str, str], nodes: Sequence[Any], scene: Any) -> dict[str, Any]:
    """Room count, IoU, object-to-room and label accuracy of ``layer`` against ``scene``'s rooms."""
    from scipy.optimize import linear_sum_assignment

    n_true = len(scene.rooms)
    n_pred = len(layer.rooms) if layer.grid is not None else 0
    if n_pred == 0:
        return {"rooms_true": n_true, "rooms_pred": 0, "iou": 0.0, "assign_acc": 0.0, "label_acc": 0.0,
                "per_room": []}
    trues = true_room_masks(layer, scene)
    iou = np.zeros((n_true, n_pred))
    for t, tm in enumerate(trues):
        for p in range(n_pred):
            pm = layer.labels == p + 1
            union = int((tm | pm).sum())
            iou[t, p] = float((tm & pm).sum()) / union if union else 0.0
    rows, cols = linear_sum_assignment(-iou)
    match: dict[int, int] = {int(t): int(p) for t, p in zip(rows, cols, strict=True) if iou[t, p] > 0}
    per_room = []
    for t, r in enumerate(scene.rooms):
        m = match.get(t)
        pred = layer.rooms[m] if m is not None else None
        per_room.append({"room": r.name, "kind": r.kind, "iou": float(iou[t, m]) if m is not None else 0.0,
                         "match": pred.room_id if pred else None, "label": pred.label if pred else None,
                         "label_confidence": pred.label_confidence if pred else 0.0,
                         "observed_fraction": pred.observed_fraction if pred else 0.0})
    name_to_t = {r.name: t for t, r in enumerate(scene.rooms)}
    total = right = 0
    for n in nodes:
        true_room = scene.room_at(float(n.centroid[0]), float(n.centroid[1]))
        if true_room is None:
            continue
        total += 1
        m = match.get(name_to_t[true_room.name])
        right += int(m is not None and in_room.get(n.node_id) == layer.rooms[m].room_id)
    return {
        "rooms_true": n_true, "rooms_pred": n_pred,
        "iou": float(np.mean([pr["iou"] for pr in per_room])),
        "assign_acc": right / total if total else float("nan"), "assigned_objects": total,
        "label_acc": float(np.mean([pr["label"] == pr["kind"] for pr in per_room])),
        "doorways_true": len(scene.doors), "doorways_pred": len(layer.doorways),
        "per_room": per_room,
    }


def map_and_score(family: str, seed: int, geometry: str, cfg: RoomsConfig, torch_threads: int
                  ) -> dict[str, Any]:
    """Tour one scene, map it with ``geometry``, score its rooms."""
    from bench.explore import mapper_config
    from bench.simdrive import mapper_views
    from mapper.core import MapperCore
    from protocol.messages import Intrinsics
    from sim.scene import generate_scene

    scene = generate_scene(family, seed)
    poses, priors = tour_walk(scene, cfg, seed)
    intr = Intrinsics.from_fov(cfg.width, cfg.height, 90.0)
    views = mapper_views(scene, poses, [np.asarray(p) for p in priors], intr, "robot0", trusted=False,
                          prior_rel_rot_deg=math.inf, prior_rel_trans_m=math.inf)
    core = MapperCore(mapper_config(geometry, cfg.perception, torch_threads, None))
    t0 = time.perf_counter()
    room_s: list[float] = []
    layer = None
    for k, v in enumerate(views):
        core.ingest(v, force_keyframe=True)
        if (k + 1) % cfg.update_every == 0 or k == len(views) - 1:
            t1 = time.perf_counter()
            layer = core.update_rooms()
            room_s.append(time.perf_counter() - t1)
    assert layer is not None and core.rooms is not None
    nodes = core.nodes()
    row = score_rooms(layer, core.rooms.in_room, nodes, scene)
    row.update(family=family, seed=seed, geometry=geometry, frames=len(views), nodes=len(nodes),
               seconds=round(time.perf_counter() - t0, 1), room_update_ms=round(1000 * float(np.median(room_s)), 1))
    return row


def run_rooms(cfg: RoomsConfig, torch_threads: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Every family x seed x geometry; per-scene rows and per (family, geometry) means."""
    rows = []
    for family in cfg.families:
        for seed in cfg.seeds:
            for geometry in cfg.geometries:
                row = map_and_score(family, seed, geometry, cfg, torch_threads)
                rows.append(row)
                log(f"rooms {family}/{seed} {geometry}: rooms {row['rooms_pred']}/{row['rooms_true']} IoU "
                    f"{row['iou']:.3f} assign {row['assign_acc']:.3f} label {row['label_acc']:.3f} "
                    f"({row['frames']} frames, {row['seconds']}s)")
    summary = []
    for family in cfg.families:
        for geometry in cfg.geometries:
            sel = [r for r in rows if r["family"] == family and r["geometry"] == geometry]
            if not sel:
                continue
            entry: dict[str, Any] = {"family": family, "geometry": geometry, "scenes": len(sel)}
            for k in ("iou", "assign_acc", "label_acc"):
                entry[k] = float(np.nanmean([r[k] for r in sel]))
            entry["count_exact"] = float(np.mean([r["rooms_pred"] == r["rooms_true"] for r in sel]))
            entry["rooms_pred"] = float(np.mean([r["rooms_pred"] for r in sel]))
            entry["rooms_true"] = float(np.mean([r["rooms_true"] for r in sel]))
            entry["room_update_ms"] = float(np.median([r["room_update_ms"] for r in sel]))
            summary.append(entry)
    return {"config": cfg.model_dump(mode="json"), "per_scene": rows, "summary": summary}


def rooms_markdown(res: dict[str, Any]) -> str:
    from bench.report import markdown_table

    rows = [{"Family": s["family"], "Geometry": s["geometry"], "Scenes": s["scenes"],
             "Rooms pred / true": f"{s['rooms_pred']:.1f} / {s['rooms_true']:.1f}",
             "Count exact": f"{s['count_exact']:.2f}", "Room IoU": f"{s['iou']:.3f}",
             "Object->room": f"{s['assign_acc']:.3f}", "Label acc": f"{s['label_acc']:.3f}",
             "Room update ms": f"{s['room_update_ms']:.0f}"} for s in res["summary"]]
    return ("## Rooms (argus eval rooms)\n\nRooms built from the map alone after a full tour, scored against the "
            "simulator's rooms; ORACLE 2D perception (sim semantic camera).\n\n" + markdown_table(rows) + "\n")


def rooms_plot(res: dict[str, Any], path: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = res["summary"]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    names = [f"{e['family']}\n{e['geometry']}" for e in s]
    x = np.arange(len(s))
    for i, (k, lab) in enumerate((("iou", "room IoU"), ("assign_acc", "object->room"), ("label_acc", "label acc"))):
        ax.bar(x + (i - 1) * 0.25, [e[k] for e in s], 0.25, label=lab)
    ax.set_xticks(x, names, fontsize=8)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# --- incremental cost ---------------------------------------------------------------------------------
def synthetic_map(rng: np.random.Generator, rooms_x: int = 4, rooms_y: int = 3, room_m: float = 4.0,
                  n_points: int = 300_000, n_objects: int = 2000) -> tuple[np.ndarray, np.ndarray, list[Any]]:
    """A grid of ``rooms_x`` x ``rooms_y`` square rooms with a doorway in every inner wall: floor and wall points
    (about ``n_points``, the mapper's default voxel budget), camera positions along the rooms' middles and
    ``n_objects`` object nodes with labels from the indoor prior."""
    from protocol.messages import GraphNode, OrientedBox
    from protocol.prior import load_prior

    W, D = rooms_x * room_m, rooms_y * room_m
    n_floor = n_points // 2
    floor = np.column_stack([rng.uniform(0, W, n_floor), rng.uniform(0, D, n_floor), rng.normal(0, 0.01, n_floor)])
    walls = []
    for k in range(rooms_x + 1):  # walls along y at x = k * room_m, a doorway in each room's span on inner walls
        walls.append(("x", k * room_m, k not in (0, rooms_x)))
    for k in range(rooms_y + 1):
        walls.append(("y", k * room_m, k not in (0, rooms_y)))
    per = (n_points - n_floor) // len(walls)
    wall_pts = []
    for axis, c, inner in walls:
        t = rng.uniform(0, D if axis == "x" else W, per)
        if inner:  # a 0.9 m doorway in the middle of every room's stretch of wall
            t = t[np.abs((t % room_m) - room_m / 2) > 0.45]
        z = rng.uniform(0, 2.5, len(t))
        xy = np.column_stack([np.full(len(t), c), t]) if axis == "x" else np.column_stack([t, np.full(len(t), c)])
        wall_pts.append(np.column_stack([xy, z]))
    points = np.concatenate([floor, *wall_pts]).astype(np.float32)
    cams = np.array([((i + 0.5) * room_m, (j + 0.5) * room_m, 1.0) for i in range(rooms_x) for j in range(rooms_y)])
    labels = sorted({e.label for es in load_prior().rooms.values() for e in es})
    nodes = []
    for k in range(n_objects):
        x, y, s = float(rng.uniform(0.3, W - 0.3)), float(rng.uniform(0.3, D - 0.3)), float(rng.uniform(0.1, 0.8))
        nodes.append(GraphNode(node_id=f"n{k}", label=labels[int(rng.integers(len(labels)))], label_confidence=0.9,
                               centroid=(x, y, s / 2), box=OrientedBox(center=(x, y, s / 2), extent=(s, s, s),
                                                                       yaw_rad=float(rng.uniform(0, math.pi))),
                               point_count=10, observation_count=1, first_seen_ns=0, last_seen_ns=0))
    return points, cams, nodes


def bench_update(n_objects: int = 2000, n_points: int = 300_000, updates: int = 30, seed: int = 0
                 ) -> dict[str, Any]:
    """Seconds per room-layer update of a full map (``n_points`` voxels, ``n_objects`` nodes): every update adds
    a keyframe's worth of points and moves a few nodes, as a graph update does."""
    import os

    from mapper.pointmap import VoxelMap
    from mapper.rooms import RoomMapper

    rng = np.random.default_rng(seed)
    points, cams, nodes = synthetic_map(rng, n_points=n_points, n_objects=n_objects)
    rm = RoomMapper()
    for c in cams:
        rm.note_camera(c)
    rm.update(points, nodes)  # the first build (imports, caches)
    vm = VoxelMap(0.08, max(n_points, 1))
    vm.add(points)
    times, cpu, copy_s = [], [], []
    for _ in range(updates):
        new = points[rng.integers(len(points), size=2000)] + rng.normal(0, 0.02, (2000, 3)).astype(np.float32)
        points = np.concatenate([points[2000:], new])
        for k in rng.integers(len(nodes), size=10):
            n = nodes[int(k)]
            c = (n.centroid[0] + 0.01, n.centroid[1], n.centroid[2])
            nodes[int(k)] = n.model_copy(update={"centroid": c})
        t = time.perf_counter()
        vm.points()
        copy_s.append(time.perf_counter() - t)
        t, c = time.perf_counter(), time.thread_time()
        layer = rm.update(points, nodes)
        times.append(time.perf_counter() - t)
        cpu.append(time.thread_time() - c)
    ms = 1000 * np.asarray(times)
    return {"objects": n_objects, "points": int(len(points)), "updates": updates, "rooms": len(layer.rooms),
            "doorways": len(layer.doorways), "assigned": len(rm.in_room),
            "update_ms_median": float(np.median(ms)), "update_ms_p95": float(np.percentile(ms, 95)),
            "update_ms_max": float(ms.max()), "update_cpu_ms_median": float(1000 * np.median(cpu)),
            "map_copy_ms_median": float(1000 * np.median(copy_s)),
            "load_1min": os.getloadavg()[0], "cores": os.cpu_count()}


def main(argv: list[str] | None = None) -> int:
    """``argus bench rooms``: the room layer's incremental cost (quality: ``argus eval rooms``)."""
    import argparse
    import json
    from pathlib import Path

    from bench.report import machine

    p = argparse.ArgumentParser(prog="argus bench rooms",
                                description="Room layer update time on a full synthetic map (12 rooms, doorways) "
                                "with N objects; room quality against the simulator is argus eval rooms.")
    p.add_argument("--objects", type=int, default=2000, help="object nodes")
    p.add_argument("--points", type=int, default=300_000, help="map voxels (the mapper's default budget)")
    p.add_argument("--updates", type=int, default=30, help="timed updates")
    p.add_argument("--quick", action="store_true", help="5 updates")
    p.add_argument("--out", type=Path, default=Path("bench_out/rooms"), help="output folder")
    a = p.parse_args(argv)
    res = bench_update(a.objects, a.points, 5 if a.quick else a.updates)
    res["machine"] = machine()
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "rooms.json").write_text(json.dumps(res, indent=1) + "\n")
    md = (f"## Room layer update (argus bench rooms)\n\n{res['objects']} objects, {res['points']} map points, "
          f"{res['rooms']} rooms, {res['doorways']} doorways: update median {res['update_ms_median']:.1f} ms, "
          f"p95 {res['update_ms_p95']:.1f} ms, max {res['update_ms_max']:.1f} ms (bar: <= 50 ms), CPU time median "
          f"{res['update_cpu_ms_median']:.1f} ms (one thread); the map copy "
          f"it reads {res['map_copy_ms_median']:.1f} ms; load {res['load_1min']:.1f} on {res['cores']} cores.\n")
    (a.out / "rooms.md").write_text(md)
    print(md)
    return 0
