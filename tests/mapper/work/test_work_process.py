"""``argus mapper`` with a real ``argus worker`` process on loopback: keyframes go to the worker and come back
into the graph; the worker killed mid-run loses no keyframe (its jobs are re-issued or done by the mapper).

RGB-only geometry (mvs) and classical perception on 160x120 simulator frames: jobs carry no ORACLE samples.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest

from bench.scaling import child_pids, process_running
from bench.system import render_cameras
from protocol.codec import DecodeError, decode
from protocol.keys import Keys
from protocol.messages import FrameHeader, GraphDelta, Status
from protocol.session import ZenohSettings, open_session
from protocol.transport import declare_frame_publisher, put_frame
from tests.support.procs import Proc, wait_for

SITE = "worktest"
pytestmark = pytest.mark.slow  # two model-loading processes and a dozen RGB keyframes: ~30 s


class Peer:
    """Publishes one simulated robot's frames; collects deltas and the mapper's and worker's status."""

    def __init__(self, endpoint: str) -> None:
        self.keys = Keys(SITE)
        self.session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        self.status: dict[str, dict[str, float]] = {}
        self.deltas: list[GraphDelta] = []
        self.lock = threading.Lock()
        self.subs = [self.session.declare_subscriber(self.keys.all_status, self._on_status),
                     self.session.declare_subscriber(self.keys.graph_delta, self._on_delta)]
        self.pub = declare_frame_publisher(self.session, self.keys.robot_frame("r1"))
        self.cam = render_cameras(1, 14, 160, 120, "apartment", 0)[0]

    def _on_status(self, sample: Any) -> None:
        try:
            st = decode(sample.payload.to_bytes(), Status)
        except DecodeError:
            return
        with self.lock:
            self.status[st.role] = dict(st.counters)

    def _on_delta(self, sample: Any) -> None:
        with self.lock:
            self.deltas.append(decode(sample.payload.to_bytes(), GraphDelta))

    def counter(self, role: str, name: str) -> float:
        with self.lock:
            return self.status.get(role, {}).get(name, 0.0)

    def send(self, k: int) -> None:
        c = self.cam
        header = FrameHeader(source_id="r1", source_kind="robot", seq=k, stamp_ns=1_000_000 + k, width=160,
                             height=120, intrinsics=c.intrinsics, T_world_cam=c.poses[k])
        put_frame(self.pub, header, c.jpegs[k])

    def settled(self) -> bool:
        """Every keyframe given to workers came back, was done by the mapper or was dropped (one status)."""
        with self.lock:
            st = dict(self.status.get("mapper", {}))
        done = sum(st.get(k, 0.0) for k in ("work_results_accepted", "work_jobs_done_locally", "keyframes_dropped"))
        out = st.get("jobs_in_flight", 0.0) + st.get("jobs_pending", 0.0)
        return st.get("keyframes_offloaded", 0.0) == done and out == 0

    def send_and_settle(self, k: int, timeout: float = 60.0) -> None:
        """Send frame ``k`` and wait until the mapper processed it and no job is out."""
        n = self.counter("mapper", "frames_processed")
        self.send(k)
        wait_for(lambda: self.counter("mapper", "frames_processed") > n, timeout, what=f"frame {k} processed")
        wait_for(self.settled, timeout, what=f"frame {k}'s job back")

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


def test_worker_does_keyframes_and_its_death_loses_none(router: str, procs: list[Proc]) -> None:
    common = ["--connect", router, "--site", SITE, "--set", "status_period_s=0.2", "--set", "torch_threads=1"]
    # No job deadline: frames are sent one at a time, a deferred keyframe's retry may come > 1.5 s after it
    mapper = Proc(["mapper", *common, "--set", "publish.snapshot_period_s=0", "--set", "workers.max_frame_age_s=0"])
    worker = Proc(["worker", *common, "--id", "w1"])
    procs += [mapper, worker]
    peer = Peer(router)
    try:
        wait_for(lambda: peer.counter("mapper", "workers_alive") == 1, 90,
                 what=f"the mapper seeing the worker\n{mapper.output}\n{worker.output}")
        for k in range(7):
            peer.send_and_settle(k)
        offloaded = peer.counter("mapper", "keyframes_offloaded")
        accepted = peer.counter("mapper", "work_results_accepted")
        assert offloaded >= 3 and accepted == offloaded, f"{peer.status}\n{mapper.output}"
        wait_for(lambda: peer.counter("worker", "jobs_done") >= accepted, 5, what="the worker's status")
        assert peer.counter("mapper", "keyframe_store_queries") >= 1  # the worker fetched source keyframes
        assert peer.counter("worker", "image_cache_hits") >= 1  # and reused them
        assert peer.counter("mapper", "nodes") >= 1, "keyframes done by the worker reached the graph"
        # Killed with a job in its hands: the job is re-issued (no other worker: done by the mapper itself).
        taken, done = peer.counter("worker", "jobs_in"), peer.counter("worker", "jobs_done")
        peer.send(7)
        wait_for(lambda: peer.counter("worker", "jobs_in") > taken, 30, what="frame 7's job taken")
        assert peer.counter("worker", "jobs_done") == done, "the job was done before the kill: make it slower"
        t_kill = time.monotonic()
        worker.signal(signal.SIGKILL)
        wait_for(lambda: peer.counter("mapper", "workers_alive") == 0, 20, what="worker gone")
        # its liveliness token goes with its link: the mapper knows within a status period or two, not a timeout
        assert time.monotonic() - t_kill < 3.0
        for k in range(8, 11):
            peer.send_and_settle(k)
        wait_for(peer.settled, 30, what="no job left out")
        assert peer.counter("mapper", "work_jobs_reissued_worker_lost") == 1
        assert peer.counter("mapper", "work_jobs_done_locally") >= 1
        offloaded = peer.counter("mapper", "keyframes_offloaded")
        done = peer.counter("mapper", "work_results_accepted") + peer.counter("mapper", "work_jobs_done_locally")
        assert done == offloaded, f"offloaded {offloaded}, done {done}\n{mapper.output}"
        assert peer.counter("mapper", "keyframes_dropped") == 0
        assert peer.counter("mapper", "keyframes") > offloaded  # later keyframes were done in-process
        versions = [d.version for d in peer.deltas]
        assert versions == sorted(versions) and len(set(versions)) == len(versions)
        assert mapper.alive(), mapper.output
        assert np.isfinite(peer.counter("mapper", "update_s_mean"))
    finally:
        peer.close()


def test_local_worker_does_keyframes_restarts_and_dies_with_its_mapper(router: str, procs: list[Proc]) -> None:
    common = ["--connect", router, "--site", SITE, "--set", "status_period_s=0.2", "--set", "torch_threads=1"]
    mapper = Proc(["mapper", *common, "--set", "publish.snapshot_period_s=0", "--set", "workers.local=1"])
    procs.append(mapper)
    peer = Peer(router)
    try:
        wait_for(lambda: peer.counter("mapper", "workers_alive") == 1, 90,
                 what=f"the mapper seeing its local worker\n{mapper.output}")
        assert peer.counter("mapper", "local_workers_alive") == 1
        for k in range(5):
            peer.send_and_settle(k)
        offloaded = peer.counter("mapper", "keyframes_offloaded")
        accepted = peer.counter("mapper", "work_results_accepted")
        # a deferred keyframe retried once its frame is over the job deadline is dropped as stale: by design
        assert accepted >= 2 and accepted + peer.counter("mapper", "keyframes_dropped") == offloaded, peer.status
        assert peer.counter("mapper", "worker_jobs_done.mapper-local0") == accepted
        assert peer.counter("mapper", "nodes") >= 1, "keyframes done by the local worker reached the graph"
        (child,) = child_pids(mapper.popen.pid)
        os.kill(child, signal.SIGKILL)
        wait_for(lambda: peer.counter("mapper", "local_worker_restarts") >= 1, 30, what="the child started again")
        wait_for(lambda: peer.counter("mapper", "workers_alive") == 1, 90, what=f"its token again\n{mapper.output}")
        (again,) = child_pids(mapper.popen.pid)
        assert again != child and peer.counter("mapper", "local_worker_exits") == 1
        os.kill(mapper.popen.pid, signal.SIGKILL)  # the mapper alone, not its process group
        wait_for(lambda: not process_running(again), 20, what="the local worker stopping with its mapper")
    finally:
        peer.close()
