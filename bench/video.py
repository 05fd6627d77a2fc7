"""Geometry on video-rate input: real RGB-D sequences and the simulator at 30 fps.

Frames arrive consecutively (or every n-th) like a live stream, and each is handled the way the mapper
handles it (``mapper.keyframes``): a frame becomes a keyframe by parallax, its source views are chosen
from all stored keyframes by triangulation angle and overlap, a keyframe without a usable source waits
for a later one (one retry per new keyframe, like ``MapperCore``). For comparison, the previous policy
(every frame a target, a window of the last N frames) runs as its own variant.

Real sequences live in ``../shared/data/<name>/`` (each with a README and licence; never copied into the
repository): frames/frame-NNNNNN.{color.png, depth.png, pose.txt} (pose = T_world_cam, OpenCV axes)
and camera-intrinsics.txt. Recorded poses are the priors; recorded depth is the ground truth.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.geomscore import ScenarioResult, score_depth
from mapper.config import KeyframeConfig
from mapper.core import typical_depth
from mapper.geometry.contract import View, anchor_pose, compose
from mapper.geometry.registry import ORACLE_RECONSTRUCTORS
from mapper.keyframes import KeyframeSelector, KeyframeStore
from protocol.messages import Intrinsics
from protocol.poses import check_pose, rotation_angle_deg

DATA_ROOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


@dataclass(frozen=True)
class SequenceSpec:
    """How to read one packaged RGB-D sequence."""

    folder: str
    intrinsics_file: str
    depth: Callable[[np.ndarray], np.ndarray]  # raw uint16 -> metres
    valid_m: tuple[float, float]  # recorded depth scored only inside this range
    rel_rot_deg: float  # relative rotation accuracy of the recorded poses (View.prior_rel_rot_deg)


SEQUENCES: dict[str, SequenceSpec] = {
    # TUM RGB-D fr1/xyz, 30 Hz, ~1.2 cm between frames, motion-capture poses (CC BY 4.0).
    "tum-fr1-xyz": SequenceSpec("tum-fr1-xyz", "camera-intrinsics.txt", lambda r: r.astype(np.float32) / 5000.0,
                                (0.1, 10.0), 0.05),
    # HoloLens corridor, ~5.7 cm between frames, device-tracked poses (MIT).
    "hololens-dvmvs": SequenceSpec("hololens-dvmvs", "camera-intrinsics.txt",
                                   lambda r: r.astype(np.float32) / 1000.0, (0.1, 10.0), 0.05),
    # label-fusion shelf, 6-32 cm between frames, recorded poses off by ~2 deg per frame (its README); the depth
    # encoding wraps at 0.82 m (MIT).
    "labelfusion": SequenceSpec("labelfusion", "camera-intrinsics.color.txt",
                                lambda r: (r >> 3).astype(np.float32) / 10000.0, (0.3, 0.82), 2.0),
}


@dataclass
class Frame:
    view: View
    depth_m: np.ndarray
    valid: np.ndarray
    T_true: np.ndarray


def read_image(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """``cv2.imread`` that raises ``ValueError`` for a missing or unreadable file instead of returning None."""
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ValueError(f"cannot read image {path}")
    return np.asarray(img)


def load_sequence(name: str, root: Path = DATA_ROOT) -> tuple[list[Frame], dict[str, int]]:
    """Frames of a packaged sequence with recorded poses as priors (as written: near-orthonormal rotations are
    projected, and counted in the returned stats)."""
    spec = SEQUENCES[name]
    base = root / spec.folder
    K = np.loadtxt(base / spec.intrinsics_file)[:3, :3]
    frames, stats = [], {"poses_projected": 0}
    for p in sorted((base / "frames").glob("frame-*.color.png")):
        stem = p.name[: -len(".color.png")]
        bgr = read_image(p)
        raw = read_image(base / "frames" / f"{stem}.depth.png", cv2.IMREAD_UNCHANGED)
        chk = check_pose(np.loadtxt(base / "frames" / f"{stem}.pose.txt"), source=f"{name} {stem}")
        stats["poses_projected"] += int(chk.projected)
        h, w = bgr.shape[:2]
        intr = Intrinsics(width=w, height=h, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
        depth = spec.depth(raw)
        rgb = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)
        view = View(rgb, name, intr, chk.T, seq=int(stem[6:]),
                    prior_rel_rot_deg=spec.rel_rot_deg)
        frames.append(Frame(view, depth, (depth > spec.valid_m[0]) & (depth < spec.valid_m[1]), chk.T))
    return frames, stats


def available(name: str, root: Path = DATA_ROOT) -> bool:
    """Whether a packaged sequence is present (they are test data outside the repository)."""
    return (root / SEQUENCES[name].folder / "frames").is_dir()


def _record(result: ScenarioResult, label: str, k: int, frame: Frame, prior: np.ndarray | None, recon: Any,
            geo: Any, i: int, seconds: float) -> None:
    s = score_depth(geo.depth_m[i], geo.confidence[i], frame.depth_m, frame.valid)
    T = geo.T_world_cam[i]
    rot_before = math.nan if prior is None else rotation_angle_deg(prior, frame.T_true)
    trans_before = math.nan if prior is None else 100 * float(np.linalg.norm(prior[:3, 3] - frame.T_true[:3, 3]))
    result.seconds.append(seconds)
    result.frames.append({
        "label": label, "k": k, "absrel": s.absrel, "delta125": s.delta125, "confident": s.confident,
        "n_gt": s.n_gt, "scale": s.scale, "seconds": seconds,
        "cpu_seconds": float(recon.info.get("cpu_total_s", math.nan)),
        "t_poses_s": float(recon.info.get("t_poses_s", math.nan)),
        "t_dense_s": float(recon.info.get("t_dense_s", math.nan)),
        "n_sources": len(recon.info.get("sources", {}).get(i, [])),
        "rot_deg_before": rot_before,
        "rot_deg_after": rotation_angle_deg(T, frame.T_true),
        "trans_cm_before": trans_before,
        "trans_cm_after": 100 * float(np.linalg.norm(T[:3, 3] - frame.T_true[:3, 3])),
        "ba": [b.get("status", "accepted" if b.get("accepted") else "rejected") for b in recon.info.get("ba", [])],
    })


def run_keyframed(rec: Any, frames: Sequence[Frame], result: ScenarioResult, label: str,
                  kcfg: KeyframeConfig | None = None) -> dict[str, int]:
    """Stream frames through the mapper's keyframe and source selection; score every keyframe that gets depth."""
    kcfg = kcfg or KeyframeConfig()
    selector, store = KeyframeSelector(kcfg), KeyframeStore(kcfg)
    deferred: list[int] = []
    counts = {"frames": len(frames), "keyframes": 0, "keyframes_without_depth": 0}

    def process(k: int) -> bool:
        v = frames[k].view
        srcs = store.neighbours(v, selector.scene_depth(v.source_id))
        if not srcs:
            return False
        win = [v, *srcs]
        t0 = time.perf_counter()
        r = rec.reconstruct(win, targets=[0])
        dt = time.perf_counter() - t0
        g = compose(r, anchor_pose(r, win))
        _record(result, label, k, frames[k], v.T_world_cam, r, g, 0, dt)
        d = typical_depth(g.depth_m[0], g.confidence[0])
        if d is not None:
            selector.observe_depth(v.source_id, d)
        store.add(v, g.T_world_cam[0], d)
        return True

    for k, f in enumerate(frames):
        if not selector.consider(f.view):
            store.note_frame(f.view)
            continue
        counts["keyframes"] += 1
        if not process(k):
            store.add(f.view)
            deferred.append(k)
            continue
        for j in list(deferred):  # one retry per new keyframe, like MapperCore
            if store.neighbours(frames[j].view, selector.scene_depth(frames[j].view.source_id)):
                deferred.remove(j)
                if not process(j):
                    deferred.append(j)
                break
    counts["keyframes_without_depth"] = len(deferred)
    return counts


def run_last_window(rec: Any, frames: Sequence[Frame], result: ScenarioResult, label: str, window: int) -> None:
    """The previous policy: every frame a target, reconstructed with the last ``window - 1`` frames."""
    for k in range(1, len(frames)):
        win = [f.view for f in frames[max(0, k - window + 1): k + 1]]
        t0 = time.perf_counter()
        r = rec.reconstruct(win, targets=[len(win) - 1])
        dt = time.perf_counter() - t0
        g = compose(r, anchor_pose(r, win))
        _record(result, label, k, frames[k], win[-1].T_world_cam, r, g, len(win) - 1, dt)


def sim_video_frames(family: str, seed: int, n: int) -> list[Frame]:
    """A simulated robot camera at video rate: 2 cm and 0.6 deg between frames (0.6 m/s at 30 fps)."""
    from bench.simdrive import sim_sequences

    kfs, _, _ = sim_sequences(family, seed, 1, n, None, step_m=0.02, turn_deg=0.6, flip_every=30)
    return [Frame(replace(k.view, prior_rel_rot_deg=0.05), k.gt_depth, k.gt_depth > 0, k.T_true) for k in kfs]


def _progress(res: ScenarioResult) -> None:
    s = res.summary()
    print(f"[bench geometry] {res.name}: {s['n_keyframes']} keyframes, AbsRel {s['median_absrel']:.3f}, "
          f"scale {s['median_scale']:.3f}, {s['median_s_per_keyframe']:.2f} s/keyframe", file=sys.stderr, flush=True)


def bench_video(backend: str, quick: bool, opts: dict[str, Any], sim_seeds: Sequence[int],
                make: Callable[..., Any]) -> dict[str, Any]:
    """All video-rate scenarios: each real sequence present (consecutive, every 3rd frame, and the previous
    last-5-frames window in the full run) and the simulator at video rate."""
    scenarios: list[ScenarioResult] = []
    extra: dict[str, Any] = {}
    names = ["tum-fr1-xyz", "hololens-dvmvs"]
    for name in names:
        if not available(name) or backend in ORACLE_RECONSTRUCTORS:
            continue
        frames, stats = load_sequence(name)
        if quick:
            frames = frames[:24]
        variants: list[tuple[str, int, bool]] = [("consecutive", 1, False), ("every 3rd frame", 3, False)]
        if not quick:
            variants.append(("consecutive, last-5 window (previous policy)", 1, True))
        for vname, stride, old in variants:
            res = ScenarioResult(f"{name}, {vname}")
            rec = make(backend, **opts)
            sub = list(frames[::stride])
            if old:
                run_last_window(rec, sub, res, name, 5)
                counts = {"frames": len(sub), "keyframes": len(sub) - 1, "keyframes_without_depth": 0}
            else:
                counts = run_keyframed(rec, sub, res, name)
            counts.update(stats)
            extra[res.name] = counts
            scenarios.append(res)
            _progress(res)
    for seed in sim_seeds:
        frames = sim_video_frames("furnished_room", seed, 24 if quick else 48)
        res = ScenarioResult(f"sim furnished_room/{seed} at video rate, true poses as priors")
        extra[res.name] = run_keyframed(make(backend, **opts), frames, res, f"sim/{seed}")
        scenarios.append(res)
        _progress(res)
    return {
        "depth": [dict(s.summary(), **extra.get(s.name, {})) for s in scenarios],
        "depth_frames": {s.name: s.frames for s in scenarios},
    }
