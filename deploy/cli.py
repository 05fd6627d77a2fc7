"""The ``argus`` command line: one entry point, one sub-command per process or tool.

Sub-commands live in their own packages and are imported only when run, so ``argus --help`` is
fast and an edge device never imports the mapper's dependencies. Third-party packages add
commands through the entry-point group ``argus.commands`` (name -> module with ``main(argv)``).
"""

from __future__ import annotations

import importlib
import sys
from importlib.metadata import entry_points

# name -> (module with main(argv) -> int, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("deploy.router", "run a Zenoh router (the rendezvous point of an Argus site)"),
    "edge-camera": ("edge_camera.cli", "stream one fixed camera's JPEG frames"),
    "robot-agent": ("robot_agent.cli", "run one robot: frames with odometry, goals, state"),
    "mapper": ("mapper.cli", "build and serve the 3D scene graph from all frames"),
    "worker": ("mapper.work.cli", "do the mapper's heavy per-keyframe work (geometry, perception) on any machine"),
    "planner": ("planner.cli", "send each robot its next-best view"),
    "up": ("deploy.up", "start a whole stack from a launch file"),
    "demo": ("deploy.demo", "run the full demo on the embedded simulated world"),
    "query": ("deploy.query", "query or watch the scene graph as a consumer"),
    "goal": ("deploy.goal", "send one goal to a robot and print its answer"),
    "explore": ("bench.explore", "closed-loop exploration run in the simulator, per-step JSON"),
    "sim": ("sim.cli", "the embedded world: generate, export, load, render, view scenes"),
    "bench": ("bench.cli", "performance and quality benchmarks (JSON + Markdown)"),
    "eval": ("bench.eval", "reproduce the paper's experiments on simulated scenes"),
}

USAGE = """usage: argus <command> [options]   (argus <command> --help for its manual)

Argus builds and serves a live 3D scene graph of an indoor space from RGB cameras, over Zenoh.

commands:
{commands}

quick start:
  argus router --listen tcp/127.0.0.1:7447      # one per site
  argus demo                                    # everything, on the simulated world
"""


def _all_commands() -> dict[str, tuple[str, str]]:
    cmds = dict(COMMANDS)
    for ep in entry_points(group="argus.commands"):
        cmds.setdefault(ep.name, (ep.value, "(plug-in)"))
    return cmds


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    cmds = _all_commands()
    if not args or args[0] in ("-h", "--help", "help"):
        width = max(len(n) for n in cmds)
        listing = "\n".join(f"  {n.ljust(width)}  {h}" for n, (_, h) in cmds.items())
        print(USAGE.format(commands=listing))
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in cmds:
        print(f"argus: unknown command {name!r} (see argus --help)", file=sys.stderr)
        return 2
    module_name = cmds[name][0]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        print(f"argus {name}: not available in this install ({e}); the server extra may be missing:"
              " pip install 'argus-scenegraph[server]'", file=sys.stderr)
        return 3
    result = module.main(rest)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
