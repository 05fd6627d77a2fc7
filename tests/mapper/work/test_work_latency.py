"""Stage times of keyframes (mapper/work/latency.py): exact percentiles, bounded memory."""

from __future__ import annotations

import math

from mapper.work.latency import StageTimes


def test_stage_percentiles_and_counts() -> None:
    st = StageTimes(keep=100)
    for i in range(1, 101):
        st.add("job_roundtrip", i / 100.0)
    st.age("age_at_commit", stamp_ns=1_000_000_000, now_ns=3_500_000_000)
    st.age("age_at_commit", stamp_ns=0, now_ns=3_500_000_000)  # unstamped: not recorded
    st.add("job_roundtrip", math.nan)  # ignored
    c = st.counters()
    assert c["kf_s.job_roundtrip.p50"] == 0.505 and c["kf_s.job_roundtrip.max"] == 1.0
    assert c["kf_s.job_roundtrip.p99"] == 0.9901 and c["kf_s.job_roundtrip.n"] == 100
    assert c["kf_s.age_at_commit.p50"] == 2.5 and c["kf_s.age_at_commit.n"] == 1


def test_values_and_stages_are_bounded() -> None:
    st = StageTimes(keep=3, max_stages=2)
    for v in (10.0, 1.0, 2.0, 3.0):
        st.add("a", v)
    st.add("b", 1.0)
    st.add("c", 1.0)  # a third stage: not kept
    c = st.counters()
    assert c["kf_s.a.max"] == 3.0 and c["kf_s.a.n"] == 4  # 10.0 fell out of the last 3
    assert "kf_s.c.n" not in c and "kf_s.b.n" in c
