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
from protocol.tomlconfig import Flag, ProcessCommand

EPILOG = """examples:
  argus edge-camera --config edge_camera/examples/folder.toml --connect tcp/127.0.0.1:7447
  argus edge-camera --source pattern --id cam1 --rate 5 --width 640
  argus edge-camera --config edge_camera/examples/sim.toml --set source.camera_index=1
  argus edge-camera --describe      # every config field, every source type
  argus edge-camera calibrate --help    # a calibration file (intrinsics + pose) from a ChArUco board

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Source faults never end it."""


COMMAND = ProcessCommand(
    "edge-camera", "Publish one fixed camera's JPEG frames (with calibration) on Zenoh; reconnect on faults.",
    EPILOG, what="camera", config_help="TOML config file (see edge_camera/examples/)",
    set_example="source.rate_hz=1", node_module="edge_camera.node",
    flags=(
        Flag("--source", "source.type", "source type: opencv, stream, video, folder, recorded, pattern, sim"),
        Flag("--rate", "publish.max_rate_hz", "max frames per second (publish.max_rate_hz)", float),
        Flag("--width", "publish.width", "publish width in pixels", int),
        Flag("--height", "publish.height", "publish height in pixels", int),
        Flag("--quality", "publish.jpeg_quality", "JPEG quality 1..100", int),
        Flag("--calibration", "calibration", "calibration file (OpenCV YAML or JSON)", Path),
    ),
)


def parser() -> argparse.ArgumentParser:
    return COMMAND.parser()


def describe_all() -> str:
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources import REGISTRY

    return COMMAND.describe(EdgeCameraConfig, REGISTRY)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["calibrate"]:
        from edge_camera.calibrate import main as calibrate_main

        return calibrate_main(argv[1:])
    a = parser().parse_args(argv)
    from edge_camera.calibration import CalibrationError
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources.base import SourceConfigError

    return COMMAND.start(a, EdgeCameraConfig, describe_all,
                         config_errors=(CalibrationError, SourceConfigError, ZenohConfigError))


if __name__ == "__main__":
    sys.exit(main())
