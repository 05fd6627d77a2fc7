"""``argus bench soak`` pieces that need no stack: the launch it runs, the growth figure and the summary."""

from __future__ import annotations

import pytest

from bench.soak import growth_pct, process_row, resting_mb, sizes_of, soak_launch, summarize


def test_growth_compares_resting_levels_after_the_warm_up() -> None:
    flat_with_spikes = [500.0, 100.0, 100.0, 700.0, 100.0, 100.0, 100.0, 100.0, 650.0, 100.0, 100.0, 100.0]
    assert growth_pct(flat_with_spikes, 1) == pytest.approx(0.0)  # spikes are not a leak
    leak = [100.0 + 10.0 * i for i in range(20)]
    # windows of 3 samples after the warm-up: [150, 160, 170] and [270, 280, 290]; their 10th percentiles
    assert growth_pct(leak, 5) == pytest.approx(100.0 * (272.0 - 152.0) / 152.0)
    assert growth_pct([100.0], 0) is None and growth_pct([100.0, 200.0, 300.0], 3) is None


def test_growth_of_a_process_spiking_in_most_early_samples_is_its_resting_growth() -> None:
    """Regression (soak of 2026-11, planner: 'growth -36.76 %' while it rested at 106 then 119-160 MiB): a median
    of a window where most samples are decision spikes is a spike, so the old figure went negative."""
    early = [700.0, 106.0, 750.0, 108.0, 720.0]  # deciding in 3 of 5 samples
    late = [120.0, 121.0, 600.0, 120.0, 122.0]  # deciding less often, resting 13 % higher
    series = [85.0] * 5 + early + [115.0] * 15 + late
    g = growth_pct(series, 5)
    assert g is not None and g == pytest.approx(100.0 * (resting_mb(late) - resting_mb(early)) / resting_mb(early))
    assert 10.0 < g < 16.0  # the old median-based figure: (121 - 700) / 700 = -83 %


def test_process_row_reports_resting_levels_and_the_peak() -> None:
    series = [50.0, 60.0, 100.0, 400.0, 100.0, 100.0, 110.0, 500.0, 110.0]
    row = process_row("planner", series, 2)
    assert row["rss_start_mb"] == 50.0 and row["rss_last_mb"] == 110.0 and row["rss_peak_mb"] == 500.0
    assert row["rss_rest_after_warmup_mb"] == pytest.approx(100.0)  # [100, 400, 100]: not the spike
    assert row["rss_rest_end_mb"] == pytest.approx(110.0)  # [110, 500, 110]
    assert row["growth_after_warmup_pct"] == pytest.approx(10.0)


def test_sizes_come_from_the_mapper_and_planner_status_only() -> None:
    mapper = {"nodes": 40.0, "keyframes_stored": 64.0, "pointmap_voxels": 1000.0, "frames_in": 9.0}
    others = {"planner/p0": {"graph_nodes": 40.0, "decisions": 3.0}, "robot-agent/robot0": {"graph_nodes": 1.0}}
    assert sizes_of(mapper, others) == {"mapper.nodes": 40.0, "mapper.keyframes_stored": 64.0,
                                        "mapper.pointmap_voxels": 1000.0, "planner.graph_nodes": 40.0}


def test_summarize_gives_per_process_rows_size_rows_drops_and_load() -> None:
    samples = [{"t_s": 10.0 * (i + 1), "rss_mb": {"mapper": 100.0 + i}, "load_avg_1m": 2.0 + i,
                "sizes": {"mapper.nodes": float(min(i, 3))}, "sent": 10 * i, "frames_dropped": float(i)}
               for i in range(8)]
    out = summarize(samples, warmup_min=20.0 / 60.0)  # 2 samples of warm-up
    assert [r["process"] for r in out["processes"]] == ["mapper"]
    assert out["sizes"] == [{"size": "mapper.nodes", "after_warmup": 2.0, "end": 3.0, "max": 3.0}]
    assert out["drops"] == {"frames_dropped": 7.0} and out["frames_offered"] == 70
    assert out["load_avg_1m_mean"] == pytest.approx(5.5) and out["load_avg_1m_max"] == 9.0


def test_soak_launch_is_the_demo_with_an_unbounded_robot_on_the_given_endpoint() -> None:
    launch = soak_launch("tcp/127.0.0.1:7999", max_steps=1234)
    assert launch.endpoint == "tcp/127.0.0.1:7999"
    robots = [p for p in launch.process if p.command == "robot-agent"]
    assert robots and all(p.settings is not None and p.settings["budget"] == {"max_steps": 1234} for p in robots)
    assert {p.command for p in launch.process} >= {"router", "mapper", "planner", "robot-agent", "edge-camera"}
    assert not [p for p in launch.process if p.command == "worker"]


def test_soak_launch_with_workers_adds_them_to_the_demo() -> None:
    launch = soak_launch("tcp/127.0.0.1:7999", max_steps=10, workers=2)
    workers = [p for p in launch.process if p.command == "worker"]
    assert [p.node_id for p in workers] == ["w0", "w1"]
    assert all(p.settings is not None and p.settings["zenoh"] == {"mode": "client", "connect": ["tcp/127.0.0.1:7999"]}
               and p.settings["site"] == launch.site for p in workers)
    mapper = next(p for p in launch.process if p.command == "mapper")
    # the demo itself: the workers take its geometry, the ORACLE masks stay in the mapper
    assert mapper.settings is not None and mapper.settings["perception"]["segmenter"] == "sim"
    assert mapper.settings["geometry"]["backend"] == "mvs"
