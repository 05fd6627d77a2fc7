"""``argus eval``: the paper's three experiments on the embedded simulated scenes.

- ``static`` (paper Table I): node precision / recall / F1 with ``oracle`` geometry (true depth and
  poses: the paper's CG) against ``mvs`` (RGB-only: the paper's CG-RGB), on the same frames with the
  same 2D perception, mean and std over scenes.
- ``active`` (paper Fig. 2): ``see`` vs ``asp`` next-best-view exploration, each with and without one
  overhead external camera, for a number of steps from several start poses: node count, recall and
  metres driven per step with std bands, steps to 50 % / 80 % recall (closed loops through
  ``bench.explore.run_episode``). RGB-only geometry (``mvs``) with the robot's goal capture by default,
  true geometry as the reference curves.
- ``external`` (paper Table II): 1, 2 and 3 fixed cameras and no robot, on both scene families.
- ``rooms`` (run only when named): the mapper's room layer against the simulator's rooms after a full tour
  (room count, IoU, object-to-room and room-label accuracy; ``bench.rooms``).
- ``changes`` (run only when named): an apartment that changes (objects moved, removed, added) while people walk
  through, watched by fixed cameras and a touring robot: time until the graph is right about each edit, stale nodes,
  false retirements, F1 over time (``bench.changes``).

Each writes ``<name>.json``, ``<name>.md`` and PNG plots under ``--out``; ``summary.md`` collects the
tables. 2D perception defaults to the simulator's semantic camera (``sim``: an ORACLE for masks and
labels, like Habitat's semantic sensor) because no open-vocabulary model ships offline; the geometry is
what the experiments compare. Every table says which perception and geometry were used.

Example::

    argus eval --quick --out eval_out            # small subset, CI smoke test (< 5 min on 2 cores)
    argus eval static --scenes 3 --out eval_out
    argus eval --out eval_full                    # everything (docs/benchmarks.md has its wall time)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bench.changes import ChangesConfig, changes_markdown, changes_plot, quick_changes, run_changes
from bench.explore import mapper_config, steps_to
from bench.report import machine, markdown_table
from bench.rooms import RoomsConfig, rooms_markdown, rooms_plot, run_rooms
from bench.simdrive import along_path
from bench.simdrive import mapper_views as _mapper_views

EXPERIMENTS = ("static", "external", "active")
OPTIONAL = ("rooms", "changes")  # run only when named


class FramesConfig(BaseModel):
    """How simulated robot frames are produced for the static experiment."""

    model_config = ConfigDict(extra="forbid")
    n_frames: int = Field(default=36, ge=2, description="frames per scene along a scanning walk")
    step_m: float = Field(default=0.3, gt=0, description="distance between consecutive frames")
    width: int = Field(default=640, ge=32, description="image width, px")
    height: int = Field(default=480, ge=24, description="image height, px")
    hfov_deg: float = Field(default=90.0, gt=0, lt=180, description="horizontal field of view")
    camera_height_m: float = Field(default=1.0, gt=0, description="robot camera height")
    camera_pitch_deg: float = Field(default=-15.0, description="robot camera pitch")
    prior_noise_m: float = Field(default=0.02, ge=0, description="odometry prior noise (std, metres)")
    prior_noise_deg: float = Field(default=1.0, ge=0, description="odometry prior noise (std, degrees yaw)")


class StaticConfig(BaseModel):
    """Table I: oracle vs mvs geometry on the same frames and 2D perception."""

    model_config = ConfigDict(extra="forbid")
    family: str = Field(default="furnished_room", description="scene family (Replica rooms are single rooms)")
    seeds: list[int] = Field(default_factory=lambda: [0, 1, 2, 3, 4], description="scene seeds")
    geometries: list[str] = Field(
        default_factory=lambda: ["oracle", "mvs"],
        description="reconstructors compared; 'probe:<pixels>' (confident, unconfident, objects, uncovered) is mvs "
        "with ORACLE true depth at those pixels: where RGB-only loses against true geometry",
    )
    perception: str = Field(default="sim", description="2D perception (sim = ORACLE semantic camera, classical)")
    frames: FramesConfig = Field(default_factory=FramesConfig, description="the robot frames")
    mapper: dict[str, Any] = Field(
        default_factory=dict,
        description="mapper configuration written over the defaults for every geometry (nested tables, as in "
        "the mapper's TOML), e.g. {single_view = {mapped_support = true}}",
    )


class ExternalConfig(BaseModel):
    """Table II: fixed cameras only, no robot."""

    model_config = ConfigDict(extra="forbid")
    families: list[str] = Field(default_factory=lambda: ["apartment", "furnished_room"], description="families")
    seeds: list[int] = Field(default_factory=lambda: list(range(10)), description="scene seeds per family")
    cameras: list[int] = Field(default_factory=lambda: [1, 2, 3], description="camera counts")
    geometries: list[str] = Field(
        default_factory=lambda: ["oracle", "mvs"],
        description="reconstructors (mvs needs overlapping views: a lone fixed camera has no parallax)",
    )
    perception: str = Field(default="sim", description="2D perception")
    width: int = Field(default=640, ge=32, description="image width, px")
    height: int = Field(default=480, ge=24, description="image height, px")


class ActiveConfig(BaseModel):
    """Fig. 2: see vs asp, with and without one external camera."""

    model_config = ConfigDict(extra="forbid")
    family: str = Field(default="apartment", description="scene family")
    seed: int = Field(default=0, description="scene seed (the paper shows one representative apartment)")
    strategies: list[str] = Field(default_factory=lambda: ["see", "asp"], description="planner strategies")
    external: list[bool] = Field(default_factory=lambda: [False, True], description="without / with one ext. cam")
    steps: int = Field(default=30, ge=1, description="exploration steps")
    starts: int = Field(default=3, ge=1, description="start poses (std bands over them)")
    geometry: str = Field(
        default="mvs",
        description="reconstructor of the main curves: mvs (RGB-only, the product's default), or oracle",
    )
    reference_geometry: str | None = Field(
        default="oracle",
        description="also run every curve with this reconstructor as the reference (true geometry); "
        "none: skip it",
    )
    goal_capture_m: float = Field(
        default=0.3, ge=0.0,
        description="the robot's goal capture (as the robot agent's frames.goal_capture_m): views this far "
        "left and right of each goal, the sidesteps counted in the distance; applied in every run alike",
    )
    perception: str = Field(default="sim", description="2D perception")
    options: dict[str, Any] = Field(default_factory=dict, description="extra fields of bench.explore.Episode")

    @property
    def geometries(self) -> list[str]:
        """The main reconstructor, then the reference (if any and different)."""
        ref = self.reference_geometry
        return [self.geometry] + ([ref] if ref and ref != self.geometry else [])


class EvalConfig(BaseModel):
    """All three experiments."""

    model_config = ConfigDict(extra="forbid")
    out: Path = Field(default=Path("eval_out"), description="output folder")
    experiments: list[str] = Field(default_factory=lambda: list(EXPERIMENTS), description="which to run")
    static: StaticConfig = Field(default_factory=StaticConfig, description="Table I")
    active: ActiveConfig = Field(default_factory=ActiveConfig, description="Fig. 2")
    external: ExternalConfig = Field(default_factory=ExternalConfig, description="Table II")
    rooms: RoomsConfig = Field(default_factory=RoomsConfig, description="the room layer against the true rooms")
    changes: ChangesConfig = Field(default_factory=ChangesConfig, description="a scene that changes while watched")
    torch_threads: int = Field(default=2, ge=1, description="torch CPU threads")


def quick_config(out: Path) -> EvalConfig:
    """The CI subset: one small scene per setting, short walks, few steps (< 5 min on 2 cores)."""
    frames = FramesConfig(n_frames=10, width=320, height=240)
    return EvalConfig(
        out=out,
        static=StaticConfig(seeds=[0], frames=frames),
        active=ActiveConfig(family="furnished_room", steps=4, starts=1, reference_geometry=None),
        external=ExternalConfig(families=["furnished_room"], seeds=[0], cameras=[1, 3], width=320, height=240),
        changes=quick_changes(),
        experiments=list(EXPERIMENTS),
    )


# --- frames ---------------------------------------------------------------------------------------
def scan_walk(scene: Any, cfg: FramesConfig, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """True camera poses of a robot walking a covering route, its head scanning left and right, and the
    odometry priors (true poses with Gaussian noise) the RGB-only path starts from."""
    from protocol.poses import camera_pose_from_base
    from sim.nav import NavMap

    rng = np.random.default_rng(seed)
    nav = NavMap(scene)
    spots = np.array([(v.x, v.y) for v in nav.viewpoints(spacing_m=0.6, n_headings=1)])
    if len(spots) == 0:
        raise RuntimeError(f"scene {scene.family}/{scene.seed} has no navigable viewpoint")
    # Waypoints by farthest-point sampling from a random start: the walk covers the scene.
    route = [spots[int(rng.integers(len(spots)))]]
    n_way = max(2, cfg.n_frames * cfg.step_m // 1.5 + 1)
    while len(route) < n_way:
        d = np.min(np.linalg.norm(spots[:, None, :] - np.array(route)[None], axis=2), axis=1)
        route.append(spots[int(np.argmax(d))])
    samples: list[tuple[float, float, float]] = []
    offsets = np.radians([0.0, 35.0, 0.0, -35.0])
    for a, b in zip(route[:-1], route[1:], strict=True):
        path = nav.path(tuple(a), tuple(b))
        if path is None or len(path) < 2:
            continue
        for xy, heading in along_path(path, cfg.step_m):
            samples.append((float(xy[0]), float(xy[1]), heading + offsets[len(samples) % 4]))
            if len(samples) >= cfg.n_frames:
                break
        if len(samples) >= cfg.n_frames:
            break
    poses, priors = [], []
    for x, y, yaw in samples:
        poses.append(camera_pose_from_base(x, y, yaw, cfg.camera_height_m, cfg.camera_pitch_deg))
        nx, ny = rng.normal(0.0, cfg.prior_noise_m, 2)
        nyaw = math.radians(rng.normal(0.0, cfg.prior_noise_deg))
        priors.append(camera_pose_from_base(x + nx, y + ny, yaw + nyaw, cfg.camera_height_m, cfg.camera_pitch_deg))
    return poses, priors


def fixed_camera_views(scene: Any, n: int, seed: int, width: int, height: int) -> list[Any]:
    """One frame from each of ``n`` fixed cameras placed high in room corners (calibrated when known)."""
    from protocol.messages import Intrinsics
    from sim.cameras import place_fixed_cameras

    intr = Intrinsics.from_fov(width, height, 90.0)
    views = []
    for cam in place_fixed_cameras(scene, n, seed, intrinsics=intr):
        T = np.asarray(cam.T_world_cam, float)
        views += _mapper_views(scene, [T], [T if cam.pose_known else None], cam.intrinsics, cam.camera_id,
                               cam.pose_known)
    return views


def map_views(views: Sequence[Any], geometry: str, perception: str, torch_threads: int = 2,
              force_keyframes: bool = True, overrides: dict[str, Any] | None = None) -> tuple[Any, dict[str, float]]:
    """Feed views to an in-process MapperCore (its configuration with ``overrides`` written over it); returns
    its final snapshot and counters."""
    from mapper.core import MapperCore

    core = MapperCore(mapper_config(geometry, perception, torch_threads, overrides))
    for v in views:
        core.ingest(v, force_keyframe=force_keyframes)
    return core.snapshot(), dict(core.counters)


def score(nodes: Sequence[Any], scene: Any) -> dict[str, float]:
    from sim.scoring import score_nodes

    s = score_nodes(list(nodes), scene)
    return {"precision": float(s.precision), "recall": float(s.recall), "f1": float(s.f1),
            "n_pred": int(s.n_pred), "n_true": int(s.n_true)}


def _mean_std(rows: Sequence[dict[str, Any]], key: str) -> tuple[float, float]:
    vals = np.array([r[key] for r in rows], dtype=float)
    return (float(vals.mean()), float(vals.std())) if len(vals) else (float("nan"), float("nan"))


def _pm(m: float, s: float) -> str:
    return f"{m:.3f} ± {s:.3f}"


def _label(geometry: str, perception: str) -> str:
    geo = {"oracle": "ORACLE geometry (CG)", "mvs": "RGB-only mvs (CG-RGB)"}.get(geometry, geometry)
    per = "ORACLE 2D perception (sim semantic camera)" if perception == "sim" else f"{perception} 2D perception"
    return f"{geo}; {per}"


# --- static -----------------------------------------------------------------------------------------
def run_static(cfg: StaticConfig, torch_threads: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Table I on ``cfg.seeds`` scenes of ``cfg.family``."""
    from protocol.messages import Intrinsics
    from sim.scene import generate_scene

    f = cfg.frames
    intr = Intrinsics.from_fov(f.width, f.height, f.hfov_deg)
    per_scene: list[dict[str, Any]] = []
    for seed in cfg.seeds:
        scene = generate_scene(cfg.family, seed)
        poses, priors = scan_walk(scene, f, seed)
        for geometry in cfg.geometries:
            t0 = time.perf_counter()
            use_priors = [np.asarray(p) for p in priors]
            # These priors' errors are drawn independently per frame (not odometry drift): they carry no
            # relative information beyond the absolute prior, and the frames say so.
            views = _mapper_views(scene, poses, use_priors, intr, "robot0", trusted=False,
                                  prior_rel_rot_deg=math.inf, prior_rel_trans_m=math.inf)
            snap, counters = map_views(views, geometry, cfg.perception, torch_threads, overrides=cfg.mapper)
            row = {"seed": seed, "geometry": geometry, **score(snap.nodes, scene), "edges": len(snap.edges),
                   "frames": len(views), "seconds": round(time.perf_counter() - t0, 1),
                   "keyframe_errors": counters.get("keyframe_errors", 0.0)}
            per_scene.append(row)
            log(f"static {cfg.family}/{seed} {geometry}: P {row['precision']:.3f} R {row['recall']:.3f} "
                f"F1 {row['f1']:.3f} nodes {row['n_pred']}/{row['n_true']} ({row['seconds']}s)")
    summary = []
    for geometry in cfg.geometries:
        rows = [r for r in per_scene if r["geometry"] == geometry]
        name = {"oracle": "CG (oracle geometry)", "mvs": "CG-RGB (mvs, ours)"}.get(geometry, geometry)
        if geometry.startswith("probe:"):
            name = f"ORACLE probe: mvs + true depth at {geometry.split(':', 1)[1]} pixels"
        entry: dict[str, str | float] = {"experiment": name, "geometry": geometry}
        for k in ("precision", "recall", "f1", "n_pred"):
            m, s = _mean_std(rows, k)
            entry[k], entry[k + "_std"] = m, s
        summary.append(entry)
    return {"config": cfg.model_dump(mode="json"), "per_scene": per_scene, "summary": summary,
            "perception": _label("-", cfg.perception).split("; ")[1]}


def static_markdown(res: dict[str, Any]) -> str:
    rows = [{"Experiment": s["experiment"], "Precision": _pm(s["precision"], s["precision_std"]),
             "Recall": _pm(s["recall"], s["recall_std"]), "F1": _pm(s["f1"], s["f1_std"]),
             "Nodes": f"{s['n_pred']:.1f}"} for s in res["summary"]]
    cfg = res["config"]
    return (f"## Static: oracle vs RGB-only geometry (paper Table I)\n\n"
            f"{len(cfg['seeds'])} `{cfg['family']}` scenes, {cfg['frames']['n_frames']} frames each "
            f"({cfg['frames']['width']}x{cfg['frames']['height']}); 2D perception: {res['perception']}. "
            f"Mean ± std over scenes.\n\n" + markdown_table(rows))


def static_plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    metrics = ("precision", "recall", "f1")
    width = 0.8 / max(len(res["summary"]), 1)
    for i, s in enumerate(res["summary"]):
        x = np.arange(len(metrics)) + i * width
        ax.bar(x, [s[m] for m in metrics], width, yerr=[s[m + "_std"] for m in metrics], capsize=3,
               label=s["experiment"])
    ax.set_xticks(np.arange(len(metrics)) + width * (len(res["summary"]) - 1) / 2, ["Precision", "Recall", "F1"])
    ax.set_ylim(0, 1)
    ax.set_title("Static: node accuracy, oracle vs RGB-only geometry")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --- external ---------------------------------------------------------------------------------------
def run_external(cfg: ExternalConfig, torch_threads: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Table II: for each family, seed and camera count, map the fixed cameras' frames only."""
    from sim.scene import generate_scene

    per_scene: list[dict[str, Any]] = []
    for family in cfg.families:
        for seed in cfg.seeds:
            scene = generate_scene(family, seed)
            for n in cfg.cameras:
                views = fixed_camera_views(scene, n, seed, cfg.width, cfg.height)
                for geometry in cfg.geometries:
                    t0 = time.perf_counter()
                    snap, _ = map_views(views, geometry, cfg.perception, torch_threads)
                    row = {"family": family, "seed": seed, "cameras": n, "geometry": geometry,
                           **score(snap.nodes, scene), "seconds": round(time.perf_counter() - t0, 1)}
                    per_scene.append(row)
                    log(f"external {family}/{seed} {n} cam {geometry}: P {row['precision']:.3f} "
                        f"R {row['recall']:.3f} F1 {row['f1']:.3f} nodes {row['n_pred']}/{row['n_true']} "
                        f"({row['seconds']}s)")
    summary = []
    for geometry in cfg.geometries:
        for family in cfg.families:
            for n in cfg.cameras:
                rows = [r for r in per_scene
                        if r["family"] == family and r["cameras"] == n and r["geometry"] == geometry]
                entry: dict[str, Any] = {"geometry": geometry, "family": family, "cameras": n, "scenes": len(rows)}
                for k in ("precision", "recall", "f1", "n_pred", "n_true"):
                    m, s = _mean_std(rows, k)
                    entry[k], entry[k + "_std"] = m, s
                summary.append(entry)
    return {"config": cfg.model_dump(mode="json"), "per_scene": per_scene, "summary": summary,
            "label": _label("-", cfg.perception).split("; ")[1]}


# The paper's Table II (ReplicaCAD, MapAnything geometry, its own perception): (precision, recall, F1) means.
PAPER_TABLE2: dict[tuple[str, int], tuple[float, float, float]] = {
    ("apartment", 1): (0.770, 0.198, 0.315), ("apartment", 2): (0.741, 0.232, 0.353),
    ("apartment", 3): (0.698, 0.301, 0.421), ("furnished_room", 1): (0.566, 0.398, 0.465),
    ("furnished_room", 2): (0.540, 0.487, 0.510), ("furnished_room", 3): (0.486, 0.555, 0.516),
}


def external_markdown(res: dict[str, Any]) -> str:
    short = {"apartment": "Apt.", "furnished_room": "Fur."}
    oracle_f1 = {(s["family"], s["cameras"]): s["f1"] for s in res["summary"] if s["geometry"] == "oracle"}
    rows = []
    for s in res["summary"]:
        ref = oracle_f1.get((s["family"], s["cameras"]))
        rows.append({"Geometry": s["geometry"], "Scene": short.get(s["family"], s["family"]), "#Cam.": s["cameras"],
                     "Precision": _pm(s["precision"], s["precision_std"]),
                     "Recall": _pm(s["recall"], s["recall_std"]), "F1": _pm(s["f1"], s["f1_std"]),
                     "F1 / oracle": f"{s['f1'] / ref:.2f}" if ref and s["geometry"] != "oracle" else "",
                     "Nodes": f"{s['n_pred']:.1f} / {s['n_true']:.0f}"})
    for (fam, n), (p, r, f) in PAPER_TABLE2.items():
        if fam in {s["family"] for s in res["summary"]} and n in {s["cameras"] for s in res["summary"]}:
            rows.append({"Geometry": "paper (MapAnything)", "Scene": short.get(fam, fam), "#Cam.": n,
                         "Precision": f"{p:.3f}", "Recall": f"{r:.3f}", "F1": f"{f:.3f}", "F1 / oracle": "",
                         "Nodes": ""})
    cfg = res["config"]
    return (f"## External cameras only (paper Table II)\n\n{len(cfg['seeds'])} scenes per family, "
            f"{cfg['width']}x{cfg['height']}; 2D perception: {res['label']}. Mean ± std over scenes. "
            f"`oracle` = true depth; `mvs` = RGB-only: multi-view stereo where views overlap enough, and for a "
            f"calibrated camera with no stereo partner single-view floor geometry (objects placed where they "
            f"touch the floor or a placed object), merged across cameras where their rays cross. The paper's "
            f"rows are its ReplicaCAD figures (MapAnything depth, its own 2D perception), for reference only: "
            f"other scenes and perception.\n\n" + markdown_table(rows))


def external_plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    families = list(dict.fromkeys(s["family"] for s in res["summary"]))
    geometries = list(dict.fromkeys(s["geometry"] for s in res["summary"]))
    fig, axes = plt.subplots(1, len(families), figsize=(5 * len(families), 3.5), squeeze=False)
    for ax, fam in zip(axes[0], families, strict=True):
        for gi, geo in enumerate(geometries):
            rows = [s for s in res["summary"] if s["family"] == fam and s["geometry"] == geo]
            x = np.array([s["cameras"] for s in rows])
            for k, mk in (("precision", "o"), ("recall", "s"), ("f1", "^")):
                m = np.array([s[k] for s in rows])
                sd = np.array([s[k + "_std"] for s in rows])
                col = {"precision": "C0", "recall": "C1", "f1": "C2"}[k]
                ax.plot(x, m, mk + ("-" if gi == 0 else "--"), color=col, label=f"{k} ({geo})")
                ax.fill_between(x, m - sd, m + sd, color=col, alpha=0.12)
        paper = [(n, PAPER_TABLE2[(fam, int(n))][2]) for n in x if (fam, int(n)) in PAPER_TABLE2]
        if paper:
            ax.plot(*zip(*paper, strict=True), "k*:", label="F1 (paper, MapAnything)")
        ax.set_xticks(x)
        ax.set_xlabel("fixed cameras")
        ax.set_ylim(0, 1)
        ax.set_title(fam)
        ax.legend(fontsize=7)
    fig.suptitle("External cameras only")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --- active -----------------------------------------------------------------------------------------
def run_active(cfg: ActiveConfig, torch_threads: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Fig. 2: per (geometry, strategy, external) the per-step node count, recall and distance driven
    over ``cfg.starts`` starts; the reference geometry's curves come after the main ones."""
    from bench.explore import run_episode

    curves: list[dict[str, Any]] = []
    for geometry in cfg.geometries:
        # Multi-view stereo needs baseline: an RGB-only run also maps two frames taken on the way to each
        # goal (both strategies alike); the goal capture applies to every run.
        options: dict[str, Any] = {"goal_capture_m": cfg.goal_capture_m}
        if geometry != "oracle":
            options["move_frames"] = 2
        options.update(cfg.options)
        for strategy in cfg.strategies:
            for ext in cfg.external:
                runs = []
                for start in range(cfg.starts):
                    t0 = time.perf_counter()
                    ep = run_episode(family=cfg.family, seed=cfg.seed, strategy=strategy,
                                     external_cameras=int(ext), steps=cfg.steps, start_index=start,
                                     geometry=geometry, perception=cfg.perception, torch_threads=torch_threads,
                                     log_fn=lambda m: None, **options)
                    nodes, recall, dist = _episode_curves(ep, cfg.steps)
                    runs.append({"start": start, "nodes": nodes, "recall": recall, "distance_m": dist,
                                 "seconds": round(time.perf_counter() - t0, 1)})
                    log(f"active {geometry} {strategy}{'+ext' if ext else ''} start {start}: nodes {nodes[0]:.0f} "
                        f"-> {nodes[-1]:.0f}, recall {recall[0]:.3f} -> {recall[-1]:.3f}, {dist[-1]:.0f} m "
                        f"({runs[-1]['seconds']}s)")
                n = np.array([r["nodes"] for r in runs], float)
                r = np.array([r["recall"] for r in runs], float)
                d = np.array([r["distance_m"] for r in runs], float)
                curves.append({"geometry": geometry, "reference": geometry != cfg.geometry, "strategy": strategy,
                               "external": ext, "runs": runs,
                               "nodes_mean": n.mean(0).tolist(), "nodes_std": n.std(0).tolist(),
                               "recall_mean": r.mean(0).tolist(), "recall_std": r.std(0).tolist(),
                               "distance_mean": d.mean(0).tolist(),
                               "steps_to": {f"{int(100 * q)}%": steps_to(r.mean(0), q) for q in (0.5, 0.8)}})
    return {"config": cfg.model_dump(mode="json"), "curves": curves, "label": _label(cfg.geometry, cfg.perception)}


def _episode_curves(ep: Any, steps: int) -> tuple[list[float], list[float], list[float]]:
    """Node count, recall and metres driven after each step 0..steps (step 0: before moving), padded."""
    records = ep["steps"] if isinstance(ep, dict) else getattr(ep, "steps", ep)
    nodes = [float(_get(s, "n_nodes", "nodes")) for s in records]
    recall = [float(_get(s, "recall")) for s in records]
    dist = [float(_get(s, "distance_m")) for s in records]
    if not nodes:
        nodes, recall, dist = [0.0], [0.0], [0.0]
    while len(nodes) < steps + 1:
        nodes.append(nodes[-1])
        recall.append(recall[-1])
        dist.append(dist[-1])
    return nodes[: steps + 1], recall[: steps + 1], dist[: steps + 1]


def _get(rec: Any, *names: str) -> Any:
    for n in names:
        if isinstance(rec, dict) and n in rec:
            return rec[n]
        if hasattr(rec, n):
            return getattr(rec, n)
    raise KeyError(f"step record has none of {names}")


def _curve_name(c: dict[str, Any]) -> str:
    name = c["strategy"].upper() + (" + Ext" if c["external"] else "")
    return name + (f" ({c['geometry']} geometry)" if c.get("reference") else "")


def active_markdown(res: dict[str, Any]) -> str:
    rows = []
    for c in res["curves"]:
        rows.append({"Method": _curve_name(c), "Nodes@0": f"{c['nodes_mean'][0]:.1f} ± {c['nodes_std'][0]:.1f}",
                     "Nodes@end": f"{c['nodes_mean'][-1]:.1f} ± {c['nodes_std'][-1]:.1f}",
                     "Recall@0": _pm(c["recall_mean"][0], c["recall_std"][0]),
                     "Recall@10": _pm(c["recall_mean"][min(10, len(c["recall_mean"]) - 1)],
                                      c["recall_std"][min(10, len(c["recall_std"]) - 1)]),
                     "Recall@end": _pm(c["recall_mean"][-1], c["recall_std"][-1]),
                     "Steps to 50 %": c.get("steps_to", {}).get("50%"),
                     "Steps to 80 %": c.get("steps_to", {}).get("80%"),
                     "Metres": round(c["distance_mean"][-1], 1) if "distance_mean" in c else None,
                     "Starts": len(c["runs"])})
    cfg = res["config"]
    return (f"## Active exploration (paper Fig. 2)\n\n`{cfg['family']}` seed {cfg['seed']}, {cfg['steps']} steps, "
            f"{cfg['starts']} start poses; {res['label']}. Mean ± std over start poses; curves in active.png.\n\n"
            + markdown_table(rows))


def active_plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    colours = {name: f"C{i}" for i, name in enumerate(dict.fromkeys(c["strategy"] for c in res["curves"]))}
    for c in res["curves"]:
        x = np.arange(len(c["nodes_mean"]))
        for ax, key in ((a1, "nodes"), (a2, "recall")):
            m, s = np.array(c[key + "_mean"]), np.array(c[key + "_std"])
            col = colours[c["strategy"]]
            ref = bool(c.get("reference"))
            ax.plot(x, m, "--" if c["external"] else "-", color=col, label=_curve_name(c),
                    alpha=0.45 if ref else 1.0, linewidth=1.0 if ref else 1.8)
            if not ref:
                ax.fill_between(x, m - s, m + s, color=col, alpha=0.15)
            ax.xaxis.get_major_locator().set_params(integer=True)
    a1.set_xlabel("exploration step")
    a1.set_ylabel("predicted nodes")
    a2.set_xlabel("exploration step")
    a2.set_ylabel("recall")
    a2.set_ylim(0, 1)
    a1.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --- driver -----------------------------------------------------------------------------------------
RUNNERS: dict[str, tuple[Callable[..., dict[str, Any]], Callable[[dict[str, Any]], str],
                         Callable[[dict[str, Any], Path], None]]] = {
    "static": (run_static, static_markdown, static_plot),
    "active": (run_active, active_markdown, active_plot),
    "external": (run_external, external_markdown, external_plot),
    "rooms": (run_rooms, rooms_markdown, rooms_plot),
    "changes": (run_changes, changes_markdown, changes_plot),
}


def run(config: EvalConfig, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the configured experiments; writes ``<name>.json/.md/.png`` and ``summary.md`` under ``out``."""
    import torch

    torch.set_num_threads(config.torch_threads)
    log = log or (lambda m: print(f"[eval] {m}", flush=True))
    out = config.out
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {}
    sections = []
    t_all = time.perf_counter()
    for name in config.experiments:
        runner, to_md, plot = RUNNERS[name]
        t0 = time.perf_counter()
        res = runner(getattr(config, name), config.torch_threads, log)
        res["wall_s"] = round(time.perf_counter() - t0, 1)
        res["machine"] = machine()
        (out / f"{name}.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
        md = to_md(res) + f"\nWall time: {res['wall_s']:.0f} s.\n"
        (out / f"{name}.md").write_text(md)
        plot(res, out / f"{name}.png")
        sections.append(md)
        results[name] = res
        log(f"{name} done in {res['wall_s']:.0f}s -> {out / name}.json/.md/.png")
    total = time.perf_counter() - t_all
    (out / "summary.md").write_text("# argus eval\n\n" + "\n".join(sections)
                                    + f"\nTotal wall time: {total:.0f} s on {machine()['cpu']} "
                                      f"({machine()['cores']} cores).\n")
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus eval",
        description="Reproduce the paper's experiments (static, active, external) on simulated scenes: "
        "JSON, Markdown tables and PNG plots under --out.",
        epilog="examples: argus eval --quick --out eval_out | argus eval static --scenes 5 --out eval_out | "
        "argus eval changes --quick --out eval_out",
    )
    p.add_argument("experiments", nargs="*",
                   help=f"which of {', '.join(EXPERIMENTS + OPTIONAL)} (default: {', '.join(EXPERIMENTS)})")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the config's out, else eval_out)")
    p.add_argument("--quick", action="store_true", help="small subset for CI (< 5 min on 2 cores)")
    p.add_argument("--config", type=Path, default=None, help="TOML file with an EvalConfig (overrides defaults)")
    p.add_argument("--scenes", type=int, default=None, help="scenes per setting (static, external, rooms, changes)")
    p.add_argument("--starts", type=int, default=None, help="start poses (active)")
    p.add_argument("--steps", type=int, default=None, help="exploration steps (active)")
    p.add_argument("--perception", default=None, help="2D perception for all: sim (ORACLE) or classical")
    p.add_argument("--active-geometry", default=None, help="reconstructor of the active runs (default mvs)")
    p.add_argument("--active-reference", default=None,
                   help="reference reconstructor of the active runs (default oracle; 'none' skips it)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    a = p.parse_args(argv)
    unknown = [e for e in a.experiments if e not in EXPERIMENTS + OPTIONAL]
    if unknown:
        print(f"argus eval: unknown experiment(s) {unknown}; choose from {EXPERIMENTS + OPTIONAL}", file=sys.stderr)
        return 2
    try:
        if a.config is not None:
            import tomllib

            data = tomllib.loads(a.config.read_text())
            if a.out is not None:
                data["out"] = str(a.out)
            cfg = EvalConfig.model_validate(data)
        else:
            out = a.out if a.out is not None else Path("eval_out")
            cfg = quick_config(out) if a.quick else EvalConfig(out=out)
        upd: dict[str, Any] = {"torch_threads": a.threads}
        if a.experiments:
            upd["experiments"] = list(dict.fromkeys(a.experiments))
        cfg = cfg.model_copy(update=upd)
        if a.scenes is not None:
            cfg.static.seeds = list(range(a.scenes))
            cfg.external.seeds = list(range(a.scenes))
            cfg.rooms.seeds = list(range(a.scenes))
            cfg.changes.seeds = list(range(a.scenes))
        if a.starts is not None:
            cfg.active.starts = a.starts
        if a.steps is not None:
            cfg.active.steps = a.steps
        if a.active_geometry is not None:
            cfg.active.geometry = a.active_geometry
        if a.active_reference is not None:
            cfg.active.reference_geometry = None if a.active_reference == "none" else a.active_reference
        if a.perception is not None:
            cfg.static.perception = cfg.external.perception = cfg.active.perception = a.perception
            cfg.rooms.perception = cfg.changes.perception = a.perception
    except (ValueError, OSError) as e:
        print(f"argus eval: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    run(cfg)
    print(f"[eval] all done in {time.perf_counter() - t0:.0f}s; tables in {cfg.out / 'summary.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
