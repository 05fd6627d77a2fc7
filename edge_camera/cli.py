"""``argus edge-camera``: stream one fixed camera's JPEG frames over Zenoh.

Example::

    argus edge-camera --config edge_camera/examples/folder.toml --connect tcp/127.0.0.1:7447
    argus edge-camera --source pattern --id cam1 --rate 5 --width 640
    argus edge-camera --config edge_camera/examples/usb.toml --set source.device=1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from protocol.session import ZenohConfigError
from protocol.tomlconfig import ConfigError, describe, load_config, process_parser, process_values

EPILOG = """examples:
  argus edge-camera --config edge_camera/examples/folder.toml --connect tcp/127.0.0.1:7447
  argus edge-camera --source pattern --id cam1 --rate 5 --width 640
  argus edge-camera --config edge_camera/examples/sim.toml --set source.camera_index=1
  argus edge-camera --describe      # every config field, every source type
  argus edge-camera calibrate --help    # a calibration file (intrinsics + pose) from a ChArUco board

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Source faults never end it."""


def parser() -> argparse.ArgumentParser:
    p = process_parser(
        "argus edge-camera",
        "Publish one fixed camera's JPEG frames (with calibration) on Zenoh; reconnect on faults.",
        EPILOG, what="camera", config_help="TOML config file (see edge_camera/examples/)",
        set_example="source.rate_hz=1",
    )
    p.add_argument("--source", default=None, help="source type: opencv, stream, video, folder, pattern, sim")
    p.add_argument("--rate", type=float, default=None, help="max frames per second (publish.max_rate_hz)")
    p.add_argument("--width", type=int, default=None, help="publish width in pixels")
    p.add_argument("--height", type=int, default=None, help="publish height in pixels")
    p.add_argument("--quality", type=int, default=None, help="JPEG quality 1..100")
    p.add_argument("--calibration", type=Path, default=None, help="calibration file (OpenCV YAML or JSON)")
    return p


def describe_all() -> str:
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources import REGISTRY

    lines = ["argus edge-camera configuration (TOML):", ""]
    lines += [ln for ln in describe(EdgeCameraConfig) if not ln.startswith("source ")]
    return "\n".join(lines + REGISTRY.describe(describe))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["calibrate"]:
        from edge_camera.calibrate import main as calibrate_main

        return calibrate_main(argv[1:])
    a = parser().parse_args(argv)
    if a.describe:
        print(describe_all())
        return 0
    from edge_camera.calibration import CalibrationError
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources.base import SourceConfigError
    from protocol.runtime import setup_logging

    values = {
        **process_values(a),
        "source.type": a.source,
        "publish.max_rate_hz": a.rate,
        "publish.width": a.width,
        "publish.height": a.height,
        "publish.jpeg_quality": a.quality,
        "calibration": None if a.calibration is None else str(a.calibration),
    }
    try:
        config = load_config(EdgeCameraConfig, a.config, values, a.overrides)
    except ConfigError as e:
        print(f"argus edge-camera: {e}", file=sys.stderr)
        return 2
    setup_logging(f"edge-camera[{config.id}]", config.log_level)
    from edge_camera.node import run

    try:
        return run(config)
    except (CalibrationError, SourceConfigError, ZenohConfigError) as e:
        print(f"argus edge-camera: configuration error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
