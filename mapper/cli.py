"""``argus mapper``: build and serve the 3D scene graph from every camera and robot frame.

Example::

    argus mapper --connect tcp/127.0.0.1:7447 --state-dir /var/lib/argus/mapper
    argus mapper --geometry oracle --segmenter sim --embedder sim    # ORACLE inputs (simulated frames only)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.tomlconfig import Flag, ProcessCommand, describe

EPILOG = """examples:
  argus mapper --connect tcp/127.0.0.1:7447 --state-dir ./mapper_state
  argus mapper --config mapper.toml --set fusion.voxel_m=0.025
  argus mapper --geometry oracle --segmenter sim --embedder sim   # ORACLE geometry + 2D perception (sim only)
  argus mapper --rerun map.rrd                                    # also record a Rerun file
  argus mapper --rerun-web 9090      # headless server: web viewer on http://127.0.0.1:9090 (ssh -L 9090:127.0.0.1:9090)
  argus mapper --describe                                         # every config field

Backends: geometry mvs (default, RGB only) | oracle (sim truth) | mapanything (optional extra);
segmenter classical (default) | sim (ORACLE) | sam (optional extra); embedder classical | sim (ORACLE) | clip.
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error (including a missing optional backend)."""


COMMAND = ProcessCommand(
    "mapper", "Build the 3D scene graph from all frames and serve it on Zenoh (deltas, snapshots, queries).",
    EPILOG, what="mapper", config_help="TOML config file", set_example="fusion.voxel_m=0.025", listen=True,
    node_module="mapper.node",
    flags=(
        Flag("--geometry", "geometry.backend", "reconstructor: mvs, oracle, mapanything, da3"),
        Flag("--segmenter", "perception.segmenter", "segmenter: classical, detector, sim (ORACLE), sam"),
        Flag("--embedder", "perception.embedder", "embedder: classical, detector, sim (ORACLE), clip"),
        Flag("--state-dir", "state_dir", "persist the graph here and resume from it; versions and node ids are "
             "leased ahead of use, so a restart, even after a kill, never reuses one (without it each start is a "
             "new graph epoch)", Path),
        Flag("--rerun", "rerun.file", "record a Rerun file", Path, metavar="FILE.rrd"),
        Flag("--rerun-web", "rerun.web_port", "serve the live Rerun stream and the web viewer on "
             "http://127.0.0.1:PORT only", int, metavar="PORT"),
    ),
)


def parser() -> argparse.ArgumentParser:
    p = COMMAND.parser()
    p.add_argument("--rerun-serve", action="store_true",
                   help="serve a live Rerun stream on 127.0.0.1 only (rerun --connect rerun+http://127.0.0.1:9876/proxy)")
    return p


def describe_all() -> str:
    """Every config field, then every backend's options (``--describe``)."""
    from mapper.config import MapperConfig
    from mapper.geometry.registry import RECONSTRUCTORS
    from mapper.perception.registry import EMBEDDERS, SEGMENTERS

    lines = ["argus mapper configuration (TOML):", "", *describe(MapperConfig), "",
             "Backend options: the table next to each backend name belongs to the chosen backend; an unknown option "
             "or a wrong type is an error at load."]
    lines += RECONSTRUCTORS.describe(describe, "geometry.options", "geometry.backend")
    lines += SEGMENTERS.describe(describe, "perception.segmenter_options", "perception.segmenter")
    lines += EMBEDDERS.describe(describe, "perception.embedder_options", "perception.embedder")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    from mapper.config import MapperConfig
    from mapper.perception.sam import BackendUnavailable

    serve = True if a.rerun_serve or a.rerun_web is not None else None
    # ValueError: unknown backend names, bad backend options
    return COMMAND.start(a, MapperConfig, describe_all, values={"rerun.serve": serve}, errors=(BackendUnavailable,),
                         config_errors=(ValueError,))


if __name__ == "__main__":
    sys.exit(main())
