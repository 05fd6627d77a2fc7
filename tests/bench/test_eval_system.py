"""``argus bench system`` helpers: /proc sampling (no psutil) and a short real run (slow)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from bench.system import _pct, delta_latency_ms, drops_by_reason, proc_cpu_s, proc_mem_mb
from protocol.messages import GraphDelta
from tests.support.messages import node_msg


def test_proc_cpu_counts_this_process_work() -> None:
    pid = os.getpid()
    before = proc_cpu_s(pid)
    t0 = time.process_time()
    x = 0
    while time.process_time() - t0 < 0.3:  # burn a measurable amount of CPU
        x += 1
    after = proc_cpu_s(pid)
    assert 0.15 <= after - before <= 2.0


def test_proc_memory_reports_rss_and_peak() -> None:
    mem = proc_mem_mb(os.getpid())
    assert 10 < mem["rss_mb"] <= mem["peak_rss_mb"] < 64_000
    with pytest.raises(FileNotFoundError):
        proc_mem_mb(2**22 + 12345)  # beyond pid_max: no such process


def test_percentiles() -> None:
    assert _pct([], 50) is None
    assert _pct([1.0, 2.0, 3.0], 50) == 2.0


def test_delta_latency_is_from_the_capture_of_the_keyframe_that_made_it() -> None:
    # Maintenance re-sends a node last seen 100 s ago in the delta of a keyframe captured 0.4 s ago: 400 ms,
    # not 100 s (the node's age).
    now = 1_000_000_000_000
    old = node_msg("n000001").model_copy(update={"last_seen_ns": now - 100_000_000_000})
    delta = GraphDelta(version=2, stamp_ns=now - 400_000_000, upserted=[old])
    assert delta_latency_ms(delta, now) == pytest.approx(400.0)
    assert delta_latency_ms(delta.model_copy(update={"upserted": []}), now) is None  # no node changed
    assert delta_latency_ms(delta.model_copy(update={"stamp_ns": 0}), now) is None


def test_drops_per_reason_are_summed_over_sources_for_the_phase() -> None:
    s0 = {"keyframes_dropped.stale.a": 2.0, "keyframes_dropped.superseded.a": 1.0, "keyframes_dropped": 3.0}
    s1 = {"keyframes_dropped.stale.a": 5.0, "keyframes_dropped.stale.b": 1.0, "keyframes_dropped.superseded.a": 1.0,
          "keyframes_dropped.full.c.d": 4.0, "keyframes_dropped": 11.0}
    assert drops_by_reason(s0, s1) == {"dropped.superseded": 0.0, "dropped.stale": 4.0, "dropped.full": 4.0,
                                       "dropped.shed": 0.0, "dropped.given_up": 0.0}


@pytest.mark.slow
@pytest.mark.integration
def test_system_bench_quick(tmp_path: Path) -> None:
    from bench.system import main

    assert main(["--quick", "--cameras", "1", "--consumers", "0,2", "--geometry", "oracle", "--segmenter", "sim",
                 "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "system.json").read_text())
    phases = res["phases"]
    assert [p["consumers"] for p in phases] == [0, 2]
    assert all(p["offered_fps"] > 1 and p["received_fps"] > 0 and p["mapper_peak_rss_mb"] > 50 for p in phases)
    assert phases[1]["queries"] > 0 and phases[1]["query_p50_ms"] is not None
    assert any(p["latency_p50_ms"] is not None for p in phases)
    assert "| consumers |" in (tmp_path / "system.md").read_text()


@pytest.mark.slow
@pytest.mark.integration
def test_system_bench_scaling_with_workers(tmp_path: Path) -> None:
    from bench.system import main

    assert main(["--quick", "--cameras", "1", "--consumers", "0", "--workers", "0,1", "--width", "160", "--height",
                 "120", "--torch-threads", "1", "--out", str(tmp_path)]) == 0
    res = json.loads((tmp_path / "system.json").read_text())
    phases = res["phases"]
    assert [p["workers"] for p in phases] == [0, 1]
    alone, helped = phases
    assert alone["mapper_status"].get("keyframes_offloaded", 0) == 0 and alone["workers_cpu_cores"] == 0
    assert helped["mapper_status"]["work_results_accepted"] > 0 and helped["workers_cpu_cores"] > 0
    assert helped["worker_job_s"] > 0 and helped["bytes_per_job"] > 1000 and helped["job_roundtrip_s"] > 0
    assert alone["worker_job_s"] is None and alone["bytes_per_job"] is None
    assert all(p["keyframes_done_per_s"] > 0 for p in phases)
    assert "| workers |" in (tmp_path / "system.md").read_text()
    # The scaling model: CPU-seconds per keyframe per role, and predictions from the worker phase.
    assert alone["cpu_s_per_kf.mapper_main"] > 0 and "model_curve" not in alone
    assert helped["cpu_s_per_job.worker.w0"] > 0 and helped["cpu_s_per_kf.router"] >= 0
    assert 0 < helped["model_c_s"] < helped["model_w_s"] + helped["model_c_s"]
    assert [r["workers"] for r in helped["model_curve"]][:3] == [0, 1, 2] and helped["model_kf_per_s_here"] > 0
    assert "## Scaling model" in (tmp_path / "system.md").read_text()


def test_rendered_frames_are_kept_and_reused(tmp_path: Path) -> None:
    from bench.system import cached_cameras

    first = cached_cameras(tmp_path, 1, 2, 64, 48, "apartment", 0, False)
    (kept,) = list(tmp_path.iterdir())
    again = cached_cameras(tmp_path, 1, 2, 64, 48, "apartment", 0, False)
    assert again[0].jpegs == first[0].jpegs and again[0].source_id == "simcam0"
    kept.write_bytes(b"")  # proof the second call read the file: an empty one cannot be unpickled
    with pytest.raises(EOFError):
        cached_cameras(tmp_path, 1, 2, 64, 48, "apartment", 0, False)
    assert len(cached_cameras(None, 1, 2, 64, 48, "apartment", 0, False)[0].jpegs) == 2
