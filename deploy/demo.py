"""``argus demo`` (placeholder until the full stack lands): a router, a publisher and a subscriber on
loopback, each its own process; prints what flowed."""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="argus demo", description=__doc__)
    p.add_argument("--frames", type=int, default=10)
    a = p.parse_args(argv)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tcp/127.0.0.1:{port}"
    py = [sys.executable, "-m"]
    router = subprocess.Popen([*py, "deploy.cli", "router", "--listen", ep], start_new_session=True)
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.05)
        sub = subprocess.Popen([*py, "deploy.loopback", "subscribe", "--endpoint", ep, "--frames", str(a.frames)])
        pub = subprocess.Popen([*py, "deploy.loopback", "publish", "--endpoint", ep, "--frames", str(a.frames)],
                               stdout=subprocess.DEVNULL)
        rc = sub.wait(timeout=60)
        pub.wait(timeout=30)
        print(f"demo: {'frames flowed' if rc == 0 else 'FAILED'} through the router at {ep}")
        return rc
    finally:
        router.terminate()
        router.wait(timeout=10)


if __name__ == "__main__":
    sys.exit(main())
