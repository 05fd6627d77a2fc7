"""``argus bench planner``: the synthetic case and its closed-loop-sized variant."""

from __future__ import annotations

import numpy as np

from bench.planner import CLOSED_LOOP, markdown, run_bench, scenario


def test_scenario_sizes() -> None:
    living = scenario(40)
    whole = scenario(40, history=5, observed="all")
    assert len(living["viewpoints"].viewpoints) == 40 and living["history"] == []
    assert whole["point_map"].points.shape[0] > living["point_map"].points.shape[0]
    assert len(whole["snapshot"].nodes) > len(living["snapshot"].nodes)
    xy = {(v.x, v.y) for v in whole["viewpoints"].viewpoints}
    assert len(whole["history"]) == 5
    assert all((round(T[0, 3], 9), round(T[1, 3], 9)) in {(round(x, 9), round(y, 9)) for x, y in xy}
               for T in whole["history"])
    assert CLOSED_LOOP.candidates >= 896 and CLOSED_LOOP.bar_s == 1.0
    stereo = scenario(40, observed="stereo")
    assert 0 < stereo["point_map"].points.shape[0] < whole["point_map"].points.shape[0]
    assert stereo["point_map"].points[:, 1].max() < 5.0


def test_run_bench_reports_wall_and_cpu() -> None:
    res = run_bench(candidates=40, completions=2, repeats=2, strategies=("see",), history=3, observed="all",
                    bar_s=1.0)
    s = res["strategies"]["see"]
    assert res["history"] == 3 and res["bar_s"] == 1.0
    assert 0 < s["p50_s"] <= s["max_s"] and s["cpu_mean_s"] > 0 and np.isfinite(s["cpu_p95_s"])
    assert "CPU mean s" in markdown(res) and "3 remembered views" in markdown(res)
