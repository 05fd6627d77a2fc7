"""``argus sim``: generate, export, load, render, view, check and benchmark simulated scenes.

Examples::

    argus sim render --family apartment --seed 0 --out sim_out      # PNGs: RGB, depth, instance ids
    argus sim export --family furnished_room --seed 3 --out scenes  # glb + JSON (labels, relations)
    argus sim load scenes/furnished_room_003.json --render-out sim_out
    argus sim view --family apartment --seed 0 --out sim_out/apartment.rrd   # Rerun file, no server
    argus sim check --seeds 0-49                                    # both families, sanity checks
    argus sim bench --frames 10                                     # ms per 640x480 frame, both ray casters
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, get_args

import numpy as np

from sim.config import (
    BenchConfig,
    CameraConfig,
    CheckConfig,
    ExportConfig,
    Family,
    RenderConfig,
    SceneSource,
    ViewConfig,
)


def _parse_seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    if not out:
        raise argparse.ArgumentTypeError("no seeds given")
    return out


def get_scene(src: SceneSource) -> Any:
    if src.scene:
        from sim.io import load_scene

        return load_scene(src.scene)
    from sim.scene import generate_scene

    return generate_scene(src.family, src.seed)


def depth_colormap(depth_m: np.ndarray, max_m: float | None = None) -> np.ndarray:
    """Colour-mapped depth (H,W,3) uint8 RGB; black where there is no depth."""
    import cv2

    valid = depth_m > 0
    top = max_m or (float(np.percentile(depth_m[valid], 99)) if valid.any() else 1.0)
    norm = np.clip(depth_m / max(top, 1e-6), 0.0, 1.0)
    bgr = cv2.applyColorMap((255 - norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return bgr[:, :, ::-1].copy()


def ids_colormap(instance_id: np.ndarray) -> np.ndarray:
    """Instance ids as distinct colours (H,W,3) uint8 RGB: structure dark grey, nothing black."""
    from sim.materials import hash01

    ids = instance_id.astype(np.int64)
    z = np.zeros_like(ids)
    rgb = np.stack([hash01(ids, z, z, s) for s in (1, 2, 3)], axis=-1)
    rgb = (60 + rgb * 195).astype(np.uint8)
    rgb[ids == 0] = 70
    rgb[ids < 0] = 0
    return rgb


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), rgb[:, :, ::-1]):
        raise OSError(f"could not write {path}")


def robot_views(scene: Any, nav: Any, height_m: float = 1.0, pitch_deg: float = -15.0) -> list[tuple[str, np.ndarray]]:
    """One robot-height camera pose per room: from the free cell farthest from the room centre, facing it."""
    from protocol.poses import camera_pose_from_base

    out = []
    for room in scene.rooms:
        cells = nav.room_cells(room)
        if len(cells) == 0:
            continue
        c = (room.xy_min + room.xy_max) / 2
        p = cells[int(np.argmax(np.linalg.norm(cells - c, axis=1)))]
        yaw = math.atan2(c[1] - p[1], c[0] - p[0])
        out.append((f"robot_{room.name}", camera_pose_from_base(p[0], p[1], yaw, height_m, pitch_deg)))
    return out


def run_render(cfg: RenderConfig) -> list[Path]:
    from protocol.messages import Intrinsics
    from sim.cameras import place_fixed_cameras
    from sim.nav import NavMap
    from sim.render import Renderer

    scene = get_scene(cfg.source)
    K = Intrinsics.from_fov(cfg.camera.width, cfg.camera.height, cfg.camera.hfov_deg)
    renderer = Renderer(scene, backend=cfg.backend)
    views: list[tuple[str, np.ndarray]] = []
    if cfg.n_fixed:
        views += [(c.camera_id, c.T_world_cam)
                  for c in place_fixed_cameras(scene, cfg.n_fixed, scene.seed, K, renderer=renderer)]
    if cfg.robot_views:
        views += robot_views(scene, NavMap(scene, renderer=renderer))
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{scene.family}_{scene.seed:03d}"
    written, times = [], []
    for name, T in views:
        t0 = time.perf_counter()
        r = renderer.render(K, T)
        times.append(time.perf_counter() - t0)
        for kind, img in (("rgb", r.rgb), ("depth", depth_colormap(r.depth_m)), ("ids", ids_colormap(r.instance_id))):
            p = out / f"{stem}_{name}_{kind}.png"
            _write_png(p, img)
            written.append(p)
    print(json.dumps({"scene": scene.summary(), "views": len(views), "backend": renderer.backend,
                      "render_ms_per_frame": round(1e3 * float(np.mean(times)), 1) if times else None,
                      "out_dir": str(out)}, indent=1))
    return written


def run_export(cfg: ExportConfig) -> tuple[Path, Path]:
    from sim.cameras import place_fixed_cameras
    from sim.io import export_scene

    scene = get_scene(cfg.source)
    cams = place_fixed_cameras(scene, cfg.n_cameras, scene.seed) if cfg.n_cameras else None
    glb, js = export_scene(scene, cfg.out_dir, cameras=cams)
    print(json.dumps({"gltf": str(glb), "json": str(js), "scene": scene.summary()}, indent=1))
    return glb, js


def run_view(cfg: ViewConfig) -> Path:
    import rerun as rr

    from sim.cameras import place_fixed_cameras
    from sim.render import Renderer

    scene = get_scene(cfg.source)
    out = Path(cfg.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(application_id="argus_sim")
    rec.save(str(out))  # file sink only: nothing is served, no port is bound
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    colors = np.array([[*(np.array(m.color1) * 255), 255] for m in scene.materials], np.uint8)

    def log_mesh(path: str, mesh: Any, fm: np.ndarray) -> None:
        tri = np.asarray(mesh.triangles, np.float32).reshape(-1, 3)
        vc = np.repeat(colors[fm], 3, axis=0)
        rec.log(path, rr.Mesh3D(vertex_positions=tri, triangle_indices=np.arange(len(tri)).reshape(-1, 3),
                                vertex_colors=vc), static=True)

    # the ceiling would hide everything from above: log structure below 2 m only
    s = scene.structure
    keep = s.triangles_center[:, 2] < 2.0
    log_mesh("world/structure", s.submesh([np.nonzero(keep)[0]], append=True, repair=False),
             scene.structure_face_material[keep])
    for o in scene.objects:
        fm = o.face_material if o.face_material is not None else np.zeros(len(o.mesh.faces), np.int32)
        log_mesh(f"world/objects/{o.obj_id:04d}_{o.category}", o.mesh, fm)
    rec.log("world/boxes", rr.Boxes3D(
        centers=[o.box.center for o in scene.objects], half_sizes=[np.array(o.box.extent) / 2 for o in scene.objects],
        rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=o.box.yaw_rad) for o in scene.objects],
        labels=[o.label for o in scene.objects]), static=True)
    strips = []
    for a, pred, b in scene.relations:
        if pred != "next_to":
            strips.append([scene.object_by_id(a).centroid, scene.object_by_id(b).centroid])
    if strips:
        rec.log("world/relations", rr.LineStrips3D(strips), static=True)
    if cfg.n_fixed:
        renderer = Renderer(scene)
        for c in place_fixed_cameras(scene, cfg.n_fixed, scene.seed, renderer=renderer):
            T = c.T_world_cam
            rec.log(f"world/cameras/{c.camera_id}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            K = c.intrinsics
            rec.log(f"world/cameras/{c.camera_id}/image", rr.Pinhole(
                focal_length=[K.fx, K.fy], principal_point=[K.cx, K.cy], width=K.width, height=K.height,
                camera_xyz=rr.ViewCoordinates.RDF), static=True)
            rec.log(f"world/cameras/{c.camera_id}/image", rr.Image(renderer.render(K, T).rgb), static=True)
    rec.flush()
    print(json.dumps({"rrd": str(out), "scene": scene.summary()}, indent=1))
    return out


def run_check(cfg: CheckConfig) -> dict[str, Any]:
    from sim.check import check_scene
    from sim.scene import generate_scene

    report: dict[str, Any] = {"scenes": [], "errors": 0, "issues": 0}
    for fam in cfg.families:
        for seed in cfg.seeds:
            t0 = time.perf_counter()
            entry: dict[str, object]
            try:
                scene = generate_scene(fam, seed)
                gen_s = time.perf_counter() - t0
                issues = check_scene(scene, full=cfg.full)
                n = sum(len(v) for v in issues.values())
                entry = {"family": fam, "seed": seed, "n_objects": len(scene.objects), "n_rooms": len(scene.rooms),
                         "n_categories": len({o.category for o in scene.objects}), "gen_s": round(gen_s, 3),
                         "issues": {k: v for k, v in issues.items() if v}}
                report["issues"] += n
            except Exception as e:  # noqa: BLE001 - a failing seed is reported, the sweep carries on
                entry = {"family": fam, "seed": seed, "error": f"{type(e).__name__}: {e}"}
                report["errors"] += 1
            report["scenes"].append(entry)
            print(json.dumps(entry), flush=True)
    for fam in cfg.families:
        ok = [s for s in report["scenes"] if s["family"] == fam and "error" not in s]
        if ok:
            counts = [s["n_objects"] for s in ok]
            report[f"{fam}_objects"] = {"min": min(counts), "mean": round(float(np.mean(counts)), 1),
                                        "max": max(counts)}
            report[f"{fam}_gen_s_mean"] = round(float(np.mean([s["gen_s"] for s in ok])), 3)
    if cfg.out:
        Path(cfg.out).write_text(json.dumps(report, indent=1))
    print(json.dumps({k: v for k, v in report.items() if k != "scenes"}, indent=1))
    return report


def run_bench(cfg: BenchConfig) -> dict[str, Any]:
    from protocol.messages import Intrinsics
    from sim.cameras import place_fixed_cameras
    from sim.nav import NavMap
    from sim.render import Renderer, benchmark

    t0 = time.perf_counter()
    scene = get_scene(cfg.source)
    gen_s = time.perf_counter() - t0
    K = Intrinsics.from_fov(cfg.camera.width, cfg.camera.height, cfg.camera.hfov_deg)
    r = Renderer(scene)
    t0 = time.perf_counter()
    nav = NavMap(scene, renderer=r)
    nav_s = time.perf_counter() - t0
    poses = [T for _, T in robot_views(scene, nav)] + [c.T_world_cam for c in place_fixed_cameras(scene, 3, 0, K)]
    poses = (poses * (cfg.frames // max(len(poses), 1) + 1))[: cfg.frames]
    res = {"scene": scene.summary(), "generate_s": round(gen_s, 3), "navmap_s": round(nav_s, 3),
           "resolution": [K.width, K.height], "frames": len(poses),
           "backends": benchmark(scene, K, poses, tuple(cfg.backends))}
    if cfg.out:
        Path(cfg.out).write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return res


def _source_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--family", choices=list(get_args(Family)), default="apartment",
                   help="scene family (apartment_large: 7-9 rooms, 150-190 objects)")
    p.add_argument("--seed", type=int, default=0, help="generator seed")
    p.add_argument("--scene", default=None, help="load this scene JSON instead of generating")


def _camera_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fov", type=float, default=90.0, help="horizontal field of view, degrees")


def _src(a: argparse.Namespace) -> SceneSource:
    return SceneSource(family=a.family, seed=a.seed, scene=a.scene)


def _cam(a: argparse.Namespace) -> CameraConfig:
    return CameraConfig(width=a.width, height=a.height, hfov_deg=a.fov)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="argus sim", description="The embedded simulated world (scenes, renderer, ground truth).",
        epilog="example: argus sim render --family apartment --seed 0 --out sim_out",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("render", help="render RGB / depth / id PNGs from fixed and robot cameras")
    _source_args(p)
    _camera_args(p)
    p.add_argument("--out", default="sim_out")
    p.add_argument("--fixed", type=int, default=3, help="fixed camera views (0-3)")
    p.add_argument("--no-robot", action="store_true", help="skip the per-room robot views")
    p.add_argument("--backend", choices=["embree", "open3d"], default="embree")
    p = sub.add_parser("export", help="write a scene as glTF (.glb) + JSON")
    _source_args(p)
    p.add_argument("--out", default="sim_out")
    p.add_argument("--cameras", type=int, default=3, help="fixed cameras to store (0-3)")
    p = sub.add_parser("load", help="read a scene JSON (+ its glb) back and summarise or render it")
    p.add_argument("path", help="scene JSON written by 'argus sim export'")
    p.add_argument("--render-out", default=None, help="also render PNGs into this directory")
    p.add_argument("--check", action="store_true", help="run the sanity checks on it")
    p = sub.add_parser("view", help="log a scene to a Rerun recording file (.rrd)")
    _source_args(p)
    p.add_argument("--out", default="sim_out/scene.rrd")
    p.add_argument("--fixed", type=int, default=2)
    p = sub.add_parser("check", help="generate many scenes and run the sanity checks")
    p.add_argument("--seeds", type=_parse_seeds, default=list(range(50)), help="e.g. 0-49 or 0,3,7")
    p.add_argument("--families", default="apartment,furnished_room",
                   help=f"comma-separated, of {', '.join(get_args(Family))}")
    p.add_argument("--full", action="store_true", help="also check interpenetration (slower)")
    p.add_argument("--out", default=None, help="JSON report path")
    p = sub.add_parser("bench", help="render time per frame for the ray-casting backends")
    _source_args(p)
    _camera_args(p)
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--backends", default="embree,open3d")
    p.add_argument("--out", default=None)
    a = parser.parse_args(argv)
    try:
        if a.cmd == "render":
            run_render(RenderConfig(source=_src(a), out_dir=a.out, camera=_cam(a), n_fixed=a.fixed,
                                    robot_views=not a.no_robot, backend=a.backend))
        elif a.cmd == "export":
            run_export(ExportConfig(source=_src(a), out_dir=a.out, n_cameras=a.cameras))
        elif a.cmd == "load":
            from sim.io import load_scene

            scene = load_scene(a.path)
            info: dict[str, Any] = {"scene": scene.summary()}
            if a.check:
                from sim.check import check_scene

                info["issues"] = check_scene(scene)
            print(json.dumps(info, indent=1))
            if a.render_out:
                run_render(RenderConfig(source=SceneSource(scene=a.path), out_dir=a.render_out))
        elif a.cmd == "view":
            run_view(ViewConfig(source=_src(a), out=a.out, n_fixed=a.fixed))
        elif a.cmd == "check":
            fams = [f.strip() for f in a.families.split(",") if f.strip()]
            check = {"families": fams, "seeds": a.seeds, "full": a.full, "out": a.out}
            rep = run_check(CheckConfig.model_validate(check))
            return 1 if rep["errors"] or rep["issues"] else 0
        elif a.cmd == "bench":
            backends = [b.strip() for b in a.backends.split(",") if b.strip()]
            run_bench(BenchConfig.model_validate({"source": _src(a), "camera": _cam(a), "frames": a.frames,
                                                  "out": a.out, "backends": backends}))
    except (ValueError, OSError, KeyError) as e:
        print(f"argus sim {a.cmd}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
