"""``argus robot-agent``: one robot on Zenoh (frames with odometry, goals, state, viewpoints).

Example::

    argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
    argus robot-agent --body kinematic --id robot1 --time-scale 10
"""

from __future__ import annotations

import argparse
import sys

from protocol.session import ZenohConfigError
from protocol.tomlconfig import ConfigError, describe, load_config, process_parser, process_values

EPILOG = """examples:
  argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
  argus robot-agent --config robot_agent/examples/sim.toml --time-scale 20 --set body.oracle=true
  argus robot-agent --body kinematic --id robot1          # no simulator: a dry-run base
  argus robot-agent --describe                            # every config field, every body type

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Bad goals never end it."""


def parser() -> argparse.ArgumentParser:
    p = process_parser(
        "argus robot-agent",
        "Run one robot: publish frames with odometry, state and viewpoints; drive to NBV goals.",
        EPILOG, what="robot", config_help="TOML config file (see robot_agent/examples/)",
        set_example="body.seed=3",
    )
    p.add_argument("--body", default=None, help="body type: sim, kinematic")
    p.add_argument("--time-scale", type=float, default=None, help="robot seconds per wall second")
    p.add_argument("--frame-rate", type=float, default=None, help="frames per second while moving")
    p.add_argument("--budget-m", type=float, default=None, help="exploration budget in metres")
    p.add_argument("--budget-steps", type=int, default=None, help="exploration budget in goals reached")
    return p


def describe_all() -> str:
    from robot_agent.bodies import REGISTRY
    from robot_agent.config import RobotAgentConfig

    lines = ["argus robot-agent configuration (TOML):", ""]
    lines += [ln for ln in describe(RobotAgentConfig) if not ln.startswith("body ")]
    return "\n".join(lines + REGISTRY.describe(describe))


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if a.describe:
        print(describe_all())
        return 0
    from protocol.runtime import setup_logging
    from robot_agent.bodies.base import BodyConfigError
    from robot_agent.config import RobotAgentConfig

    values = {
        **process_values(a),
        "body.type": a.body,
        "motion.time_scale": a.time_scale,
        "frames.moving_rate_hz": a.frame_rate,
        "budget.max_distance_m": a.budget_m,
        "budget.max_steps": a.budget_steps,
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
    except (BodyConfigError, ZenohConfigError) as e:
        print(f"argus robot-agent: configuration error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
