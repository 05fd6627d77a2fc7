"""A minimal frame publisher and subscriber, each runnable as its own process.

Used by the transport smoke demo and the integration tests to prove that frames flow through a
router intact (payload and header attachment), and that liveliness tokens come and go with their
process.

Examples::

    python -m deploy.loopback publish --endpoint tcp/127.0.0.1:7447 --frames 10
    python -m deploy.loopback subscribe --endpoint tcp/127.0.0.1:7447 --frames 10
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import threading
import time

import numpy as np

from protocol.jpeg import decode_jpeg, encode_jpeg
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics
from protocol.runtime import install_stop_handlers
from protocol.session import client, open_session
from protocol.transport import declare_frame_publisher, decode_frame_sample, put_frame


def textured_image(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A textured image (noise plus gradients) that compresses like a camera frame."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.stack([xx * 255 // max(width - 1, 1), yy * 255 // max(height - 1, 1), (xx + yy) % 256], axis=-1)
    noise = rng.integers(0, 40, size=(height, width, 3))
    return np.clip(base + noise, 0, 255).astype(np.uint8)


def publish(endpoint: str, frames: int, site: str = "default", source_id: str = "demo-cam",
            rate_hz: float = 10.0, width: int = 640, height: int = 480, wait_subscriber_s: float = 10.0) -> int:
    """Publish ``frames`` synthetic frames (prints one JSON line per frame); 0 frames = until stopped."""
    stop = install_stop_handlers()
    keys = Keys(site)
    with open_session(client(endpoint)) as session:
        token = session.liveliness().declare_token(keys.alive("publisher", source_id))
        pub = declare_frame_publisher(session, keys.cam_frame(source_id))
        deadline = time.monotonic() + wait_subscriber_s
        while not pub.matching_status and time.monotonic() < deadline and not stop.is_set():
            stop.wait(0.05)
        seq = 0
        while not stop.is_set() and (frames == 0 or seq < frames):
            img = textured_image(width, height, seed=seq)
            jpeg = encode_jpeg(img, 90)
            hdr = FrameHeader(source_id=source_id, source_kind="fixed", seq=seq, stamp_ns=time.time_ns(),
                              width=width, height=height, intrinsics=Intrinsics.from_fov(width, height, 90.0))
            put_frame(pub, hdr, jpeg)
            print(json.dumps({"sent": seq, "bytes": len(jpeg), "sha1": hashlib.sha1(jpeg).hexdigest()}), flush=True)
            seq += 1
            stop.wait(1.0 / rate_hz)
        if frames and not stop.is_set():
            stop.wait(1.0)  # let the last frames drain before the session closes
        token.undeclare()
    return 0


def subscribe(endpoint: str, frames: int, site: str = "default", timeout_s: float = 30.0) -> int:
    """Print one JSON line per received frame (header and payload digest) and per liveliness change."""
    stop = install_stop_handlers()
    keys = Keys(site)
    done = threading.Event()
    count = 0
    lock = threading.Lock()

    def on_frame(sample) -> None:  # noqa: ANN001 - zenoh.Sample
        nonlocal count
        f = decode_frame_sample(sample)
        img = decode_jpeg(f.jpeg)
        with lock:
            count += 1
            print(json.dumps({
                "received": f.header.seq, "key": f.key, "source_id": f.header.source_id,
                "width": img.shape[1], "height": img.shape[0], "sha1": hashlib.sha1(f.jpeg).hexdigest(),
                "latency_ms": round((f.received_ns - f.header.stamp_ns) / 1e6, 3),
            }), flush=True)
            if frames and count >= frames:
                done.set()

    def on_alive(sample) -> None:  # noqa: ANN001 - zenoh.Sample
        role, node = keys.parse_alive(str(sample.key_expr))
        print(json.dumps({"alive": str(sample.kind).split(".")[-1].lower(), "role": role, "id": node}), flush=True)

    with open_session(client(endpoint)) as session:
        subs = [session.declare_subscriber(keys.all_frames, on_frame),
                session.liveliness().declare_subscriber(keys.all_alive, on_alive, history=True)]
        print(json.dumps({"ready": True}), flush=True)
        deadline = time.monotonic() + timeout_s
        while not stop.is_set() and not done.is_set() and time.monotonic() < deadline:
            done.wait(0.1)
        for s in subs:
            s.undeclare()
    return 0 if (frames == 0 or count >= frames) else 1


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.loopback", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("role", choices=["publish", "subscribe"])
    p.add_argument("--endpoint", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--frames", type=int, default=10, help="frames to send/receive (0: until stopped)")
    p.add_argument("--site", default="default")
    p.add_argument("--timeout", type=float, default=30.0, help="subscriber: give up after this many seconds")
    a = p.parse_args(argv)
    if a.role == "publish":
        return publish(a.endpoint, a.frames, a.site)
    return subscribe(a.endpoint, a.frames, a.site, a.timeout)


if __name__ == "__main__":
    sys.exit(main())
