"""``argus bench soak`` pieces that need no stack: the launch it runs and the growth figure."""

from __future__ import annotations

import pytest

from bench.soak import growth_pct, soak_launch


def test_growth_is_median_based_after_the_warm_up() -> None:
    flat_with_spikes = [500.0, 100.0, 100.0, 700.0, 100.0, 100.0, 100.0, 100.0, 650.0, 100.0, 100.0, 100.0]
    assert growth_pct(flat_with_spikes, 1) == pytest.approx(0.0)  # spikes are not a leak
    leak = [100.0 + 10.0 * i for i in range(20)]
    assert growth_pct(leak, 5) == pytest.approx(100.0 * (280.0 - 160.0) / 160.0)  # windows of 3 samples
    assert growth_pct([100.0], 0) is None and growth_pct([100.0, 200.0, 300.0], 3) is None


def test_soak_launch_is_the_demo_with_an_unbounded_robot_on_the_given_endpoint() -> None:
    launch = soak_launch("tcp/127.0.0.1:7999", max_steps=1234)
    assert launch.endpoint == "tcp/127.0.0.1:7999"
    robots = [p for p in launch.process if p.command == "robot-agent"]
    assert robots and all(p.settings is not None and p.settings["budget"] == {"max_steps": 1234} for p in robots)
    assert {p.command for p in launch.process} >= {"router", "mapper", "planner", "robot-agent", "edge-camera"}
