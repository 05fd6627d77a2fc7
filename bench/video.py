"""Geometry on video-rate input: recorded RGB-D sequences and the simulator at 30 fps.

Frames arrive consecutively like a live stream, each as a live frame arrives (header + JPEG through the
mapper's intake, ``bench.sequences.WireFeed``), and each is handled the way the mapper handles it
(``mapper.keyframes``): a frame becomes a keyframe by parallax, its source views are chosen from all stored
keyframes by triangulation angle and overlap, a keyframe without a usable source waits for a later one (one
retry per new keyframe, like ``MapperCore``).

Recorded sequences are folders in the layout of ``bench.sequences`` (``../shared/data/<name>/``, each with a
README and licence, never copied into the repository, or any folder given with ``--sequence``). Recorded
poses are the priors; recorded depth is the ground truth.
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

from bench import sequences as seqs
from bench.geomscore import ScenarioResult, score_depth
from bench.sequences import DATA_ROOT, RecordedFrame, WireFeed
from mapper.config import KeyframeConfig
from mapper.core import typical_depth
from mapper.geometry.contract import View, anchor_pose, compose
from mapper.geometry.registry import ORACLE_RECONSTRUCTORS
from mapper.keyframes import KeyframeSelector, KeyframeStore
from protocol.poses import PoseAccuracy, rotation_angle_deg

DECLARED_DEFAULT = PoseAccuracy(trans_m=0.005, rot_deg=0.05)
"""The accuracy the 'declared' runs state for a sequence whose meta file states none: tracking grade (motion
capture, a robot arm, visual-inertial tracking; what every shared sequence without a statement is)."""


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


def wire_frames(recorded: Sequence[RecordedFrame], declared: PoseAccuracy | None,
                source_id: str = "replay") -> list[Frame]:
    """Recorded frames as the mapper sees them from the wire (``bench.sequences.WireFeed``: header + JPEG through
    the mapper's intake), each with its recorded depth as the reference. The recorded pose is the prior and
    the reference pose. A frame the intake refuses is left out."""
    feed = WireFeed(source_id)
    out = []
    for r in recorded:
        v = feed.view(r, declared)
        if v is not None:
            out.append(Frame(v, r.depth_m, r.valid, r.T_world_cam))
    return out


def load_sequence(name: str, root: Path = DATA_ROOT, declared: PoseAccuracy | None = None
                  ) -> tuple[list[Frame], dict[str, int]]:
    """Frames of a sequence folder ``root / name`` through the wire (``wire_frames``; ``declared``: the accuracy
    the frames declare, None: none), and counts (``poses_projected``: near-rotations projected onto SO(3))."""
    seq = seqs.load(root / name)
    return wire_frames(seq.frames, declared, name), {"poses_projected": seq.poses_projected}


def available(name: str, root: Path = DATA_ROOT) -> bool:
    """Whether a sequence folder is present (they are test data outside the repository)."""
    return (root / name / "frames").is_dir()


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
        "cpu_stage_s": dict(recon.info.get("cpu_stage_s", {})),
        "n_sources": len(recon.info.get("sources", {}).get(i, [])),
        "rot_deg_before": rot_before,
        "rot_deg_after": rotation_angle_deg(T, frame.T_true),
        "trans_cm_before": trans_before,
        "trans_cm_after": 100 * float(np.linalg.norm(T[:3, 3] - frame.T_true[:3, 3])),
        "ba": [b.get("status", "accepted" if b.get("accepted") else "rejected") for b in recon.info.get("ba", [])],
    })


def run_keyframed(rec: Any, frames: Sequence[Frame], result: ScenarioResult, label: str,
                  kcfg: KeyframeConfig | None = None, after_frame: Callable[[int], None] | None = None
                  ) -> dict[str, int]:
    """Stream frames through the mapper's keyframe and source selection; score every keyframe that gets depth.
    ``after_frame(k)`` is called after frame ``k`` was handled."""
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

    def handle(k: int, f: Frame) -> None:
        if not selector.consider(f.view):
            store.note_frame(f.view)
            return
        counts["keyframes"] += 1
        if not process(k):
            store.add(f.view)
            deferred.append(k)
            return
        for j in list(deferred):  # one retry per new keyframe, like MapperCore
            if store.neighbours(frames[j].view, selector.scene_depth(frames[j].view.source_id)):
                deferred.remove(j)
                if not process(j):
                    deferred.append(j)
                break

    for k, f in enumerate(frames):
        handle(k, f)
        if after_frame is not None:
            after_frame(k)
    counts["keyframes_without_depth"] = len(deferred)
    return counts


def sim_video_frames(family: str, seed: int, n: int) -> list[Frame]:
    """A simulated robot camera at video rate: 2 cm and 0.6 deg between frames (0.6 m/s at 30 fps), true poses
    as priors declared tracking-grade, through the wire like the recorded sequences."""
    from bench.simdrive import sim_sequences

    kfs, _, _ = sim_sequences(family, seed, 1, n, None, step_m=0.02, turn_deg=0.6, flip_every=30)
    rec = [RecordedFrame(i, k.view.image, k.view.intrinsics.K() if k.view.intrinsics else np.eye(3), k.T_true,
                         k.gt_depth, k.gt_depth > 0) for i, k in enumerate(kfs)]
    return wire_frames(rec, DECLARED_DEFAULT, f"sim{seed}")


def _progress(res: ScenarioResult) -> None:
    s = res.summary()
    print(f"[bench geometry] {res.name}: {s['n_keyframes']} keyframes, AbsRel {s['median_absrel']:.3f}, "
          f"scale {s['median_scale']:.3f}, {s['median_s_per_keyframe']:.2f} s/keyframe", file=sys.stderr, flush=True)


def stretches(n: int, length: int) -> list[tuple[int, int]]:
    """Non-overlapping [start, stop) stretches of ``length`` frames covering ``n`` frames (a shorter tail
    stretch is dropped unless it is the only one)."""
    if length <= 0 or n <= 0:
        return []
    out = [(a, a + length) for a in range(0, n - length + 1, length)]
    return out or [(0, n)]


def long_stream(rec: Any, frames: Sequence[Frame], n_frames: int, label: str) -> dict[str, Any]:
    """``n_frames`` frames played back and forth over ``frames`` (no jump at the turn) through the keyframe path:
    resident memory every 50 frames and seconds per keyframe over the run (the keyframe store and every cache
    are bounded, so both must stay flat)."""
    import resource

    def rss_mb() -> float:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * resource.getpagesize() / 2**20
        except OSError:  # not Linux: the peak is the best there is
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    period = max(1, 2 * len(frames) - 2)
    order = [k % period if k % period < len(frames) else period - k % period for k in range(n_frames)]
    res = ScenarioResult(label)
    rss: list[tuple[int, float]] = []
    # Each pass is a new stretch of stream: frames get new sequence numbers, like a camera that keeps running.
    played = [replace(frames[i], view=replace(frames[i].view, seq=k)) for k, i in enumerate(order)]

    def sample(k: int) -> None:
        if (k + 1) % 50 == 0 or k + 1 == n_frames:
            rss.append((k + 1, rss_mb()))
            print(f"[bench geometry] long stream: {k + 1}/{n_frames} frames, {len(res.frames)} keyframes, "
                  f"RSS {rss[-1][1]:.0f} MB", file=sys.stderr, flush=True)

    run_keyframed(rec, played, res, label, after_frame=sample)
    secs = [f["seconds"] for f in res.frames]
    q = max(1, len(secs) // 4)
    after = [m for k, m in rss if k >= 200]
    return {
        "scenario": label, "frames": n_frames, "keyframes": len(secs), "rss_mb": rss,
        "rss_growth_after_200": (after[-1] / after[0] - 1.0) if len(after) >= 2 else float("nan"),
        "s_per_keyframe_first_quarter": float(np.median(secs[:q])) if secs else float("nan"),
        "s_per_keyframe_last_quarter": float(np.median(secs[-q:])) if secs else float("nan"),
        "median_absrel": res.summary()["median_absrel"],
    }


def bench_video(backend: str, quick: bool, opts: dict[str, Any], sim_seeds: Sequence[int],
                make: Callable[..., Any], folders: Sequence[Path] | None = None, stretch: int = 0,
                long_frames: int = 0) -> dict[str, Any]:
    """Every recorded sequence (``folders``; default: every folder of ../shared/data with a meta file) through
    the wire twice, with the accuracy its meta file states (else ``DECLARED_DEFAULT``) declared and with none
    declared (an unconfigured camera); with ``stretch`` also every ``stretch``-frame piece of each, undeclared,
    as its own stream; with ``long_frames`` a long stream of the first sequence; then the simulator at video rate."""
    scenarios: list[ScenarioResult] = []
    extra: dict[str, Any] = {}
    out: dict[str, Any] = {"stretches": [], "long": None}
    if backend in ORACLE_RECONSTRUCTORS:  # real frames carry no ORACLE data
        folders = []
    for folder in (seqs.discover() if folders is None else folders):
        seq = seqs.load(folder, stop=24 if quick else None)
        declared = seq.meta.declared() or DECLARED_DEFAULT
        for tag, decl in (("declared", declared), ("undeclared", None)):
            frames = wire_frames(seq.frames, decl, seq.name)
            res = ScenarioResult(f"{seq.name}, {tag}")
            counts: dict[str, Any] = dict(run_keyframed(make(backend, **opts), frames, res, seq.name))
            counts.update(poses_projected=seq.poses_projected, sequence=seq.name, declared=tag,
                          declared_rot_deg=None if decl is None else decl.rot_deg,
                          declared_trans_m=None if decl is None else decl.trans_m)
            extra[res.name] = counts
            scenarios.append(res)
            _progress(res)
        for a, b in stretches(len(seq.frames), stretch):
            frames = wire_frames(seq.frames[a:b], None, seq.name)
            res = ScenarioResult(f"{seq.name} frames {a}-{b - 1}, undeclared")
            n = run_keyframed(make(backend, **opts), frames, res, seq.name)
            out["stretches"].append(dict(res.summary(), **n, sequence=seq.name))
            _progress(res)
        if long_frames and out["long"] is None:
            frames = wire_frames(seq.frames, None, seq.name)
            out["long"] = long_stream(make(backend, **opts), frames, long_frames,
                                      f"{seq.name} played back and forth, {long_frames} frames, undeclared")
            print(f"[bench geometry] long stream: {out['long']}", file=sys.stderr, flush=True)
    for seed in sim_seeds:
        frames = sim_video_frames("furnished_room", seed, 24 if quick else 48)
        res = ScenarioResult(f"sim furnished_room/{seed} at video rate, true poses declared")
        extra[res.name] = run_keyframed(make(backend, **opts), frames, res, f"sim/{seed}")
        scenarios.append(res)
        _progress(res)
    out.update(depth=[dict(s.summary(), **extra.get(s.name, {})) for s in scenarios],
               depth_frames={s.name: s.frames for s in scenarios})
    return out
