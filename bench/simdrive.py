"""Simulated robot drives for the geometry benchmarks: keyframes rendered along wandering drives near what a
scene's fixed camera sees, with true or odometry-like pose priors (``bench.geometry``, ``bench.video``)."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapper.geometry.contract import OracleData, View
from protocol.messages import Intrinsics
from protocol.poses import camera_pose_from_base


def _perturb(T: np.ndarray, rng: np.random.Generator, trans_m: float, rot_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(rng.normal(0, math.radians(rot_deg), 3)).as_matrix() @ T[:3, :3]
    out[:3, 3] += rng.normal(0, trans_m, 3)
    return out


def mapper_views(scene: Any, poses_true: Sequence[np.ndarray], priors: Sequence[np.ndarray | None],
                  intr: Any, source_id: str, trusted: bool, prior_rel_rot_deg: float | None = None,
                  prior_rel_trans_m: float | None = None) -> list[Any]:
    """Render each pose and wrap it as a mapper View with its ORACLE data (used only by oracle backends)."""
    from sim.render import Renderer

    renderer = Renderer(scene)
    labels = scene.labels()
    views = []
    for k, (T_true, prior) in enumerate(zip(poses_true, priors, strict=True)):
        out = renderer.render(intr, T_true)
        oracle = OracleData(depth_m=out.depth_m.astype(np.float32), T_world_cam_true=np.asarray(T_true, float),
                            instance_id=out.instance_id.astype(np.int32), labels=labels)
        views.append(View(image=out.rgb, source_id=source_id, intrinsics=intr, T_world_cam=prior,
                          pose_trusted=trusted, stamp_ns=(k + 1) * 1_000_000_000, seq=k, oracle=oracle,
                          prior_rel_rot_deg=prior_rel_rot_deg, prior_rel_trans_m=prior_rel_trans_m))
    return views


# ---- simulated scenes ------------------------------------------------------------------------------------
@dataclass
class SimKeyframe:
    view: View
    gt_depth: np.ndarray
    T_true: np.ndarray


def _drive(nav: Any, x: float, y: float, yaw: float, n: int, rng: np.random.Generator,
           step_m: float = 0.15, turn_deg: float = 8.0, flip_every: int = 4) -> list[tuple]:
    """A wandering drive: forward steps of ``step_m`` while turning ``turn_deg`` per step (the turn direction
    flips every ``flip_every`` steps), staying in free space."""
    turn = math.radians(turn_deg) * (1 if rng.random() < 0.5 else -1)
    poses = [(x, y, yaw)]
    for step in range(n - 1):
        if step and step % flip_every == 0:
            turn = -turn
        x0, y0, yaw0 = poses[-1]
        # Keep ~0.45 m of free space ahead, steering harder when needed; a boxed-in robot backs up
        # (it moves rather than spinning on the spot, which no stereo method can use).
        for t in (turn, -turn, 0.0, 2 * turn, -2 * turn, 4 * turn, -4 * turn, 8 * turn, -8 * turn):
            yaw1 = yaw0 + t
            c, s = math.cos(yaw1), math.sin(yaw1)
            if all(nav.is_free(x0 + d * c, y0 + d * s) for d in (0.15, 0.3, 0.45)):
                poses.append((x0 + step_m * c, y0 + step_m * s, yaw1))
                break
        else:
            c, s = math.cos(yaw0), math.sin(yaw0)
            if nav.is_free(x0 - step_m * c, y0 - step_m * s):
                poses.append((x0 - step_m * c, y0 - step_m * s, yaw0 + turn))
            else:
                poses.append((x0, y0, yaw0 + turn))
    return poses


def _overlap(renderer: Any, intr: Intrinsics, T_a: np.ndarray, pts_world: np.ndarray) -> float:
    T_cw = np.linalg.inv(T_a)
    p = pts_world @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = p[:, 0] / z * intr.fx + intr.cx
        v = p[:, 1] / z * intr.fy + intr.cy
    return float(np.mean((z > 0.3) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)))


def sim_sequences(
    family: str, seed: int, n_clusters: int, per_cluster: int, odom_noise: tuple[float, float] | None,
    step_m: float = 0.15, turn_deg: float = 8.0, flip_every: int = 4,
) -> tuple[list[SimKeyframe], Any, Any]:
    """Robot keyframes that look at what the scene's first fixed camera sees (so a map exists to register
    it against), plus the fixed camera and the renderer."""
    from sim.cameras import place_fixed_cameras
    from sim.nav import NavMap
    from sim.render import Renderer
    from sim.scene import generate_scene

    scene = generate_scene(family, seed)
    nav = NavMap(scene)
    renderer = Renderer(scene)
    intr = Intrinsics.from_fov(640, 480, 90.0)
    cam = place_fixed_cameras(scene, 1, seed, renderer=renderer)[0]
    fixed = renderer.render(cam.intrinsics, cam.T_world_cam)
    # World points the fixed camera sees (ORACLE: used only to choose where the simulated robot drives).
    K = cam.intrinsics
    vv, uu = np.mgrid[0:K.height:8, 0:K.width:8]
    d = fixed.depth_m[vv, uu]
    ok = d > 0
    pc = np.stack([(uu[ok] - K.cx) / K.fx * d[ok], (vv[ok] - K.cy) / K.fy * d[ok], d[ok]], 1)
    pw = pc @ cam.T_world_cam[:3, :3].T + cam.T_world_cam[:3, 3]
    rng = np.random.default_rng(seed)
    vps = [vp for vp in nav.viewpoints(spacing_m=0.6, n_headings=8) if vp.room in (None, cam.room)]
    # A robot exploring the room also looks the way the fixed camera does: prefer such viewpoints.
    from protocol.poses import yaw_of

    cam_yaw = yaw_of(cam.T_world_cam)
    scored = sorted(
        ((_overlap(renderer, intr, camera_pose_from_base(vp.x, vp.y, vp.yaw_rad, 1.0, -15.0), pw)
          * max(0.0, math.cos(vp.yaw_rad - cam_yaw)) ** 2, i)
         for i, vp in enumerate(vps)), reverse=True,
    )
    chosen: list[Any] = []
    for _, i in scored:
        vp = vps[i]
        if all(math.hypot(vp.x - c.x, vp.y - c.y) > 0.9 for c in chosen):
            chosen.append(vp)
        if len(chosen) == n_clusters:
            break
    keyframes: list[SimKeyframe] = []
    seq = 0
    for vp in chosen:
        for x, y, yaw in _drive(nav, vp.x, vp.y, vp.yaw_rad, per_cluster, rng, step_m, turn_deg, flip_every):
            T = camera_pose_from_base(x, y, yaw, 1.0, -15.0)
            out = renderer.render(intr, T)
            prior = T if odom_noise is None else _perturb(T, rng, *odom_noise)
            view = View(out.rgb, "robot", intr, prior, False, seq=seq,
                        oracle=OracleData(out.depth_m, T, out.instance_id))
            keyframes.append(SimKeyframe(view, out.depth_m, T))
            seq += 1
    fixed_view = (cam, fixed)
    return keyframes, fixed_view, renderer


def along_path(path: np.ndarray, step_m: float) -> Iterator[tuple[np.ndarray, float]]:
    """Points every ``step_m`` along a polyline ``path`` (N >= 2, 2) from its start, each with the heading (rad) of
    the segment it lies on: where a simulated robot takes its frames on the way."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    for t in np.arange(0.0, s[-1], step_m):
        i = min(int(np.searchsorted(s, t, side="right")) - 1, len(seg) - 1)
        f = (t - s[i]) / max(seg[i], 1e-9)
        yield path[i] + f * (path[i + 1] - path[i]), math.atan2(*(path[i + 1] - path[i])[::-1])
