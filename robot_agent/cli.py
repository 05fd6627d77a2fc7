"""``argus robot-agent``: one robot on Zenoh (frames with odometry, goals, state, viewpoints).

Example::

    argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
    argus robot-agent --body kinematic --id robot1 --time-scale 10
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.tomlconfig import ConfigError, describe, load_config

EPILOG = """examples:
  argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
  argus robot-agent --config robot_agent/examples/sim.toml --time-scale 20 --set body.oracle=true
  argus robot-agent --body kinematic --id robot1          # no simulator: a dry-run base
  argus robot-agent --describe                            # every config field, every body type

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Bad goals never end it."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus robot-agent",
        description="Run one robot: publish frames with odometry, state and viewpoints; drive to NBV goals.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", type=Path, default=None, help="TOML config file (see robot_agent/examples/)")
    p.add_argument("--id", default=None, help="robot id")
    p.add_argument("--site", default=None, help="Argus site name")
    p.add_argument("--connect", action="append", default=None, help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--mode", choices=["client", "peer"], default=None, help="Zenoh mode (default client)")
    p.add_argument("--body", default=None, help="body type: sim, kinematic")
    p.add_argument("--time-scale", type=float, default=None, help="robot seconds per wall second")
    p.add_argument("--frame-rate", type=float, default=None, help="frames per second while moving")
    p.add_argument("--budget-m", type=float, default=None, help="exploration budget in metres")
    p.add_argument("--budget-steps", type=int, default=None, help="exploration budget in goals reached")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override any config field, e.g. --set body.seed=3 (repeatable)")
    p.add_argument("--describe", action="store_true", help="print every config field and exit")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def describe_all() -> str:
    from robot_agent.bodies import available, backend_module
    from robot_agent.config import RobotAgentConfig

    lines = ["argus robot-agent configuration (TOML):", ""]
    lines += [ln for ln in describe(RobotAgentConfig) if not ln.startswith("body ")]
    for name in sorted(available()):
        try:
            cls = backend_module(name).Config
        except Exception as e:  # noqa: BLE001 - a broken plug-in must not hide the others
            lines += ["", f"[body] type = {name!r}: unavailable ({e})"]
            continue
        lines += ["", f"[body] type = {name!r}"]
        lines += [f"  {ln}" for ln in describe(cls, prefix="body.") if not ln.startswith("body.type ")]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if a.describe:
        print(describe_all())
        return 0
    from protocol.runtime import setup_logging
    from robot_agent.bodies.base import BodyConfigError
    from robot_agent.config import RobotAgentConfig

    values = {
        "id": a.id,
        "site": a.site,
        "zenoh.connect": a.connect,
        "zenoh.mode": a.mode,
        "body.type": a.body,
        "motion.time_scale": a.time_scale,
        "frames.moving_rate_hz": a.frame_rate,
        "budget.max_distance_m": a.budget_m,
        "budget.max_steps": a.budget_steps,
        "log_level": a.log_level,
    }
    try:
        config = load_config(RobotAgentConfig, a.config, values, a.overrides)
    except ConfigError as e:
        print(f"argus robot-agent: {e}", file=sys.stderr)
        return 2
    setup_logging(f"robot-agent[{config.id}]", config.log_level)
    from robot_agent.node import run

    try:
        return run(config)
    except BodyConfigError as e:
        print(f"argus robot-agent: configuration error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
