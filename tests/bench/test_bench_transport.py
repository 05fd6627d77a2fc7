"""``argus bench transport``: delivered frames/s and loss reported apart, with a raw-Zenoh baseline row."""

from __future__ import annotations

import time

import pytest

from bench.transport import _drive, _Receipts, run, table_rows


def test_lost_frames_do_not_dilute_the_delivered_rate() -> None:
    """Issue 38: 299 of 300 frames at 30 Hz read as 14.9 fps, the wait for the lost one counted in the rate."""
    got = _Receipts(frames=20)

    def put(seq: int) -> None:
        if seq != 7:  # one frame lost on the way
            now = time.time_ns()
            got.add(seq, now, now + 1_000_000, 100)

    fig = _drive(put, got, frames=20, rate_hz=100.0, loss_wait_s=1.0)
    assert fig["frames_received"] == 19 and fig["frames_lost"] == 1
    assert fig["loss_fraction"] == pytest.approx(0.05)
    assert 60 < fig["frames_per_s"] < 120, fig  # ~100 Hz over the delivery window, not 19 / 1.2 s
    assert fig["latency_ms_p50"] == pytest.approx(1.0)


@pytest.mark.integration
def test_a_run_has_the_argus_row_and_the_raw_zenoh_baseline_row() -> None:
    results = {"rate_50": run(frames=15, width=160, height=120, quality=80, rate_hz=50.0, endpoint=None,
                              loss_wait_s=3.0)}
    rows = table_rows(results)
    assert [r["path"] for r in rows] == ["argus", "raw_zenoh"]
    for r in rows:
        assert r["frames_received"] + r["frames_lost"] == 15 and r["frames_per_s"] > 0, r
