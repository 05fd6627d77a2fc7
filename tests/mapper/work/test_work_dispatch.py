"""The dispatcher's state machine (mapper/work/dispatch.py): exact transitions, no Zenoh."""

from __future__ import annotations

from mapper.work.dispatch import DispatchConfig, Dispatcher, Outcome, State


def make(**kw: float) -> Dispatcher:
    """A dispatcher with no frame-age deadline unless one is given (the times below are arbitrary)."""
    d = Dispatcher(DispatchConfig(**{"max_frame_age_s": 0.0, **kw}))  # type: ignore[arg-type]
    return d


def test_assigns_to_the_least_loaded_live_worker() -> None:
    d = make(max_in_flight=2)
    d.worker_up("w1")
    d.worker_up("w2")
    for i in range(5):
        assert d.submit(f"cam{i}#0", f"cam{i}", now=float(i))
    sent = d.assign(now=10.0)
    # oldest first, alternating between the two workers, two each, the fifth waits
    assert sent == [("cam0#0", "w1", 1), ("cam1#0", "w2", 1), ("cam2#0", "w1", 1), ("cam3#0", "w2", 1)]
    assert d.jobs["cam4#0"].state is State.PENDING
    assert d.result("cam1#0", "w2", now=11.0) is Outcome.ACCEPTED
    assert d.assign(now=11.0) == [("cam4#0", "w2", 1)]


def test_job_lost_with_its_worker_is_reissued_to_another() -> None:
    d = make()
    d.worker_up("w1")
    d.submit("cam#1", "cam", now=0.0)
    assert d.assign(now=0.0) == [("cam#1", "w1", 1)]
    assert d.ack("cam#1", "w1", 1, now=0.1)
    d.worker_up("w2")
    assert d.worker_down("w1", now=0.5) == ["cam#1"]
    assert d.counters["jobs_reissued_worker_lost"] == 1
    assert d.assign(now=0.5) == [("cam#1", "w2", 2)]
    # a late result of the dead worker's attempt still counts once, the live worker's then is a duplicate
    assert d.result("cam#1", "w1", now=0.6) is Outcome.ACCEPTED
    assert d.result("cam#1", "w2", now=0.7) is Outcome.DUPLICATE
    assert d.counters["results_duplicate"] == 1
    assert d.workers["w2"].in_flight == set()


def test_duplicate_results_and_submits_are_ignored() -> None:
    d = make()
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    d.assign(0.0)
    assert d.result("a#1", "w", 1.0) is Outcome.ACCEPTED
    assert d.result("a#1", "w", 1.1) is Outcome.DUPLICATE
    assert not d.submit("a#1", "a", 2.0)  # the same keyframe again: idempotent
    assert d.result("nope#3", "w", 1.2) is Outcome.UNKNOWN
    assert d.workers["w"].done == 1


def test_no_ack_within_the_timeout_reissues() -> None:
    d = make(ack_timeout_s=2.0, result_timeout_s=5.0)
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    d.assign(0.0)
    assert d.expire(2.0) == []  # not yet late
    assert d.expire(2.01) == ["a#1"]
    assert d.counters["jobs_reissued_no_ack"] == 1
    d.assign(3.0)
    assert d.ack("a#1", "w", 2, 3.5)
    assert not d.ack("a#1", "w", 1, 3.6)  # a stale ack of the first attempt
    assert d.expire(8.4) == []
    assert d.expire(8.6) == ["a#1"]  # acked, but no result within result_timeout_s
    assert d.counters["jobs_reissued_late"] == 1


def test_given_up_after_max_attempts() -> None:
    d = make(max_attempts=2, ack_timeout_s=1.0)
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    d.assign(0.0)
    d.expire(2.0)
    d.assign(2.0)
    assert d.expire(4.0) == []
    assert "a#1" not in d.jobs
    assert d.take_dropped() == [("a#1", "given_up")]
    assert d.take_dropped() == []


def test_garbage_results_are_rejected_and_the_worker_quarantined_after_n() -> None:
    d = make(quarantine_after=2, max_in_flight=2, max_attempts=5)
    d.worker_up("bad")
    d.worker_up("good")
    for i in range(2):
        d.submit(f"s{i}#0", f"s{i}", float(i))
    sent = dict((j, w) for j, w, _ in d.assign(5.0))
    bad_job = next(j for j, w in sent.items() if w == "bad")
    assert d.result(bad_job, "bad", 6.0, problem="result_not_finite") is Outcome.REJECTED
    assert d.jobs[bad_job].state is State.PENDING  # re-issued
    assert not d.workers["bad"].quarantined
    assert d.assign(6.0) == [(bad_job, "bad", 2)]  # "bad" has fewest in flight (0 vs 1)
    d.submit("s9#0", "s9", 6.5)
    assert d.assign(6.5) == [("s9#0", "bad", 1)]
    assert d.result(bad_job, "bad", 7.0, problem="result_bad_shape") is Outcome.REJECTED
    assert d.workers["bad"].quarantined
    assert d.counters["workers_quarantined"] == 1 and d.counters["results_rejected"] == 2
    assert d.live_workers() == ["good"]
    # its other job went back to pending too, and only "good" gets work now
    assert d.jobs["s9#0"].state is State.PENDING
    assert {w for _, w, _ in d.assign(7.0)} == {"good"}
    # a restarted process (its token goes and comes back) is trusted again
    d.worker_down("bad", 8.0)
    d.worker_up("bad")
    assert "bad" in d.live_workers()


def test_freshest_pending_frame_per_source_and_bounded() -> None:
    d = make(max_jobs=3)
    assert d.submit("cam#1", "cam", 0.0)
    assert d.submit("cam#2", "cam", 0.1)  # no worker yet: #1 was pending, superseded
    assert d.take_dropped() == [("cam#1", "superseded")]
    d.submit("r#1", "r", 0.2)
    d.submit("q#1", "q", 0.3)
    assert not d.submit("z#1", "z", 0.4)
    assert d.take_dropped() == [("z#1", "full")]
    assert d.counters["jobs_dropped_superseded"] == 1 and d.counters["jobs_dropped_full"] == 1
    # an assigned job is not superseded (its worker is already on it)
    d.worker_up("w")
    d.assign(1.0)
    assert d.submit("cam#3", "cam", 1.1) is False  # still full: 3 jobs in flight
    d.result("cam#2", "w", 1.2)
    assert d.submit("cam#3", "cam", 1.3)
    assert "r#1" in d.jobs and d.take_dropped() == [("cam#3", "full")]


def test_orphans_without_live_workers_are_handed_back() -> None:
    d = make()
    d.submit("a#1", "a", 0.0)
    assert d.orphans() == ["a#1"]
    assert d.jobs == {}
    d.worker_up("w")
    d.submit("b#1", "b", 1.0)
    assert d.orphans() == []
    d.assign(1.0)
    assert d.worker_down("w", 2.0) == ["b#1"]
    assert d.orphans() == ["b#1"]
    assert d.counters["jobs_done_locally"] == 2


def test_the_worker_table_is_bounded() -> None:
    d = Dispatcher(DispatchConfig(max_workers=2))
    for w in ("a", "b", "c"):
        d.worker_up(w)
    assert d.live_workers() == ["a", "b"] and d.counters["workers_refused"] == 1
    d.worker_down("a", 0.0)
    d.worker_up("c")
    assert d.live_workers() == ["b", "c"]


def test_a_job_whose_frame_is_too_old_is_dropped_but_a_started_one_is_not() -> None:
    d = make(max_frame_age_s=2.0, max_in_flight=1, ack_timeout_s=1.0)
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    d.submit("b#1", "b", 0.5, age_s=0.3)  # its frame reached the mapper at 0.2
    d.submit("c#1", "c", 0.6, fresh=False, age_s=0.8)  # an older keyframe retried: it ages from its frame
    assert d.assign(0.6) == [("a#1", "w", 1)]
    assert d.expire(1.7) == ["a#1"]  # no ack within 1 s: re-issued (pending again, started once)
    assert d.take_dropped() == [] and "c#1" in d.jobs  # c#1's frame is 1.9 s old: not yet
    assert d.expire(1.85) == [] and d.take_dropped() == [("c#1", "stale")]  # 2.05 s
    assert "b#1" in d.jobs  # 1.65 s
    assert d.expire(2.25) == [] and d.take_dropped() == [("b#1", "stale")]  # 2.05 s
    assert d.expire(10.0) == [] and set(d.jobs) == {"a#1"}  # started once: kept (the graph has no gap)
    assert d.counters["jobs_dropped_stale"] == 2


def test_a_job_already_too_old_when_submitted_is_dropped_as_stale() -> None:
    """A deferred keyframe retried long after its capture never becomes a job: its source's fresher keyframes
    are mapped instead (before: retried keyframes were never dropped for age and came out seconds late)."""
    d = make(max_frame_age_s=1.5)
    d.worker_up("w")
    assert not d.submit("a#3", "a", 10.0, fresh=False, age_s=1.6)
    assert d.take_dropped() == [("a#3", "stale")] and d.jobs == {}
    assert d.counters["jobs_dropped_stale"] == 1
    assert d.submit("a#9", "a", 10.0, age_s=0.1)  # fresh enough
    assert d.assign(10.0) == [("a#9", "w", 1)]


def test_a_slot_that_frees_takes_the_least_recently_served_source() -> None:
    """Fair order: the source whose last job went out longest ago is served first, even when another source's
    pending keyframe is older (before: oldest submission first, so a source whose keyframes came at the right
    moments was served again and again)."""
    d = make(max_in_flight=1)
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    assert d.assign(0.0) == [("a#1", "w", 1)]  # a served at 0.0
    d.submit("b#1", "b", 0.1)
    assert d.result("a#1", "w", 0.2) is Outcome.ACCEPTED
    assert d.assign(0.2) == [("b#1", "w", 1)]  # b served at 0.2
    d.submit("a#2", "a", 0.3)  # a's older pending keyframe...
    d.submit("b#2", "b", 0.5)
    d.submit("c#1", "c", 0.7)  # ...and a source never served
    assert d.result("b#1", "w", 0.8) is Outcome.ACCEPTED
    assert d.assign(0.8) == [("c#1", "w", 1)]  # never served first, though its frame is the newest
    assert d.result("c#1", "w", 0.9) is Outcome.ACCEPTED
    assert d.assign(0.9) == [("a#2", "w", 1)]  # a (served at 0.0) before b (at 0.2)


def test_each_source_is_served_with_its_freshest_keyframe() -> None:
    """A source with a retried older keyframe and a fresh one pending: the fresh one goes first."""
    d = make(max_in_flight=1)
    d.worker_up("w")
    d.submit("a#7", "a", 1.0)  # the fresh keyframe
    d.submit("a#3", "a", 1.1, fresh=False)  # an older one, deferred and retried
    assert d.assign(1.2) == [("a#7", "w", 1)]
    d.submit("b#1", "b", 1.3)
    assert d.result("a#7", "w", 1.4) is Outcome.ACCEPTED
    assert d.assign(1.4) == [("b#1", "w", 1)]  # a was just served: b first


def test_equally_loaded_workers_keep_each_source_on_its_last_worker() -> None:
    """Source affinity: a source's next job goes where its last one went when that worker is among the least
    loaded (its cached features and depth of the source's keyframes are reused); never onto a busier worker."""
    d = make(max_in_flight=2)
    d.worker_up("w1")
    d.worker_up("w2")
    d.submit("a#0", "a", now=0.0)
    d.submit("b#0", "b", now=0.1)
    assert d.assign(now=1.0) == [("a#0", "w1", 1), ("b#0", "w2", 1)]
    for job, w in (("a#0", "w1"), ("b#0", "w2")):
        assert d.result(job, w, now=2.0) is Outcome.ACCEPTED
    # Both idle: b goes back to w2 although w1 comes first by id (without affinity: w1, then a to w2).
    d.submit("b#1", "b", now=3.0)
    d.submit("a#1", "a", now=3.1)
    assert d.assign(now=3.5) == [("b#1", "w2", 1), ("a#1", "w1", 1)]
    assert d.counters["jobs_assigned_same_worker"] == 2
    # Load beats affinity.
    d.submit("c#0", "c", now=4.0)
    assert d.assign(now=4.0) == [("c#0", "w1", 1)]  # a new source: the least loaded (w1 and w2 both have 1: w1)
    d.submit("b#2", "b", now=4.5)
    assert d.assign(now=4.5) == [("b#2", "w2", 1)]  # w2 has 1 in flight, w1 has 2: b stays on w2
    d.submit("b#3", "b", now=5.0)
    assert d.assign(now=5.0) == []  # both full: it waits, not piled onto its worker
    assert d.result("a#1", "w1", now=5.1) is Outcome.ACCEPTED
    # w1 has room, b's worker w2 is full: b's job is held for w2 a little (affinity_hold_s)...
    assert d.assign(now=5.2) == [] and d.counters["jobs_held_for_affinity"] == 1
    # ... then given to the worker with room.
    assert d.assign(now=5.6) == [("b#3", "w1", 1)]
    assert d._affinity["b"] == "w1"


def test_a_job_is_not_held_for_a_worker_that_went_away() -> None:
    d = make(max_in_flight=1)
    d.worker_up("w1")
    d.worker_up("w2")
    d.submit("a#0", "a", now=0.0)
    d.submit("b#0", "b", now=0.0)
    assert d.assign(now=0.0) == [("a#0", "w1", 1), ("b#0", "w2", 1)]
    assert d.result("a#0", "w1", now=0.1) is Outcome.ACCEPTED
    d.submit("b#1", "b", now=0.2)
    assert d.assign(now=0.2) == []  # held for w2 (full)
    d.worker_down("w2", now=0.3)  # b#0 re-issued, b#1 no longer held: w2 is gone
    assert sorted(d.assign(now=0.3)) == [("b#0", "w1", 2)]
    assert d.result("b#0", "w1", now=0.4) is Outcome.ACCEPTED
    assert d.assign(now=0.4) == [("b#1", "w1", 1)]


def test_affinity_memory_is_bounded() -> None:
    d = Dispatcher(DispatchConfig(max_sources=3))
    d.worker_up("w1")
    for i in range(10):
        d.submit(f"s{i}#0", f"s{i}", now=float(i))
        d.assign(now=float(i))
        d.result(f"s{i}#0", "w1", now=float(i))
    assert len(d._affinity) == 3


def test_without_fair_order_the_job_submitted_first_goes_first() -> None:
    d = make(max_in_flight=1, fair=False)
    d.worker_up("w")
    d.submit("a#1", "a", 0.0)
    assert d.assign(0.0) == [("a#1", "w", 1)]
    d.submit("a#2", "a", 0.3)
    d.submit("c#1", "c", 0.7)
    assert d.result("a#1", "w", 0.8) is Outcome.ACCEPTED
    assert d.assign(0.8) == [("a#2", "w", 1)]  # fair: c#1 (never served)


def test_an_arrival_view_is_never_shed_under_load() -> None:
    """A kept job (FrameHeader.map_always: a robot's arrival view) is never stale nor superseded, goes before the
    other new jobs, and a full table sheds the least informative job for it: the one of the source served most
    recently."""
    d = make(max_frame_age_s=1.5, max_jobs=4, max_in_flight=1)
    d.worker_up("w")
    d.submit("cam#1", "cam", 0.0)
    assert d.assign(0.0) == [("cam#1", "w", 1)]  # cam served at 0.0
    assert d.ack("cam#1", "w", 1, 0.05)
    assert d.submit("r1#5", "r1", 0.1, age_s=0.2, keep=True)  # the robot arrived
    assert d.submit("r1#6", "r1", 0.2)  # a later frame of the robot does not supersede its arrival view
    assert "r1#5" in d.jobs and d.take_dropped() == []
    assert d.submit("cam#2", "cam", 0.3)
    assert not d.submit("q#1", "q", 0.4)  # full, and q#1 is no kept job: refused
    assert d.submit("r2#9", "r2", 0.5, keep=True)  # full: cam#2 gives way (cam was served most recently)
    assert d.take_dropped() == [("q#1", "full"), ("cam#2", "shed")] and d.counters["jobs_dropped_shed"] == 1
    assert d.expire(5.0) == [] and "r1#5" in d.jobs and "r2#9" in d.jobs  # never stale...
    assert ("r1#6", "stale") in d.take_dropped()  # ...while the robot's video-rate frame is
    assert d.result("cam#1", "w", 5.1) is Outcome.ACCEPTED
    assert d.assign(5.1) == [("r1#5", "w", 1)]  # kept jobs first, oldest first
    assert d.counters["jobs_kept"] == 2
