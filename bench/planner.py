"""``argus bench planner``: planner decision time for many candidates and completions.

A synthetic 3-room apartment (planner.synthetic: point map of the observed living room, a few graph
nodes, a viewpoint lattice cut to exactly ``--candidates`` viewpoints) is planned on repeatedly with
each strategy; the decision time (one ``Planner.plan`` call: panoramas, sampling, placement, view
prediction, gain) is reported with its percentiles. Bar: <= 2 s for 300 candidates and 8 completions.

Example::

    argus bench planner --candidates 300 --completions 8 --repeats 10 --out bench_out/planner
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from planner.config import Strategy

BAR_S = 2.0


def scenario(n_candidates: int, seed: int = 0) -> dict[str, Any]:
    """Synthetic world with exactly ``n_candidates`` viewpoints (lattice subsampled evenly)."""
    from planner import synthetic as S

    w = S.apartment(seed)
    name = S.room_namer(w["rooms"])
    vset = S.grid_viewpoints("r1", (0.3, 0.3), (9.7, 8.7), spacing_m=0.4, room_of=name)
    vps = [v for v in vset.viewpoints if v.room]
    if len(vps) < n_candidates:
        raise ValueError(f"the synthetic world has only {len(vps)} viewpoints")
    idx = np.linspace(0, len(vps) - 1, n_candidates).round().astype(int)
    vset = vset.model_copy(
        update={"viewpoints": [vps[i].model_copy(update={"vp_id": k}) for k, i in enumerate(idx)]}
    )
    pts = w["points"]
    observed = (pts[:, 0] < 6) & (pts[:, 1] < 5)
    pm = S.point_map(pts[observed], 0.05, counts=2.0)
    nodes = [n for n in w["nodes"] if n.centroid[0] < 6 and n.centroid[1] < 5]
    return {
        "snapshot": S.snapshot(nodes),
        "point_map": pm,
        "viewpoints": vset,
        "state": S.robot_state("r1", 3.0, 2.5, 0.0),
    }


def run_bench(
    candidates: int = 300,
    completions: int = 8,
    repeats: int = 10,
    strategies: tuple[Strategy, ...] = ("see", "asp"),
    threads: int = 1,
) -> dict[str, Any]:
    """Decision-time statistics per strategy (seconds)."""
    from planner.config import AspConfig, PlannerConfig
    from planner.core import Planner

    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:
        pass
    sc = scenario(candidates)
    out: dict[str, Any] = {
        "candidates": candidates,
        "completions": completions,
        "repeats": repeats,
        "map_points": int(sc["point_map"].points.shape[0]),
        "bar_s": BAR_S,
        "strategies": {},
    }
    for strategy in strategies:
        times, hyps, frontier = [], [], []
        for r in range(repeats):
            planner = Planner(
                PlannerConfig(strategy=strategy, seed=r, asp=AspConfig(n_completions=completions))
            )
            t0 = time.perf_counter()
            planner.plan(sc["snapshot"], sc["point_map"], {"r1": (sc["state"], sc["viewpoints"])})
            times.append(time.perf_counter() - t0)
            hyps.append(planner.info.n_hypotheses)
            frontier.append(planner.info.n_frontier)
        t = np.array(times)
        out["strategies"][strategy] = {
            "mean_s": float(t.mean()),
            "p50_s": float(np.percentile(t, 50)),
            "p95_s": float(np.percentile(t, 95)),
            "max_s": float(t.max()),
            "hypotheses_mean": float(np.mean(hyps)),
            "frontier_points_mean": float(np.mean(frontier)),
            "meets_bar": bool(np.percentile(t, 95) <= BAR_S),
        }
    return out


def markdown(res: dict[str, Any]) -> str:
    rows = [
        f"Planner decision time: {res['candidates']} candidates, {res['completions']} completions, "
        f"{res['map_points']} map points, {res['repeats']} repeats (bar {res['bar_s']:.1f} s)",
        "",
        "| strategy | mean s | p50 s | p95 s | max s | hypotheses | frontier pts | bar |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in res["strategies"].items():
        rows.append(
            f"| {name} | {s['mean_s']:.3f} | {s['p50_s']:.3f} | {s['p95_s']:.3f} | {s['max_s']:.3f} | "
            f"{s['hypotheses_mean']:.0f} | {s['frontier_points_mean']:.0f} | "
            f"{'ok' if s['meets_bar'] else 'MISS'} |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench planner",
        description="Planner decision time for many candidate viewpoints and completions.",
        epilog="example:\n  argus bench planner --candidates 300 --completions 8 --out bench_out/planner",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--candidates", type=int, default=300, help="candidate viewpoints")
    p.add_argument("--completions", type=int, default=8, help="completions K (asp)")
    p.add_argument("--repeats", type=int, default=10, help="decisions timed per strategy")
    p.add_argument("--strategy", nargs="+", default=["see", "asp"], choices=["see", "asp"], help="strategies")
    p.add_argument("--threads", type=int, default=1, help="torch threads (numpy BLAS is not limited here)")
    p.add_argument("--quick", action="store_true", help="3 repeats")
    p.add_argument("--out", type=Path, default=None, help="directory for planner.json and planner.md")
    a = p.parse_args(argv)
    res = run_bench(a.candidates, a.completions, 3 if a.quick else a.repeats, tuple(a.strategy), a.threads)
    md = markdown(res)
    print(md)
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "planner.json").write_text(json.dumps(res, indent=1))
        (a.out / "planner.md").write_text(md + "\n")
    return 0 if all(s["meets_bar"] for s in res["strategies"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
