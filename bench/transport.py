"""``argus bench transport``: 640x480 JPEG frames through a Zenoh router on loopback.

Starts a real ``argus router`` process, a publisher session and a subscriber session (client mode),
publishes frames at full speed or a set rate, and reports delivered frames/s (frames received over the
window from the first put to the last receipt: the wait for lost frames is not counted), lost frames
(separately), MB/s and latency p50/p99 (capture stamp to receipt) as JSON and a Markdown table. Each run
also sends the same JPEG bytes as raw Zenoh samples (same publisher settings, same router, no Argus
header or decoding): the baseline row says what Argus's framing costs.

Example::

    argus bench transport --frames 300 --out bench_out/transport
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

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


class _Receipts:
    """What a subscriber got: per frame its latency and size, and when the last one arrived."""

    def __init__(self, frames: int) -> None:
        self.frames = frames
        self.latencies_ms: list[float] = []
        self.bytes = 0
        self.last_ns = 0
        self.warm = threading.Event()
        self.all = threading.Event()

    def add(self, seq: int, stamp_ns: int, received_ns: int, size: int) -> None:
        if seq == 0:  # warm-up frames: the route exists
            self.warm.set()
            return
        self.latencies_ms.append((received_ns - stamp_ns) / 1e6)
        self.bytes += size
        self.last_ns = received_ns
        if len(self.latencies_ms) >= self.frames:
            self.all.set()


def _drive(put: Callable[[int], None], got: _Receipts, frames: int, rate_hz: float, loss_wait_s: float,
           ) -> dict[str, float | int]:
    """Warm up (seq 0 until one arrives), publish ``frames`` frames at ``rate_hz`` (0: as fast as possible), wait
    up to ``loss_wait_s`` for the last ones, and return the figures. Frames/s is over the delivery window, from the
    first put to the last receipt: the wait for frames that never arrive is not counted."""
    deadline = time.monotonic() + 10
    while not got.warm.is_set() and time.monotonic() < deadline:
        put(0)
        got.warm.wait(0.1)
    period = 1.0 / rate_hz if rate_hz > 0 else 0.0
    t0_ns = time.time_ns()
    t0 = time.perf_counter()
    for seq in range(1, frames + 1):
        put(seq)
        if period:
            sleep = t0 + seq * period - time.perf_counter()
            if sleep > 0:
                time.sleep(sleep)
    publish_s = time.perf_counter() - t0
    got.all.wait(timeout=loss_wait_s)
    n = len(got.latencies_ms)
    window_s = (got.last_ns - t0_ns) / 1e9 if n else 0.0
    lat = np.asarray(got.latencies_ms) if n else np.asarray([np.nan])
    return {
        "frames_sent": frames,
        "frames_received": n,
        "frames_lost": frames - n,
        "loss_fraction": 1.0 - n / frames,
        "offered_frames_per_s": frames / publish_s if publish_s > 0 else 0.0,
        "frames_per_s": n / window_s if window_s > 0 else 0.0,
        "MB_per_s": got.bytes / window_s / 1e6 if window_s > 0 else 0.0,
        "latency_ms_p50": float(np.nanpercentile(lat, 50)),
        "latency_ms_p99": float(np.nanpercentile(lat, 99)),
    }


def _argus_path(endpoint: str, keys: Keys, jpeg: bytes, width: int, height: int, frames: int, rate_hz: float,
                loss_wait_s: float) -> dict[str, float | int]:
    """Frames as Argus sends them: JPEG payload, msgpack FrameHeader attachment, decoded on receipt."""
    K = Intrinsics.from_fov(width, height, 90.0)
    got = _Receipts(frames)
    with open_session(client(endpoint)) as sub_s, open_session(client(endpoint)) as pub_s:

        def on_sample(sample: Any) -> None:
            f = decode_frame_sample(sample)
            got.add(f.header.seq, f.header.stamp_ns, f.received_ns, len(f.jpeg))

        sub = sub_s.declare_subscriber(keys.cam_frame("bench"), on_sample)
        pub = declare_frame_publisher(pub_s, keys.cam_frame("bench"))

        def put(seq: int) -> None:
            put_frame(pub, FrameHeader(source_id="bench", source_kind="fixed", seq=seq, stamp_ns=time.time_ns(),
                                       width=width, height=height, intrinsics=K), jpeg)

        try:
            return _drive(put, got, frames, rate_hz, loss_wait_s)
        finally:
            sub.undeclare()
            pub.undeclare()


def _raw_zenoh(endpoint: str, keys: Keys, jpeg: bytes, frames: int, rate_hz: float,
               loss_wait_s: float) -> dict[str, float | int]:
    """The baseline: the same JPEG bytes with the same publisher settings (DROP, DATA priority) through the same
    router, with only a 16-byte (seq, stamp) attachment and no Argus encoding or decoding."""
    import zenoh

    got = _Receipts(frames)
    key = keys.cam_frame("bench-raw")
    with open_session(client(endpoint)) as sub_s, open_session(client(endpoint)) as pub_s:

        def on_sample(sample: Any) -> None:
            received = time.time_ns()
            att = sample.attachment
            seq, stamp = struct.unpack("<qq", att.to_bytes()) if att is not None else (-1, received)
            got.add(seq, stamp, received, len(sample.payload.to_bytes()))

        sub = sub_s.declare_subscriber(key, on_sample)
        pub = pub_s.declare_publisher(key, encoding=zenoh.Encoding.IMAGE_JPEG,
                                      congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.DATA)

        def put(seq: int) -> None:
            pub.put(jpeg, attachment=struct.pack("<qq", seq, time.time_ns()))

        try:
            return _drive(put, got, frames, rate_hz, loss_wait_s)
        finally:
            sub.undeclare()
            pub.undeclare()


def run(frames: int, width: int, height: int, quality: int, rate_hz: float, endpoint: str | None,
        loss_wait_s: float = 5.0) -> dict[str, dict[str, float | int]]:
    """Publish ``frames`` frames the Argus way and, through the same router in the same run, the raw-Zenoh
    baseline; return ``{"argus": figures, "raw_zenoh": figures}``."""
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
    try:
        out = {"argus": _argus_path(endpoint, keys, jpeg, width, height, frames, rate_hz, loss_wait_s),
               "raw_zenoh": _raw_zenoh(endpoint, keys, jpeg, frames, rate_hz, loss_wait_s)}
    finally:
        if router_proc is not None:
            router_proc.terminate()
            router_proc.wait(timeout=10)
    for figures in out.values():
        figures.update(frame_bytes=len(jpeg), width=width, height=height, rate_hz_requested=rate_hz)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus bench transport",
        description="Publish JPEG frames through a router on loopback, the Argus way and as raw Zenoh samples "
        "(the baseline, same run); print delivered frames/s, loss, MB/s and latency as JSON.",
        epilog="example: argus bench transport --frames 300 --rate 30 --out bench_out/transport",
    )
    p.add_argument("--frames", type=int, default=300, help="frames to publish")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--quality", type=int, default=90, help="JPEG quality")
    p.add_argument("--rate", type=float, default=0.0, help="publish rate in Hz (0: as fast as possible and 30 Hz)")
    p.add_argument("--loss-wait", type=float, default=5.0,
                   help="seconds to wait for the last frames before counting the missing ones as lost")
    p.add_argument("--endpoint", default=None, help="use this router instead of starting one")
    p.add_argument("--out", type=Path, default=None, help="write transport.json and transport.md here")
    p.add_argument("--quick", action="store_true", help="100 frames")
    a = p.parse_args(argv)
    frames = min(a.frames, 100) if a.quick else a.frames
    results = {}
    for rate in ([a.rate] if a.rate else [0.0, 30.0]):
        results[f"rate_{rate:g}"] = run(frames, a.width, a.height, a.quality, rate, a.endpoint, a.loss_wait)
    print(json.dumps(results, indent=2))
    if a.out:
        write_report(a.out, "transport", {"runs": results}, table_rows(results),
                     "Transport: 640x480 JPEG over a loopback router, Argus frames and the raw-Zenoh baseline")
    return 0


def table_rows(results: dict[str, dict[str, dict[str, float | int]]]) -> list[dict[str, Any]]:
    """One row per rate and path: delivered frames/s, loss (separately), MB/s, latency."""
    return [{"rate_hz": rate, "path": path, **{m: fig[m] for m in (
        "frames_per_s", "frames_received", "frames_lost", "loss_fraction", "MB_per_s", "latency_ms_p50",
        "latency_ms_p99", "frame_bytes")}} for rate, paths in results.items() for path, fig in paths.items()]

if __name__ == "__main__":
    sys.exit(main())
