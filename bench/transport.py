"""``argus bench transport``: 640x480 JPEG frames through a Zenoh router on loopback.

Starts a real ``argus router`` process, a publisher session and a subscriber session (client mode),
publishes frames at full speed or a set rate, and reports frames/s, MB/s and latency p50/p99
(capture stamp in the header to receipt) as JSON and a Markdown table.

Example::

    argus bench transport --frames 300 --out bench_out/transport
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from bench.report import write_report
from deploy.loopback import textured_image
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics
from protocol.session import client, open_session
from protocol.transport import declare_frame_publisher, decode_frame_sample, put_frame


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"router did not listen on port {port}")


def run(frames: int, width: int, height: int, quality: int, rate_hz: float, endpoint: str | None) -> dict:
    """Publish ``frames`` frames and return the measured figures."""
    router_proc = None
    if endpoint is None:
        port = _free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        router_proc = subprocess.Popen(
            [sys.executable, "-m", "deploy.cli", "router", "--listen", endpoint, "--log-level", "WARNING"],
            start_new_session=True,
        )
        _wait_port(port)
    keys = Keys("bench")
    jpeg = encode_jpeg(textured_image(width, height), quality)
    K = Intrinsics.from_fov(width, height, 90.0)
    latencies_ms: list[float] = []
    received_bytes = 0
    got_all = threading.Event()
    first = threading.Event()
    try:
        with open_session(client(endpoint)) as sub_s, open_session(client(endpoint)) as pub_s:

            def on_sample(sample) -> None:  # noqa: ANN001 - zenoh.Sample
                nonlocal received_bytes
                f = decode_frame_sample(sample)
                if f.header.seq == 0 and not first.is_set():
                    first.set()
                    return
                latencies_ms.append((f.received_ns - f.header.stamp_ns) / 1e6)
                received_bytes += len(f.jpeg)
                if len(latencies_ms) >= frames:
                    got_all.set()

            sub = sub_s.declare_subscriber(keys.cam_frame("bench"), on_sample)
            pub = declare_frame_publisher(pub_s, keys.cam_frame("bench"))
            # Warm-up: repeat a seq-0 frame until the subscriber sees one (routes established).
            deadline = time.monotonic() + 10
            while not first.is_set() and time.monotonic() < deadline:
                hdr = FrameHeader(source_id="bench", source_kind="fixed", seq=0, stamp_ns=time.time_ns(),
                                  width=width, height=height, intrinsics=K)
                put_frame(pub, hdr, jpeg)
                first.wait(0.1)
            period = 1.0 / rate_hz if rate_hz > 0 else 0.0
            t0 = time.perf_counter()
            for seq in range(1, frames + 1):
                hdr = FrameHeader(source_id="bench", source_kind="fixed", seq=seq, stamp_ns=time.time_ns(),
                                  width=width, height=height, intrinsics=K)
                put_frame(pub, hdr, jpeg)
                if period:
                    sleep = t0 + seq * period - time.perf_counter()
                    if sleep > 0:
                        time.sleep(sleep)
            got_all.wait(timeout=10.0)
            elapsed = time.perf_counter() - t0
            sub.undeclare()
            pub.undeclare()
    finally:
        if router_proc is not None:
            router_proc.terminate()
            router_proc.wait(timeout=10)
    lat = np.asarray(latencies_ms) if latencies_ms else np.asarray([np.nan])
    n = len(latencies_ms)
    return {
        "frames_sent": frames,
        "frames_received": n,
        "frame_bytes": len(jpeg),
        "width": width,
        "height": height,
        "rate_hz_requested": rate_hz,
        "frames_per_s": n / elapsed if elapsed > 0 else 0.0,
        "MB_per_s": received_bytes / elapsed / 1e6 if elapsed > 0 else 0.0,
        "latency_ms_p50": float(np.nanpercentile(lat, 50)),
        "latency_ms_p99": float(np.nanpercentile(lat, 99)),
        "loss_fraction": 1.0 - n / frames,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench transport",
        description="Publish JPEG frames through a router on loopback; print frames/s, MB/s, latency as JSON.",
        epilog="example: argus bench transport --frames 300 --rate 30 --out bench_out/transport",
    )
    p.add_argument("--frames", type=int, default=300, help="frames to publish")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--quality", type=int, default=90, help="JPEG quality")
    p.add_argument("--rate", type=float, default=0.0, help="publish rate in Hz (0: as fast as possible)")
    p.add_argument("--endpoint", default=None, help="use this router instead of starting one")
    p.add_argument("--out", type=Path, default=None, help="write transport.json and transport.md here")
    p.add_argument("--quick", action="store_true", help="100 frames")
    a = p.parse_args(argv)
    frames = min(a.frames, 100) if a.quick else a.frames
    results = {}
    for rate in ([a.rate] if a.rate else [0.0, 30.0]):
        results[f"rate_{rate:g}"] = run(frames, a.width, a.height, a.quality, rate, a.endpoint)
    print(json.dumps(results, indent=2))
    if a.out:
        rows = [{"rate_hz": k, **{m: v[m] for m in ("frames_per_s", "MB_per_s", "latency_ms_p50",
                                                     "latency_ms_p99", "loss_fraction", "frame_bytes")}}
                for k, v in results.items()]
        write_report(a.out, "transport", {"runs": results}, rows, "Transport: 640x480 JPEG over a loopback router")
    return 0


if __name__ == "__main__":
    sys.exit(main())
