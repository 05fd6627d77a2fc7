"""``argus robot-agent``: one robot on Zenoh (frames with odometry, goals, state, viewpoints).

Example::

    argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
    argus robot-agent --body kinematic --id robot1 --time-scale 10
"""

from __future__ import annotations

import argparse
import sys

from protocol.session import ZenohConfigError
from protocol.tomlconfig import Flag, ProcessCommand

EPILOG = """examples:
  argus robot-agent --config robot_agent/examples/sim.toml --connect tcp/127.0.0.1:7447
  argus robot-agent --config robot_agent/examples/sim.toml --time-scale 20 --set body.oracle=true
  argus robot-agent --body kinematic --id robot1          # no simulator: a dry-run base
  argus robot-agent --describe                            # every config field, every body type

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Bad goals never end it."""


COMMAND = ProcessCommand(
    "robot-agent", "Run one robot: publish frames with odometry, state and viewpoints; drive to NBV goals.",
    EPILOG, what="robot", config_help="TOML config file (see robot_agent/examples/)", set_example="body.seed=3",
    node_module="robot_agent.node",
    flags=(
        Flag("--body", "body.type", "body type: sim, kinematic"),
        Flag("--time-scale", "motion.time_scale", "robot seconds per wall second", float),
        Flag("--frame-rate", "frames.moving_rate_hz", "frames per second while moving", float),
        Flag("--budget-m", "budget.max_distance_m", "exploration budget in metres", float),
        Flag("--budget-steps", "budget.max_steps", "exploration budget in goals reached", int),
    ),
)


def parser() -> argparse.ArgumentParser:
    return COMMAND.parser()


def describe_all() -> str:
    from robot_agent.bodies import REGISTRY
    from robot_agent.config import RobotAgentConfig

    return COMMAND.describe(RobotAgentConfig, REGISTRY)


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    from robot_agent.bodies.base import BodyConfigError
    from robot_agent.config import RobotAgentConfig

    return COMMAND.start(a, RobotAgentConfig, describe_all, config_errors=(BodyConfigError, ZenohConfigError))


if __name__ == "__main__":
    sys.exit(main())
