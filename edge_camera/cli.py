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

from protocol.tomlconfig import ConfigError, describe, load_config

EPILOG = """examples:
  argus edge-camera --config edge_camera/examples/folder.toml --connect tcp/127.0.0.1:7447
  argus edge-camera --source pattern --id cam1 --rate 5 --width 640
  argus edge-camera --config edge_camera/examples/sim.toml --set source.camera_index=1
  argus edge-camera --describe      # every config field, every source type

Command-line flags override the file; --set PATH=VALUE overrides any field (TOML value syntax).
Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error. Source faults never end it."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus edge-camera",
        description="Publish one fixed camera's JPEG frames (with calibration) on Zenoh; reconnect on faults.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", type=Path, default=None, help="TOML config file (see edge_camera/examples/)")
    p.add_argument("--id", default=None, help="camera id")
    p.add_argument("--site", default=None, help="Argus site name")
    p.add_argument("--connect", action="append", default=None, help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--mode", choices=["client", "peer"], default=None, help="Zenoh mode (default client)")
    p.add_argument("--source", default=None, help="source type: opencv, stream, video, folder, pattern, sim")
    p.add_argument("--rate", type=float, default=None, help="max frames per second (publish.max_rate_hz)")
    p.add_argument("--width", type=int, default=None, help="publish width in pixels")
    p.add_argument("--height", type=int, default=None, help="publish height in pixels")
    p.add_argument("--quality", type=int, default=None, help="JPEG quality 1..100")
    p.add_argument("--calibration", type=Path, default=None, help="calibration file (OpenCV YAML or JSON)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override any config field, e.g. --set source.rate_hz=1 (repeatable)")
    p.add_argument("--describe", action="store_true", help="print every config field and exit")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def describe_all() -> str:
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources import available, backend_module

    lines = ["argus edge-camera configuration (TOML):", ""]
    lines += [ln for ln in describe(EdgeCameraConfig) if not ln.startswith("source ")]
    for name in sorted(available()):
        try:
            cls = backend_module(name).Config
        except Exception as e:  # noqa: BLE001 - a broken plug-in must not hide the others
            lines += ["", f"[source] type = {name!r}: unavailable ({e})"]
            continue
        lines += ["", f"[source] type = {name!r}"]
        lines += [f"  {ln}" for ln in describe(cls, prefix="source.") if not ln.startswith("source.type ")]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if a.describe:
        print(describe_all())
        return 0
    from edge_camera.calibration import CalibrationError
    from edge_camera.config import EdgeCameraConfig
    from edge_camera.sources.base import SourceConfigError
    from protocol.runtime import setup_logging

    values = {
        "id": a.id,
        "site": a.site,
        "zenoh.connect": a.connect,
        "zenoh.mode": a.mode,
        "source.type": a.source,
        "publish.max_rate_hz": a.rate,
        "publish.width": a.width,
        "publish.height": a.height,
        "publish.jpeg_quality": a.quality,
        "calibration": None if a.calibration is None else str(a.calibration),
        "log_level": a.log_level,
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
    except (CalibrationError, SourceConfigError) as e:
        print(f"argus edge-camera: configuration error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
