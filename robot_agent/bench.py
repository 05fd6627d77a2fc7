"""Robot agent costs: per-frame capture + encode + put, and a fast-simulation exploration run.

* ``frame``: the agent's own ``publish_frame`` (body capture, JPEG, put) over a real loopback Zenoh
  link (two in-process peers), at 640x480 by default, for each body given.
* ``explore``: a whole agent (``RobotAgent.run``, the same loop as ``argus robot-agent``) in the
  simulated world with a fast time scale, driven through ``--steps`` goals to random reachable
  viewpoints; reports the wall time per step (drive + arrival frame + state).

Example::

    python -m robot_agent.bench --frames 30 --bodies kinematic,sim --explore-steps 30 --out bench_out/robot.json
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from protocol.messages import NbvGoal
from protocol.node import Node
from protocol.session import ZenohSettings, open_session
from robot_agent.bodies import parse_body_config
from robot_agent.config import FramesConfig, MotionConfig, RobotAgentConfig
from robot_agent.node import ROLE, RobotAgent


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _body(name: str, width: int, height: int, oracle: bool) -> dict[str, Any]:
    if name == "kinematic":
        return {"type": "kinematic", "width": width, "height": height}
    if name == "sim":
        return {"type": "sim", "family": "apartment", "seed": 0, "width": width, "height": height, "oracle": oracle,
                "speed_mps": 1.0}
    raise SystemExit(f"unknown body {name!r} (kinematic, sim)")


def bench_frames(body: str, n: int, width: int, height: int, oracle: bool) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{_free_port()}"
    cfg = RobotAgentConfig(id="bench", site="bench", body=parse_body_config(_body(body, width, height, oracle)),
                           zenoh=ZenohSettings(mode="peer", connect=[], listen=[ep]))
    agent = RobotAgent(cfg)
    received = [0]

    def on_frame(_sample: Any) -> None:
        received[0] += 1

    node = Node(cfg.zenoh, agent.keys, ROLE, cfg.id, stop=threading.Event())
    with node, open_session(ZenohSettings(mode="peer", connect=[ep])) as sub_s:
        sub = sub_s.declare_subscriber(agent.keys.robot_frame("bench"), on_frame)
        time.sleep(0.5)  # let the subscription reach the publisher (a benchmark, not a test)
        agent.declare_publishers(node)
        rows = [agent.publish_frame() for _ in range(n + 2)][2:]
        deadline = time.monotonic() + 5
        while received[0] < n + 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        sub.undeclare()
    cap, enc, put = (list(col) for col in zip(*[r for r in rows if r is not None], strict=True))
    total = [a + b + c for a, b, c in zip(cap, enc, put, strict=True)]
    return {
        "body": body + (" +oracle" if oracle else ""),
        "size": f"{width}x{height}",
        "frames": n,
        "capture_ms": statistics.fmean(cap),
        "encode_ms": statistics.fmean(enc),
        "put_ms": statistics.fmean(put),
        "total_ms_p50": sorted(total)[len(total) // 2],
        "total_ms_mean": statistics.fmean(total),
        "received": received[0],
    }


def bench_explore(steps: int, width: int, height: int, time_scale: float, seed: int = 0) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{_free_port()}"
    cfg = RobotAgentConfig(
        id="bench", site="bench", body=parse_body_config(_body("sim", width, height, oracle=True)),
        frames=FramesConfig(moving_rate_hz=0.0), motion=MotionConfig(time_scale=time_scale, tick_hz=50.0),
        zenoh=ZenohSettings(mode="peer", connect=[], listen=[ep]),
    )
    t0 = time.perf_counter()
    agent = RobotAgent(cfg)
    startup_s = time.perf_counter() - t0
    stop = threading.Event()
    thread = threading.Thread(target=agent.run, args=(stop,), daemon=True)
    thread.start()
    rng = np.random.default_rng(seed)
    vps = agent.viewpoint_set.viewpoints
    step_s: list[float] = []
    try:
        deadline = time.monotonic() + 30
        while agent.status != "idle" and time.monotonic() < deadline:
            time.sleep(0.01)
        for k in range(steps):
            cost = agent._travel_cost
            ok = [v for v in vps if cost is None or np.isfinite(cost[v.vp_id])]
            v = ok[int(rng.integers(len(ok)))]
            t = time.perf_counter()
            agent.mailbox.put(NbvGoal(goal_id=f"b{k}", robot_id="bench", stamp_ns=time.time_ns(), x=v.x, y=v.y,
                                      yaw_rad=v.yaw_rad, vp_id=v.vp_id))
            deadline = time.monotonic() + 120
            while not (agent.goal_id == f"b{k}" and agent.status in ("arrived", "refused", "failed")):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"step {k} did not finish")
                time.sleep(0.002)
            step_s.append(time.perf_counter() - t)
    finally:
        stop.set()
        thread.join(timeout=10)
    return {
        "steps": steps,
        "size": f"{width}x{height}",
        "time_scale": time_scale,
        "startup_s": startup_s,
        "wall_s": sum(step_s),
        "step_s_mean": statistics.fmean(step_s),
        "distance_m": agent.body.distance_m(),
        "arrivals": int(agent.counters.get("arrivals")),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench robot",
        description="Robot agent per-frame cost and fast-simulation exploration time.",
        epilog="example: argus bench robot --frames 30 --bodies kinematic,sim --explore-steps 30",
    )
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--bodies", default="kinematic,sim", help="comma list of kinematic, sim")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--oracle", action="store_true", help="sim body also packs ORACLE ids + depth per frame")
    p.add_argument("--explore-steps", type=int, default=0, help="run a fast-sim exploration of this many goals")
    p.add_argument("--time-scale", type=float, default=50.0)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--quick", action="store_true", help="at most 5 frames per source (smoke run)")
    a = p.parse_args(argv)
    if a.quick:
        a.frames = min(a.frames, 5)
    import cv2

    cv2.setNumThreads(1)
    frames = [bench_frames(b.strip(), a.frames, a.width, a.height, a.oracle and b.strip() == "sim")
              for b in a.bodies.split(",") if b.strip()]
    print("| body | size | capture ms | encode ms | put ms | total ms (p50) |")
    print("|---|---|---|---|---|---|")
    for r in frames:
        print(f"| {r['body']} | {r['size']} | {r['capture_ms']:.2f} | {r['encode_ms']:.2f} | {r['put_ms']:.2f} | "
              f"{r['total_ms_p50']:.2f} |")
    result: dict[str, Any] = {"frames": frames}
    if a.explore_steps > 0:
        ex = bench_explore(a.explore_steps, a.width, a.height, a.time_scale)
        result["explore"] = ex
        print(f"\nexplore: {ex['steps']} steps, {ex['distance_m']:.1f} m, {ex['wall_s']:.1f} s wall "
              f"({ex['step_s_mean']:.2f} s/step at time_scale {ex['time_scale']:g}, {ex['size']}); "
              f"startup {ex['startup_s']:.1f} s")
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"robot_agent": result}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
