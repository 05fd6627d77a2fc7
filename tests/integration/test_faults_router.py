"""Fault: the router is SIGKILLed and restarted on the same endpoint. Every process reconnects by
itself and frames, deltas, status and goals flow again; the time per process is printed."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.codec import DecodeError, decode
from protocol.messages import Status
from tests.support.boxes import EYES
from tests.support.mapper_peer import SITE, Consumer, mapper_args
from tests.support.procs import Proc, endpoint, free_port, wait_for, wait_port
from tests.support.robot import kinematic_config


class StatusTimes:
    """When each process's Status was last seen, and its newest counters."""

    def __init__(self, consumer: Consumer) -> None:
        self.lock = threading.Lock()
        self.seen: dict[str, float] = {}
        self.counters: dict[str, dict[str, float]] = {}
        self.sub = consumer.session.declare_subscriber(consumer.keys.all_status, self._on)

    def _on(self, sample) -> None:  # noqa: ANN001
        try:
            st = decode(sample.payload.to_bytes(), Status)
        except DecodeError:
            return
        with self.lock:
            self.seen[st.role] = time.monotonic()
            self.counters[st.role] = dict(st.counters)

    def since(self, role: str, t: float) -> bool:
        with self.lock:
            return self.seen.get(role, 0.0) > t

    def get(self, role: str, name: str) -> float:
        with self.lock:
            return self.counters.get(role, {}).get(name, 0.0)


@pytest.mark.slow
def test_every_process_reconnects_after_the_router_is_killed(tmp_path: Path, procs: list[Proc]) -> None:
    port = free_port()
    ep = endpoint(port)
    router = Proc(["router", "--listen", ep])
    procs.append(router)
    wait_port(port)
    fast = ["--set", "status_period_s=0.2"]
    procs.append(Proc(mapper_args(ep, tmp_path / "state")))
    procs.append(Proc(["planner", "--connect", ep, "--site", SITE, "--strategy", "see", *fast]))
    robot_cfg = kinematic_config(tmp_path / "robot.toml", ep)
    procs.append(Proc(["robot-agent", "--config", str(robot_cfg), "--site", SITE, *fast]))
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"{i}.jpg"), np.full((48, 64, 3), 80 * i, np.uint8))
    cam_cfg = tmp_path / "cam.toml"
    cam_cfg.write_text(f'id = "cam_f"\nsite = "{SITE}"\nstatus_period_s = 0.2\n[source]\ntype = "folder"\n'
                       f'path = "{folder}"\nrate_hz = 2.0\nloop = true\n[zenoh]\nconnect = ["{ep}"]\n')
    procs.append(Proc(["edge-camera", "--config", str(cam_cfg)]))
    consumer = Consumer(ep)
    times = StatusTimes(consumer)
    roles = ("mapper", "planner", "robot-agent", "edge-camera")
    try:
        wait_for(lambda: all(times.since(r, 0.0) for r in roles), timeout=90, what="every process up")
        consumer.send(EYES[0], 0)
        wait_for(lambda: len(consumer.deltas) >= 1, timeout=30, what="a delta before the fault")
        wait_for(lambda: times.get("robot-agent", "goals_received") >= 1, timeout=30, what="a goal before the fault")

        router.signal(signal.SIGKILL)
        router.wait(10)
        time.sleep(1.0)
        router2 = Proc(["router", "--listen", ep])
        procs.append(router2)
        wait_port(port)
        t0 = time.monotonic()
        goals0 = times.get("robot-agent", "goals_received")
        frames0 = times.get("mapper", "frames_in")
        recovered: dict[str, float] = {}
        deadline = t0 + 60
        while time.monotonic() < deadline and len(recovered) < len(roles):
            for r in roles:
                if r not in recovered and times.since(r, t0):
                    recovered[r] = time.monotonic() - t0
            time.sleep(0.05)
        assert set(recovered) == set(roles), f"no status after the restart from {set(roles) - set(recovered)}"
        n = len(consumer.deltas)
        consumer.send(EYES[1], 1)  # frames flow to the mapper and deltas back to a consumer
        wait_for(lambda: len(consumer.deltas) > n, timeout=30, what="a delta after the restart")
        delta_s = time.monotonic() - t0
        wait_for(lambda: times.get("mapper", "frames_in") >= frames0 + 4, timeout=30,
                 what="the camera's and robot's frames reaching the mapper again")
        wait_for(lambda: times.get("robot-agent", "goals_received") > goals0, timeout=60,
                 what="a goal reaching the robot after the restart")
        goal_s = time.monotonic() - t0
        print("\n[fault router] status again after restart: "
              + ", ".join(f"{r} {s:.1f} s" for r, s in recovered.items())
              + f"; frame->delta round trip by {delta_s:.1f} s; planner->robot goal by {goal_s:.1f} s")
    finally:
        times.sub.undeclare()
        consumer.close()
