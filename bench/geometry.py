"""``argus bench geometry``: quality and speed of RGB-only geometry (the ``mvs`` reconstructor by default).

Scenarios
- sim robot, known poses: short robot drives in simulated scenes (both families); each keyframe is
  reconstructed the way the mapper does it (a window of the last views, the newest as target) with the
  true poses as priors; depth scored against the ORACLE depth.
- sim robot, odometry priors: the same with priors perturbed like wheel odometry (refined from images).
- sim fixed camera, uncalibrated: a robot-built map (mvs depth of the robot's keyframes), then the fixed
  camera registered against it with no pose: rotation / translation error against the truth.
- recorded sequences (``bench/sequences.py``; every folder of ../shared/data with a meta file, or
  ``--sequence DIR``): each frame goes the way a live frame goes (header + JPEG through the mapper's intake),
  through the mapper's keyframe and source selection, twice: with the sequence's stated pose accuracy
  declared in the header, and with none (an unconfigured camera). Depth scored against the recorded depth;
  the worst sequence decides.

Depth is scored on confident pixels (confidence >= 0.5): median AbsRel, delta < 1.25, and the
fraction of pixels with ground truth that are confident. Writes geometry.json and geometry.md.

Example:
  argus bench geometry --quick --out bench_out/geometry
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.geomscore import ScenarioResult, score_depth
from bench.report import key_values
from bench.simdrive import sim_sequences
from mapper.geometry.contract import OracleData, View, anchor_pose, compose
from mapper.geometry.register import MapKeyframe, PoseEstimate, register_view
from mapper.geometry.registry import make_reconstructor
from mapper.keyframes import intrinsics_of
from protocol.poses import rotation_angle_deg

REPO_ROOT = Path(__file__).resolve().parents[1]
WINDOW = 5

BARS = {
    "video_absrel": 0.08,  # every recorded sequence, nothing declared (the worst one decides)
    "video_absrel_declared": 0.06,  # ... with the accuracy declared
    "video_delta125": 0.90,
    "video_confident": 0.45,
    "video_scale_tol": 0.03,
    "s_per_keyframe_video": 0.5,
    "sim_known_absrel": 0.05,
    "sim_known_confident": 0.70,
    "reg_rot_deg": 2.0,
    "reg_trans_m": 0.15,
    "reg_success": 0.90,
    "pair_trans_frac": 0.05,
    "s_per_keyframe": 2.0,
}


def run_incremental(rec: Any, views: Sequence[View], gts: Sequence[tuple[np.ndarray, np.ndarray]],
                    result: ScenarioResult, label: str, window: int = WINDOW) -> list[tuple[int, Any]]:
    """Reconstruct keyframes one at a time like the mapper (window of the last views, newest as target)."""
    outputs = []
    for k in range(len(views)):
        win = list(views[max(0, k - window + 1): k + 1])
        t0 = time.perf_counter()
        r = rec.reconstruct(win, targets=[len(win) - 1])
        dt = time.perf_counter() - t0
        g = compose(r, anchor_pose(r, win))
        i = len(win) - 1
        if k > 0:  # the very first keyframe has nothing to match against
            result.seconds.append(dt)
            s = score_depth(g.depth_m[i], g.confidence[i], gts[k][0], gts[k][1])
            result.frames.append({"label": label, "k": k, "absrel": s.absrel, "delta125": s.delta125,
                                  "confident": s.confident, "n_gt": s.n_gt, "seconds": dt,
                                  "cpu_seconds": float(r.info.get("cpu_total_s", float("nan")))})
        outputs.append((k, (g, i, r)))
    return outputs


def bench_sim(
    families: Sequence[str], seeds: Sequence[int], quick: bool, backend: str, opts: dict[str, Any]
) -> dict[str, Any]:
    known = ScenarioResult("sim robot, known poses")
    odom = ScenarioResult("sim robot, odometry priors (1 cm, 0.5 deg)")
    fixed_depth = ScenarioResult("sim fixed camera, registered pose, depth from the robot keyframes")
    reg_trials: list[dict[str, Any]] = []
    pair_trials: list[dict[str, Any]] = []
    # One continuous drive per scene, like the stream of keyframes the mapper sees.
    n_clusters, per_cluster = (1, 8) if quick else (1, 12)
    for family in families:
        for seed in seeds:
            kfs, (cam, fixed), renderer = sim_sequences(family, seed, n_clusters, per_cluster, None)
            pair_trials.append(fixed_pair_trial(renderer, cam, fixed.rgb, f"{family}/{seed}"))
            rec = make_reconstructor(backend, **opts)
            gts = [(k.gt_depth, k.gt_depth > 0) for k in kfs]
            outs = run_incremental(rec, [k.view for k in kfs], gts, known, f"{family}/{seed}")
            # Registration of the fixed camera, uncalibrated extrinsics, against the robot-built map.
            map_kfs = []
            for (k, (g, i, _)) in outs:
                map_kfs.append(MapKeyframe(kfs[k].view.image, intrinsics_of(kfs[k].view), g.T_world_cam[i],
                                           g.depth_m[i], g.intrinsics[i], g.confidence[i], kfs[k].view.key))
            fview = View(fixed.rgb, cam.camera_id, cam.intrinsics, None)
            t0 = time.perf_counter()
            est = register_view(fview, [m for m in map_kfs if m.confidence is not None and m.confidence.max() > 0])
            reg_trials.append(_reg_trial(est, cam.T_world_cam, f"{family}/{seed}", time.perf_counter() - t0))
            if est.ok and est.T_world_cam is not None:
                # The fixed camera's own depth: swept against the robot keyframes that see the same things.
                fv = View(fixed.rgb, cam.camera_id, cam.intrinsics, est.T_world_cam, False, seq=1_000_000,
                          oracle=OracleData(fixed.depth_m, cam.T_world_cam, fixed.instance_id))
                win = [fv, *[k.view for k in kfs]]
                t0 = time.perf_counter()
                r = rec.reconstruct(win, targets=[0])
                dt = time.perf_counter() - t0
                g = compose(r, anchor_pose(r, win))
                s = score_depth(g.depth_m[0], g.confidence[0], fixed.depth_m, fixed.depth_m > 0)
                fixed_depth.seconds.append(dt)
                fixed_depth.frames.append({"label": f"{family}/{seed}", "k": 0, "absrel": s.absrel,
                                           "delta125": s.delta125, "confident": s.confident, "n_gt": s.n_gt,
                                           "seconds": dt, "cpu_seconds": float(r.info.get("cpu_total_s", np.nan))})
            print(f"[bench geometry] sim {family}/{seed}: known poses done, registration {reg_trials[-1]['success']}",
                  file=sys.stderr, flush=True)
            kfs_o, _, _ = sim_sequences(family, seed, n_clusters, per_cluster, (0.01, 0.5))
            rec_o = make_reconstructor(backend, **opts)
            run_incremental(rec_o, [k.view for k in kfs_o], [(k.gt_depth, k.gt_depth > 0) for k in kfs_o], odom,
                            f"{family}/{seed}")
    ok = [t for t in reg_trials if t["success"]]
    return {
        "depth": [known.summary(), odom.summary(), fixed_depth.summary()],
        "depth_frames": {known.name: known.frames, odom.name: odom.frames, fixed_depth.name: fixed_depth.frames},
        "fixed_pair": {
            "trials": pair_trials,
            "median_rot_deg": _median_of_trials([t["rot_deg"] for t in pair_trials]),
            "median_trans_pct": _median_of_trials([t["trans_pct"] for t in pair_trials]),
            "within_bar": (sum(t["trans_pct"] <= 100 * BARS["pair_trans_frac"] for t in pair_trials) / len(pair_trials)
                           if pair_trials else float("nan")),
        },
        "registration": {
            "trials": reg_trials,
            "success_rate": len(ok) / len(reg_trials) if reg_trials else float("nan"),
            "median_rot_deg": _median_of_trials([t["rot_deg"] for t in reg_trials]),
            "median_trans_m": _median_of_trials([t["trans_m"] for t in reg_trials]),
        },
    }


def _median_of_trials(values: Sequence[float]) -> float:
    """Median over trials, failed ones (inf) included; NaN when there are none."""
    return float(np.median(values)) if len(values) else float("nan")


def fixed_pair_trial(renderer: Any, cam: Any, image_a: np.ndarray, label: str, baseline_m: float = 1.2,
                     ) -> dict[str, Any]:
    """A second fixed camera ``baseline_m`` along the wall from a calibrated one, aimed at the same spot:
    its pose from the essential matrix, metric scale from the first camera's mounting height (floor z = 0)."""
    from mapper.geometry.register import two_view_pose
    from protocol.poses import look_at

    A = np.asarray(cam.T_world_cam, np.float64)
    axis = A[:3, 2]
    target = A[:3, 3] + axis * ((0.6 - A[2, 3]) / axis[2])  # where A's optical axis is 0.6 m above the floor
    # Along the wall (a world axis) towards the room: the horizontal axis A looks along most.
    k = int(np.argmax(np.abs(axis[:2])))
    step = np.zeros(3)
    step[k] = math.copysign(baseline_m, axis[k])
    B = look_at(A[:3, 3] + step, target)
    image_b = renderer.render(cam.intrinsics, B).rgb
    t0 = time.perf_counter()
    est = two_view_pose(View(image_a, "cam_a", cam.intrinsics, A, True), View(image_b, "cam_b", cam.intrinsics, None),
                        camera_height_m=float(A[2, 3]))
    dt = time.perf_counter() - t0
    if est.T_world_cam is None:
        rot, trans = float("inf"), float("inf")
    else:
        rot = rotation_angle_deg(est.T_world_cam, B)
        trans = float(np.linalg.norm(est.T_world_cam[:3, 3] - B[:3, 3]))
    return {"label": label, "ok": bool(est.ok), "inliers": int(est.inliers), "rot_deg": rot,
            "trans_m": trans, "trans_pct": 100.0 * trans / baseline_m, "seconds": dt, "reason": est.reason}


def _reg_trial(est: PoseEstimate, T_true: np.ndarray, label: str, seconds: float) -> dict[str, Any]:
    if est.T_world_cam is None:
        rot, trans = float("inf"), float("inf")
    else:
        rot = rotation_angle_deg(est.T_world_cam, T_true)
        trans = float(np.linalg.norm(est.T_world_cam[:3, 3] - T_true[:3, 3]))
    success = bool(est.ok and rot <= BARS["reg_rot_deg"] and trans <= BARS["reg_trans_m"])
    return {"label": label, "ok": est.ok, "reason": est.reason, "inliers": est.inliers, "rot_deg": rot,
            "trans_m": trans, "success": success, "seconds": seconds}


# ---- report --------------------------------------------------------------------------------------------
def _fmt(x: float, nd: int = 3) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def cpu_headline(report: dict[str, Any]) -> str | None:
    """The report's first figure: CPU-seconds per keyframe of the reconstruction (median over the scenarios'
    medians, with their range) and the cameras one core carries at one keyframe per second each; None without
    a timed scenario."""
    cpu = [s["median_cpu_s_per_keyframe"] for block in ("sim", "real", "video") if report.get(block)
           for s in report[block]["depth"] if np.isfinite(s.get("median_cpu_s_per_keyframe", np.nan))]
    if not cpu:
        return None
    mid = float(np.median(cpu))
    return (f"**{mid:.2f} CPU-seconds per keyframe** (median over {len(cpu)} scenarios, {min(cpu):.2f}-"
            f"{max(cpu):.2f}; the reconstruction alone: perception, fusion and transfers come on top, "
            f"`argus bench system` counts them): one core carries {1.0 / mid:.1f} cameras at one keyframe per "
            "second each.")


def markdown(report: dict[str, Any]) -> str:
    head = cpu_headline(report)
    lines = [f"# Geometry benchmark (`{report['backend']}`)", "", *([head, ""] if head else []),
             f"{report['machine']}, {report['cpus']} CPUs, load average {report['load_avg']} at start "
             "(the machine is shared: wall times include contention; CPU s is process time).",
             f"Each keyframe: window of the last {WINDOW} keyframes, newest as target, like the mapper. "
             f"Backend options: {report.get('options') or 'defaults'}.", "",
             "| scenario | keyframes | median AbsRel | delta<1.25 | confident (median / mean) "
             "| s/keyframe (median / p90) | CPU s/keyframe |",
             "|---|---|---|---|---|---|---|"]
    for block in ("sim", "real", "video"):
        if report.get(block):
            for s in report[block]["depth"]:
                lines.append(
                    f"| {s['scenario']} | {s['n_keyframes']} | {_fmt(s['median_absrel'])} | "
                    f"{_fmt(s['median_delta125'])} | {_fmt(s['median_confident'])} / {_fmt(s['mean_confident'])} | "
                    f"{_fmt(s['median_s_per_keyframe'], 2)} / {_fmt(s['p90_s_per_keyframe'], 2)} | "
                    f"{_fmt(s['median_cpu_s_per_keyframe'], 2)} |"
                )
    if report.get("video"):
        lines += ["", "## Video-rate input: keyframes and sources chosen by parallax", "",
                  "Scale = median estimated / recorded depth; time = pose refinement + dense depth per keyframe; "
                  "pose error of the target against the recorded (true) pose before / after refinement.", "",
                  "| scenario | frames (poses projected) | keyframes (no depth) | scale | s poses / dense "
                  "| rot err deg before / after | trans err cm before / after |", "|---|---|---|---|---|---|---|"]
        for s in report["video"]["depth"]:
            lines.append(
                f"| {s['scenario']} | {s.get('frames', '-')} ({s.get('poses_projected', 0)}) | "
                f"{s.get('keyframes', '-')} "
                f"({s.get('keyframes_without_depth', '-')}) | {_fmt(s['median_scale'])} | "
                f"{_fmt(s['median_t_poses_s'], 2)} / {_fmt(s['median_t_dense_s'], 2)} | "
                f"{_fmt(s['median_pose_rot_deg_before'], 2)} / {_fmt(s['median_pose_rot_deg_after'], 2)} | "
                f"{_fmt(s['median_pose_trans_cm_before'], 2)} / {_fmt(s['median_pose_trans_cm_after'], 2)} |"
            )
    stage_rows = [s for block in ("sim", "real", "video") if report.get(block) for s in report[block]["depth"]
                  if s.get("median_cpu_stage_s")]
    if stage_rows:
        stages = list(stage_rows[0]["median_cpu_stage_s"])
        lines += ["", "## Where a keyframe's CPU goes (median CPU seconds per stage)", "",
                  "features: SIFT of views not yet cached; matching: ratio test, epipolar and prior checks of new "
                  "pairs; poses: tracks, bundle adjustment, held-out check; sweep: plane sweep of the target and of "
                  "neighbours without a depth map; consistency: multi-view check and texture gate; upsample: "
                  "edge-aware upsampling to the output size; other: the rest of the call.", "",
                  "| scenario | " + " | ".join(stages) + " |", "|---|" + "---|" * len(stages)]
        for s in stage_rows:
            lines.append(f"| {s['scenario']} | "
                         + " | ".join(_fmt(s["median_cpu_stage_s"].get(k), 3) for k in stages) + " |")
    if report.get("video"):
        worst = worst_rows(report["video"]["depth"])
        if worst:
            lines += ["", "## Worst recorded sequence (each figure its own worst)", "",
                      "| declared accuracy | sequences | AbsRel (max) | delta<1.25 (min) | coverage (min) "
                      "| scale (furthest from 1) |", "|---|---|---|---|---|---|"]
            for w in worst:
                lines.append(f"| {w['declared']} | {w['n']} | {_fmt(w['absrel'])} ({w['absrel_at']}) | "
                             f"{_fmt(w['delta125'])} ({w['delta125_at']}) | {_fmt(w['confident'])} "
                             f"({w['confident_at']}) | {_fmt(w['scale'])} ({w['scale_at']}) |")
        st = report["video"].get("stretches") or []
        if st:
            lines += ["", "## Short stretches, each its own stream, nothing declared", "",
                      "| stretch | keyframes (no depth) | AbsRel | delta<1.25 | coverage | scale |",
                      "|---|---|---|---|---|---|"]
            for x in st:
                lines.append(f"| {x['scenario']} | {x['keyframes']} ({x['keyframes_without_depth']}) | "
                             f"{_fmt(x['median_absrel'])} | {_fmt(x['median_delta125'])} | "
                             f"{_fmt(x['median_confident'])} | {_fmt(x['median_scale'])} |")
            ws = worst_rows([dict(x, declared="undeclared") for x in st])
            if ws:
                lines.append(f"| **worst stretch** | | {_fmt(ws[0]['absrel'])} | {_fmt(ws[0]['delta125'])} | "
                             f"{_fmt(ws[0]['confident'])} | {_fmt(ws[0]['scale'])} |")
        lg = report["video"].get("long")
        if lg:
            lines += ["", f"## Long stream: {lg['scenario']}", "",
                      f"{lg['keyframes']} keyframes; resident memory growth after the first 200 frames "
                      f"{100 * lg['rss_growth_after_200']:.1f} %; seconds per keyframe (median) first quarter "
                      f"{_fmt(lg['s_per_keyframe_first_quarter'], 2)}, last quarter "
                      f"{_fmt(lg['s_per_keyframe_last_quarter'], 2)}; RSS MB by frame: "
                      + ", ".join(f"{k}: {m:.0f}" for k, m in lg["rss_mb"])]
    if report.get("sim"):
        reg = report["sim"]["registration"]
        lines += ["", "## Uncalibrated fixed camera registered against the robot-built map", "",
                  "| trial | ok | inliers | rot err (deg) | trans err (m) | within bars | reason |",
                  "|---|---|---|---|---|---|---|"]
        for t in reg["trials"]:
            lines.append(f"| {t['label']} | {t['ok']} | {t['inliers']} | {_fmt(t['rot_deg'], 2)} | "
                         f"{_fmt(t['trans_m'], 3)} | {t['success']} | {t['reason']} |")
        lines.append(f"\nsuccess rate {_fmt(reg['success_rate'], 2)} (bar >= {BARS['reg_success']})")
        pair = report["sim"].get("fixed_pair")
        if pair:
            lines += ["", "## Second fixed camera 1.2 m along the wall: essential matrix, scale from the first "
                      "camera's mounting height", "",
                      "| trial | ok | inliers | rot err (deg) | trans err (% of baseline) | reason |",
                      "|---|---|---|---|---|---|"]
            for t in pair["trials"]:
                lines.append(f"| {t['label']} | {t['ok']} | {t['inliers']} | {_fmt(t['rot_deg'], 2)} | "
                             f"{_fmt(t['trans_pct'], 1)} | {t['reason']} |")
    lines += ["", "## Bars", "", "| bar | target | measured | met |", "|---|---|---|---|"]
    for b in report["bars"]:
        lines.append(f"| {b['bar']} | {b['target']} | {_fmt(b['measured'])} | {b['met']} |")
    return "\n".join(lines) + "\n"


def _worst(rows: Sequence[dict[str, Any]], key: str, badness: Any) -> tuple[float, str]:
    """The value of ``key`` in the row where ``badness`` of it is largest (NaN counts as worst), and where."""
    r = max(rows, key=lambda r: math.inf if not np.isfinite(r[key]) else badness(r[key]))
    return float(r[key]), str(r.get("sequence", r["scenario"]))


def worst_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per declaration ("declared", "undeclared"), the worst recorded sequence of each figure and where it is:
    the largest AbsRel, the smallest delta<1.25 and coverage, the scale furthest from 1. Rows without a
    ``declared`` entry (the simulator) are left out; a sequence that scored no pixel counts as worst (NaN)."""
    out = []
    for tag in ("declared", "undeclared"):
        rs = [r for r in rows if r.get("declared") == tag]
        if not rs:
            continue

        absrel, absrel_at = _worst(rs, "median_absrel", lambda x: x)
        delta, delta_at = _worst(rs, "median_delta125", lambda x: -x)
        conf, conf_at = _worst(rs, "median_confident", lambda x: -x)
        scale, scale_at = _worst(rs, "median_scale", lambda x: abs(x - 1.0))
        out.append({"declared": tag, "n": len(rs), "absrel": absrel, "absrel_at": absrel_at, "delta125": delta,
                    "delta125_at": delta_at, "confident": conf, "confident_at": conf_at, "scale": scale,
                    "scale_at": scale_at})
    return out


def check_bars(report: dict[str, Any]) -> list[dict[str, Any]]:
    out = []

    def add(name: str, target: str, measured: float, met: bool) -> None:
        out.append({"bar": name, "target": target, "measured": measured, "met": bool(met)})

    times: list[float] = []
    if report.get("sim"):
        s = report["sim"]["depth"][0]
        add("sim known poses: median AbsRel", f"<= {BARS['sim_known_absrel']}", s["median_absrel"],
            s["median_absrel"] <= BARS["sim_known_absrel"])
        add("sim known poses: confident fraction", f">= {BARS['sim_known_confident']}", s["median_confident"],
            s["median_confident"] >= BARS["sim_known_confident"])
        reg = report["sim"]["registration"]
        add("uncalibrated camera within 2 deg / 0.15 m", f">= {BARS['reg_success']}", reg["success_rate"],
            reg["success_rate"] >= BARS["reg_success"])
        pair = report["sim"].get("fixed_pair")
        if pair and pair["trials"]:
            add("second fixed camera from mounting height: median translation error, % of baseline",
                f"<= {100 * BARS['pair_trans_frac']:.0f}", pair["median_trans_pct"],
                pair["median_trans_pct"] <= 100 * BARS["pair_trans_frac"])
        times += [x["seconds"] for name, sc in report["sim"]["depth_frames"].items() if name.startswith("sim robot")
                  for x in sc]
    video_times: list[float] = []
    if report.get("video"):
        for w in worst_rows(report["video"]["depth"]):
            d = w["declared"]
            lim = BARS["video_absrel"] if d == "undeclared" else BARS["video_absrel_declared"]
            add(f"worst recorded sequence, {d}: AbsRel ({w['absrel_at']})", f"<= {lim}", w["absrel"],
                w["absrel"] <= lim)
            if d != "undeclared":
                continue
            add(f"worst recorded sequence, {d}: delta<1.25 ({w['delta125_at']})", f">= {BARS['video_delta125']}",
                w["delta125"], w["delta125"] >= BARS["video_delta125"])
            add(f"worst recorded sequence, {d}: coverage ({w['confident_at']})", f">= {BARS['video_confident']}",
                w["confident"], w["confident"] >= BARS["video_confident"])
            add(f"worst recorded sequence, {d}: scale ({w['scale_at']})", f"1 +- {BARS['video_scale_tol']}",
                w["scale"], abs(w["scale"] - 1.0) <= BARS["video_scale_tol"])
        video_times = [x["seconds"] for sc in report["video"]["depth_frames"].values() for x in sc]
    if video_times:
        med = float(np.median(video_times))
        add("seconds per keyframe, video-rate input (median)", f"<= {BARS['s_per_keyframe_video']}", med,
            med <= BARS["s_per_keyframe_video"])
    if times:
        med = float(np.median(times))
        add("seconds per 640x480 keyframe (median)", f"<= {BARS['s_per_keyframe']}", med, med <= BARS["s_per_keyframe"])
    return out


def run(out_dir: Path | None, quick: bool, families: Sequence[str], seeds: Sequence[int], backend: str,
        sim: bool = True, opts: dict[str, Any] | None = None, video: bool = True, video_sim: bool = True,
        sequences: Sequence[Path] | None = None, stretch: int = 0, long_frames: int = 0) -> dict[str, Any]:
    t0 = time.perf_counter()
    report: dict[str, Any] = {
        "backend": backend, "quick": quick, "families": list(families), "seeds": list(seeds),
        "machine": f"{platform.machine()} python {platform.python_version()}",
        "cpus": os.cpu_count(),
        "load_avg": " ".join(f"{x:.1f}" for x in os.getloadavg()),
    }
    opts = dict(opts or {})
    report["options"] = opts
    report["sim"] = bench_sim(families, seeds, quick, backend, opts) if sim else None
    if video:
        from bench.video import bench_video

        report["video"] = bench_video(backend, quick, opts, seeds if video_sim else [], make_reconstructor,
                                      sequences, stretch, long_frames)
    else:
        report["video"] = None
    report["bars"] = check_bars(report)
    report["wall_s"] = time.perf_counter() - t0
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "geometry.json").write_text(json.dumps(report, indent=1, default=_json_default))
        (out_dir / "geometry.md").write_text(markdown(report))
    return report


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench geometry", description=__doc__.split("\n\n")[0],
        epilog="examples:\n  argus bench geometry --quick --out bench_out/geometry\n"
               "  argus bench geometry --only-video --no-sim --sequence ../shared/data/apc-shelf --out bench_out/g",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=None, help="directory for geometry.json and geometry.md")
    p.add_argument("--quick", action="store_true", help="one seed per family, fewer keyframes and frames")
    p.add_argument("--families", nargs="+", default=["furnished_room", "apartment"], help="sim scene families")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="sim seeds (default 1 2 3; quick: 1)")
    p.add_argument("--backend", default="mvs", help="reconstructor to benchmark (mvs, oracle, mapanything, da3)")
    p.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                   help="backend option (JSON value), e.g. --opt sweep_width=224; repeatable")
    p.add_argument("--sequence", action="append", type=Path, default=None, metavar="DIR",
                   help="a recorded sequence folder (frames/frame-NNNNNN.{color,depth}.png + .pose.txt, "
                   "camera-intrinsics.txt, meta.json; see bench/sequences.py); repeatable. Default: every folder "
                   "of ../shared/data with a meta file")
    p.add_argument("--stretch", type=int, default=0, metavar="N",
                   help="also run every N-frame stretch of each sequence as its own stream, nothing declared")
    p.add_argument("--long-frames", type=int, default=0, metavar="N",
                   help="also play the first sequence back and forth for N frames: memory and s/keyframe over the run")
    p.add_argument("--no-sim", action="store_true", help="skip the simulated scenes")
    p.add_argument("--no-video", action="store_true",
                   help="skip the video-rate scenarios (recorded sequences and the sim at 30 fps)")
    p.add_argument("--only-video", action="store_true", help="run only the video-rate scenarios")
    p.add_argument("--batch-views", nargs="+", type=int, default=None, metavar="N",
                   help="only time the backend: seconds per batch of N real views (e.g. 8 32; bench/modeltiming.py)")
    p.add_argument("--random-weights", default=None, metavar="MODEL",
                   help="with --batch-views and --backend da3: a random-weight model of this size (e.g. da3-base)")
    a = p.parse_args(list(argv) if argv is not None else None)
    seeds = a.seeds or ([1] if a.quick else [1, 2, 3])
    opts = key_values(a.opt, "--opt", p.error)
    if a.batch_views:
        from bench.modeltiming import batch_timing

        timing = batch_timing(a.backend, opts, a.batch_views, a.random_weights)
        if a.out is not None:
            a.out.mkdir(parents=True, exist_ok=True)
            (a.out / "geometry.json").write_text(json.dumps({"batch_timing": timing}, indent=1))
        print(json.dumps(timing, indent=1))
        return 0
    if a.sequence:
        from bench.sequences import SequenceError, load

        for d in a.sequence:  # one clear line for a broken folder, before anything runs
            try:
                load(d, stop=1)
            except SequenceError as e:
                p.error(str(e))
    report = run(a.out, a.quick, a.families, seeds, a.backend, sim=not (a.no_sim or a.only_video), opts=opts,
                 video=not a.no_video, video_sim=not a.no_sim, sequences=a.sequence, stretch=a.stretch,
                 long_frames=a.long_frames)
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
