"""The scaling model of ``argus bench system --workers`` (bench/scaling.py): per-role CPU from /proc and the
predictions, exact on hand-made numbers."""

from __future__ import annotations

import os
import threading
import time

import pytest

from bench.scaling import ChildClock, RoleClock, curve, model_inputs, predict, role_costs, thread_cpu_s, workers_cpu_s


def test_thread_cpu_splits_main_thread_from_the_others() -> None:
    burned, release = threading.Event(), threading.Event()

    def burn() -> None:
        t0 = time.thread_time()
        x = 0
        while time.thread_time() - t0 < 0.3:
            x += 1
        burned.set()
        release.wait(10)  # alive while sampled: a thread that ended is no longer in /proc/<pid>/task

    before = thread_cpu_s(os.getpid())
    main0 = time.thread_time()
    t = threading.Thread(target=burn)
    t.start()
    assert burned.wait(30)
    after = thread_cpu_s(os.getpid())
    main_spent = time.thread_time() - main0
    release.set()
    t.join()
    assert after["threads"] - before["threads"] >= 0.2  # the burning thread is not the main one
    assert after["main"] - before["main"] <= main_spent + 0.05


def test_role_costs_per_keyframe_and_per_job() -> None:
    cpu0 = {"mapper_main": 10.0, "mapper_threads": 1.0, "router": 0.5, "cameras": 2.0, "worker.w0": 5.0,
            "worker.w1": 0.0}
    cpu1 = {"mapper_main": 14.0, "mapper_threads": 2.0, "router": 0.9, "cameras": 2.4, "worker.w0": 13.0,
            "worker.w1": 6.0}
    c = role_costs(cpu0, cpu1, keyframes_done=40.0, jobs_by_worker={"w0": 20.0, "w1": 15.0})
    assert c["cpu_s_per_kf.mapper_main"] == pytest.approx(0.1)
    assert c["cpu_s_per_kf.mapper_threads"] == pytest.approx(0.025)
    assert c["cpu_s_per_job.worker.w0"] == pytest.approx(0.4) and c["cpu_s_per_job.worker.w1"] == pytest.approx(0.4)
    assert c["cpu_s_per_kf.workers"] == pytest.approx(14.0 / 40.0)
    assert c["cpu_s_per_kf.all"] == pytest.approx((4.0 + 1.0 + 0.4 + 0.4 + 8.0 + 6.0) / 40.0)
    inputs = model_inputs(c, n_workers=2)
    assert inputs == pytest.approx({"c": 0.1, "o": 0.025 + 0.01 + 0.01, "w": 0.4})
    assert model_inputs(c, n_workers=0) is None
    none = role_costs(cpu0, cpu1, keyframes_done=0.0, jobs_by_worker={})
    assert none["cpu_s_per_kf.mapper_main"] is None and none["cpu_s_per_job.worker.w0"] is None


def test_predictions() -> None:
    # 2 cores here; a worker 0.4 s per job, the mapper's thread 0.05 s, the rest 0.05 s per keyframe.
    p1 = predict(0.05, 0.05, 0.4, 1, cores=2)
    assert p1["shared"] == pytest.approx(2.5) and p1["separate"] == pytest.approx(2.5)
    p2 = predict(0.05, 0.05, 0.4, 2, cores=2)
    assert p2["separate"] == pytest.approx(5.0)
    assert p2["shared"] == pytest.approx(2 / 0.5)  # 2 cores / (c + o + w) = 4.0: 1.6x one worker, not 2x
    # Many machines: the mapper's single thread is the ceiling, then its cores, then the link.
    assert predict(0.05, 0.05, 0.4, 64, cores=2)["separate"] == pytest.approx(min(1 / 0.05, 2 / 0.1))
    assert predict(0.05, 0.05, 0.4, 64, cores=2, bytes_per_job=2e7)["separate"] == pytest.approx(125e6 / 2e7)
    assert predict(0.05, 0.05, 0.4, 2, cores=2, offered=3.0)["separate"] == 3.0
    assert predict(0.05, 0.05, 0.4, 0, cores=2)["shared"] == pytest.approx(1 / 0.45)
    rows = curve({"c": 0.05, "o": 0.05, "w": 0.4}, 2, None, None, counts=(1, 2))
    assert [r["workers"] for r in rows] == [1, 2]
    assert rows[1]["model_kf_per_s_this_machine"] == pytest.approx(4.0)


def test_role_clock_samples_live_processes() -> None:
    s = RoleClock(os.getpid(), None, {"w0": os.getpid()}).sample()
    assert set(s) == {"mapper_main", "mapper_threads", "cameras", "worker.w0"}
    assert s["worker.w0"] >= s["mapper_main"] > 0
    assert RoleClock(os.getpid(), 2**22 + 12345, {}).sample()["router"] == 0.0  # a process that ended


def test_child_clock_finds_children_when_they_exist_and_keeps_the_cpu_of_those_that_ended(
        monkeypatch: pytest.MonkeyPatch) -> None:
    live: list[int] = []
    cpu = {101: 1.0, 202: 0.5, 303: 9.0}
    lines = {101: "python -m mapper.work.local", 202: "python -m mapper.work.local", 303: "python -c tracker"}
    clock = ChildClock(1, "local", None, children=lambda parent: list(live), cpu=cpu.get)
    assert clock.sample() == {}  # the mapper has not started its worker yet
    live.append(101)
    assert clock.sample() == {"local0": 1.0}
    cpu[101] = 2.5
    assert clock.sample() == {"local0": 2.5}
    live.remove(101)  # it ended (and was restarted as 202)
    live.append(202)
    assert clock.sample() == {"local0": 2.5, "local1": 0.5}
    from bench import scaling

    monkeypatch.setattr(scaling, "cmdline", lines.get)
    only = ChildClock(1, "w", "mapper.work.local", children=lambda parent: [101, 303], cpu=cpu.get)
    assert only.sample() == {"w0": 2.5}  # not the child that is no worker


def test_the_mappers_local_worker_started_after_the_clock_is_in_the_workers_cpu() -> None:
    """Issue 41: bench system looked the local worker up once, before the mapper had started it: workers_cpu_cores
    read 0 and cpu_s_per_kf.workers / .all left it out. This process plays the mapper; its child, started after the
    clock, runs as ``mapper.work.local`` (argv[0]) and spins."""
    import subprocess
    import time
    from types import SimpleNamespace

    from bench.system import role_clock

    clock = role_clock(SimpleNamespace(children=[]), os.getpid())
    s0 = clock.sample()
    assert not [k for k in s0 if k.startswith("worker.")]
    child = subprocess.Popen(["bash", "-c", "exec -a mapper.work.local bash -c 'while :; do :; done'"])
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and "worker.mapper-local0" not in (s1 := clock.sample()):
            time.sleep(0.05)
        while time.monotonic() < deadline and s1.get("worker.mapper-local0", 0.0) < 0.05:
            time.sleep(0.05)
            s1 = clock.sample()
    finally:
        child.kill()
        child.wait()
    assert s1["worker.mapper-local0"] >= 0.05
    costs = role_costs(s0, s1, 1.0, {})
    assert costs["cpu_s_per_kf.workers"] == pytest.approx(s1["worker.mapper-local0"])
    assert costs["cpu_s_per_kf.all"] >= s1["worker.mapper-local0"]  # type: ignore[operator]
    assert workers_cpu_s(s0, s1) == pytest.approx(s1["worker.mapper-local0"])
    assert clock.sample()["worker.mapper-local0"] >= s1["worker.mapper-local0"]  # ended: its CPU kept, not 0


def test_job_profile_is_cpu_per_job_by_stage_over_all_workers() -> None:
    from bench.system import job_profile

    before = {"w1": {"jobs_done": 10.0, "cpu_s.geometry.sweep": 2.0, "cpu_s.decode": 0.5}}
    after = {"w1": {"jobs_done": 12.0, "cpu_s.geometry.sweep": 2.6, "cpu_s.decode": 0.54, "frames_in": 9.0},
             "w2": {"jobs_done": 2.0, "cpu_s.geometry.sweep": 0.6, "cpu_s.perception": 0.2}}  # first seen now
    prof = job_profile(before, after)
    assert list(prof) == ["geometry.sweep", "perception", "decode", "total"]  # the costliest first
    assert prof["geometry.sweep"] == pytest.approx(0.3) and prof["perception"] == pytest.approx(0.05)
    assert prof["decode"] == pytest.approx(0.01) and prof["total"] == pytest.approx(0.36)
    assert job_profile(before, before) == {}


def test_the_headline_is_cpu_per_keyframe_and_the_cameras_one_core_carries() -> None:
    from bench.system import cameras_per_core, headline

    assert cameras_per_core(0.5, 2.0, 2) == pytest.approx(2.0)  # each camera: 1 keyframe/s x 0.5 s
    assert cameras_per_core(None, 2.0, 2) is None and cameras_per_core(0.5, 0.0, 2) is None
    phases = [{"consumers": 0, "cpu_s_per_kf.all": 0.5, "keyframes_per_s": 2.0, "latency_p50_ms": 900.0,
               "latency_p99_ms": 1600.0, "load_avg_1m": 1.1, "job_cpu_s": {"geometry.sweep": 0.3, "total": 0.3}},
              {"consumers": 1, "cpu_s_per_kf.all": None}]
    text = "\n".join(headline(phases, 2, 2.0))
    assert "**0.500 CPU-s per keyframe**" in text and "p50 0.90 s, p99 1.60 s" in text
    assert "one core carries 2.00 such cameras (2 fps, 1.00 keyframes/s each)" in text
    assert "1 consumers: no keyframe done" in text and "| geometry.sweep | 0.3 | 100 % |" in text
