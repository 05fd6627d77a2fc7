"""Per-frame cost of an edge camera: grab + resize/encode + put, at 640x480 by default.

Runs the same code path as ``argus edge-camera`` (source backend -> ``FramePublisher``) against a
real Zenoh link: by default two in-process peers on a free loopback port (publisher and a
subscriber that receives every frame), or a router given with ``--connect``. Prints a Markdown
table and optionally writes JSON. The lead wires it as ``argus bench edge``.

Example::

    python -m edge_camera.bench --frames 100 --sources pattern,folder --out bench_out/edge.json
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from edge_camera.config import EdgeCameraConfig, PublishConfig
from edge_camera.publish import FramePublisher
from edge_camera.sources import create_source, parse_source_config
from protocol.keys import Keys
from protocol.session import ZenohSettings, open_session
from protocol.transport import declare_frame_publisher


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stats(values: list[float]) -> dict[str, float]:
    v = sorted(values)
    return {
        "mean": statistics.fmean(v),
        "p50": v[len(v) // 2],
        "p95": v[min(len(v) - 1, int(round(0.95 * (len(v) - 1))))],
    }


def _folder_of_jpegs(folder: Path, width: int, height: int, n: int = 8) -> None:
    rng = np.random.default_rng(0)
    for i in range(n):
        yy, xx = np.mgrid[0:height, 0:width]
        img = np.stack([(xx + 7 * i) % 256, (yy + 3 * i) % 256, (xx * yy) % 251], -1).astype(np.uint8)
        img = np.clip(img.astype(np.int16) + rng.integers(-20, 20, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"f{i:03d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 90])


def bench_source(
    source: dict[str, Any], n_frames: int, width: int, height: int, quality: int, session: Any, keys: Keys,
    received: list[int],
) -> dict[str, Any]:
    """Time ``n_frames`` frames of one source through the publisher; returns the figures."""
    source_config = parse_source_config(source)
    cfg = EdgeCameraConfig(
        id="bench", source=source_config, publish=PublishConfig(width=width, height=height, jpeg_quality=quality)
    )
    src = create_source(source_config)
    src.open()
    pub = declare_frame_publisher(session, keys.cam_frame("bench"))
    publisher = FramePublisher(cfg, pub, None, None)
    grab_ms: list[float] = []
    encode_ms: list[float] = []
    put_ms: list[float] = []
    sizes: list[int] = []
    start_received = received[0]
    for i in range(n_frames + 3):
        t0 = time.perf_counter()
        grab = src.read()
        g = (time.perf_counter() - t0) * 1e3
        done = publisher.publish(grab, g)
        if i >= 3:  # warm-up frames excluded
            grab_ms.append(g)
            encode_ms.append(done.encode_ms)
            put_ms.append(done.put_ms)
            sizes.append(done.jpeg_bytes)
    src.close()
    deadline = time.monotonic() + 5.0
    while received[0] - start_received < n_frames + 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    pub.undeclare()
    total = [a + b + c for a, b, c in zip(grab_ms, encode_ms, put_ms, strict=True)]
    return {
        "source": source["type"],
        "frames": n_frames,
        "size": f"{width}x{height}",
        "jpeg_quality": quality,
        "grab_ms": _stats(grab_ms),
        "encode_ms": _stats(encode_ms),
        "put_ms": _stats(put_ms),
        "total_ms": _stats(total),
        "max_fps": 1000.0 / statistics.fmean(total),
        "jpeg_kib": statistics.fmean(sizes) / 1024.0,
        "received": received[0] - start_received,
    }


def run(n_frames: int, sources: list[str], width: int, height: int, quality: int,
        connect: str | None) -> list[dict[str, Any]]:
    keys = Keys("bench")
    received = [0]
    lock = threading.Lock()

    def on_frame(_sample: Any) -> None:
        with lock:
            received[0] += 1

    if connect:
        pub_settings = ZenohSettings(mode="client", connect=[connect])
        sub_settings = ZenohSettings(mode="client", connect=[connect])
    else:
        ep = f"tcp/127.0.0.1:{_free_port()}"
        pub_settings = ZenohSettings(mode="peer", connect=[], listen=[ep])
        sub_settings = ZenohSettings(mode="peer", connect=[ep])
    results = []
    with open_session(pub_settings) as pub_session, open_session(sub_settings) as sub_session:
        sub = sub_session.declare_subscriber(keys.cam_frame("bench"), on_frame)
        time.sleep(0.5)  # let the subscription reach the publisher (a benchmark, not a test)
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            _folder_of_jpegs(folder, width, height)
            configs = {
                "pattern": {"type": "pattern", "width": width, "height": height, "rate_hz": None},
                "folder": {"type": "folder", "path": str(folder), "rate_hz": 1000.0},
                "sim": {"type": "sim", "family": "apartment", "seed": 0, "width": width, "height": height,
                        "rerender": True},
            }
            for name in sources:
                if name not in configs:
                    raise SystemExit(f"unknown bench source {name!r} (pattern, folder, sim)")
                results.append(bench_source(configs[name], n_frames, width, height, quality, pub_session, keys,
                                            received))
        sub.undeclare()
    return results


def markdown(results: list[dict[str, Any]]) -> str:
    lines = [
        "| source | size | grab ms | encode ms | put ms | total ms (p50 / p95) | max fps | JPEG KiB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['source']} | {r['size']} | {r['grab_ms']['mean']:.2f} | {r['encode_ms']['mean']:.2f} | "
            f"{r['put_ms']['mean']:.2f} | {r['total_ms']['p50']:.2f} / {r['total_ms']['p95']:.2f} | "
            f"{r['max_fps']:.0f} | {r['jpeg_kib']:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench edge",
        description="Per-frame cost of an edge camera (grab + encode + put) over a real loopback Zenoh link.",
        epilog="example: argus bench edge --frames 100 --sources pattern,folder --out bench_out/edge.json",
    )
    p.add_argument("--frames", type=int, default=100, help="frames per source (after 3 warm-up frames)")
    p.add_argument("--sources", default="pattern,folder", help="comma list of pattern, folder, sim")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--quality", type=int, default=85, help="JPEG quality")
    p.add_argument("--connect", default=None, help="use this router instead of two in-process peers")
    p.add_argument("--threads", type=int, default=1, help="OpenCV threads (an edge box has few cores)")
    p.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    p.add_argument("--quick", action="store_true", help="at most 30 frames per source (smoke run)")
    a = p.parse_args(argv)
    if a.quick:
        a.frames = min(a.frames, 30)
    cv2.setNumThreads(a.threads)
    results = run(a.frames, [s.strip() for s in a.sources.split(",") if s.strip()], a.width, a.height,
                  a.quality, a.connect)
    print(markdown(results))
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps({"edge_camera": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
