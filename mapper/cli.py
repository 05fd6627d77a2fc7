"""``argus mapper``: build and serve the 3D scene graph from every camera and robot frame.

Example::

    argus mapper --connect tcp/127.0.0.1:7447 --state-dir /var/lib/argus/mapper
    argus mapper --geometry oracle --segmenter sim --embedder sim    # ORACLE inputs (simulated frames only)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.tomlconfig import ConfigError, describe, load_config, process_parser, process_values

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


def parser() -> argparse.ArgumentParser:
    p = process_parser(
        "argus mapper",
        "Build the 3D scene graph from all frames and serve it on Zenoh (deltas, snapshots, queries).",
        EPILOG, what="mapper", config_help="TOML config file", set_example="fusion.voxel_m=0.025", listen=True,
    )
    p.add_argument("--geometry", default=None, help="reconstructor: mvs, oracle, mapanything, da3")
    p.add_argument("--segmenter", default=None, help="segmenter: classical, detector, sim (ORACLE), sam")
    p.add_argument("--embedder", default=None, help="embedder: classical, detector, sim (ORACLE), clip")
    p.add_argument("--state-dir", type=Path, default=None,
                   help="persist the graph here and resume from it; versions and node ids are leased ahead of use, "
                   "so a restart, even after a kill, never reuses one (without it each start is a new graph epoch)")
    p.add_argument("--rerun", type=Path, default=None, metavar="FILE.rrd", help="record a Rerun file")
    p.add_argument("--rerun-serve", action="store_true",
                   help="serve a live Rerun stream on 127.0.0.1 only (rerun --connect rerun+http://127.0.0.1:9876/proxy)")
    p.add_argument("--rerun-web", type=int, default=None, metavar="PORT",
                   help="serve the live Rerun stream and the web viewer on http://127.0.0.1:PORT only")
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

    if a.describe:
        print(describe_all())
        return 0
    values = {
        **process_values(a),
        "geometry.backend": a.geometry,
        "perception.segmenter": a.segmenter,
        "perception.embedder": a.embedder,
        "state_dir": None if a.state_dir is None else str(a.state_dir),
        "rerun.file": None if a.rerun is None else str(a.rerun),
        "rerun.serve": True if a.rerun_serve or a.rerun_web is not None else None,
        "rerun.web_port": a.rerun_web,
    }
    try:
        config = load_config(MapperConfig, a.config, values, a.overrides)
    except ConfigError as e:
        print(f"argus mapper: {e}", file=sys.stderr)
        return 2
    from protocol.runtime import setup_logging

    setup_logging(f"mapper[{config.id}]", config.log_level)
    from mapper.node import run
    from mapper.perception.sam import BackendUnavailable

    try:
        return run(config)
    except BackendUnavailable as e:
        print(f"argus mapper: {e}", file=sys.stderr)
        return 2
    except ValueError as e:  # unknown backend names, bad backend options
        print(f"argus mapper: configuration error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
