"""A Zenoh peer of a real ``argus mapper`` process: the mapper's command line for tests, and a consumer
that publishes box-world frames (JPEG + header, with ORACLE samples) and collects deltas, snapshots and
status."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from protocol.codec import DecodeError, decode, encode
from protocol.jpeg import encode_jpeg
from protocol.keys import Keys
from protocol.messages import FrameHeader, GraphDelta, GraphNode, GraphSnapshot, OracleFrame, Status
from protocol.oracle import depth_to_png, ids_to_png
from protocol.query import GraphQuery
from protocol.session import ZenohSettings, open_session
from protocol.transport import declare_frame_publisher, declare_message_publisher, put_frame
from tests.support.boxes import INTR, LABELS, view

SITE = "maptest"


def mapper_args(endpoint: str, state_dir: Path) -> list[str]:
    return [
        "mapper", "--connect", endpoint, "--site", SITE, "--geometry", "oracle", "--segmenter", "sim",
        "--embedder", "sim", "--state-dir", str(state_dir), "--set", "save_period_s=0",
        "--set", "publish.snapshot_period_s=0", "--set", "status_period_s=0.2", "--set", "torch_threads=1",
    ]


class Consumer:
    """Collects deltas, snapshots and status; publishes frames."""

    def __init__(self, endpoint: str) -> None:
        self.keys = Keys(SITE)
        self.session = open_session(ZenohSettings(mode="client", connect=[endpoint]))
        self.deltas: list[GraphDelta] = []
        self.status: dict[str, float] = {}
        self.lock = threading.Lock()
        self.subs = [
            self.session.declare_subscriber(self.keys.graph_delta, self._on_delta),
            self.session.declare_subscriber(self.keys.status("mapper", "mapper"), self._on_status),
        ]
        self.frame_pub = declare_frame_publisher(self.session, self.keys.robot_frame("robot1"))
        self.oracle_pub = declare_message_publisher(self.session, self.keys.oracle("robot", "robot1"))

    def _on_delta(self, sample: Any) -> None:
        with self.lock:
            self.deltas.append(decode(sample.payload.to_bytes(), GraphDelta))

    def _on_status(self, sample: Any) -> None:
        try:
            self.status = decode(sample.payload.to_bytes(), Status).counters
        except DecodeError:
            pass

    def send(self, eye: list[float], seq: int) -> None:
        v = view(eye, seq)
        assert v.oracle is not None and v.oracle.instance_id is not None
        self.oracle_pub.put(
            encode(
                OracleFrame(
                    source_id="robot1", seq=seq, stamp_ns=v.stamp_ns, T_world_cam_true=v.oracle.T_world_cam_true,
                    ids_png=ids_to_png(v.oracle.instance_id), depth_png=depth_to_png(v.oracle.depth_m),
                    labels={str(k): lab for k, lab in LABELS.items()},
                )
            )
        )
        header = FrameHeader(
            source_id="robot1", source_kind="robot", seq=seq, stamp_ns=v.stamp_ns, width=INTR.width,
            height=INTR.height, intrinsics=INTR, T_world_cam=v.T_world_cam,
        )
        put_frame(self.frame_pub, header, encode_jpeg(v.image))

    def get(self, key: str, params: str = "") -> list[bytes]:
        import zenoh

        sel = zenoh.Selector(key, params) if params else key
        return [r.ok.payload.to_bytes() for r in self.session.get(sel, timeout=5.0) if r.ok is not None]

    def snapshot(self) -> GraphSnapshot | None:
        replies = self.get(self.keys.graph_snapshot)
        return decode(replies[0], GraphSnapshot) if replies else None

    def nodes(self, q: GraphQuery) -> list[GraphNode]:
        (data,) = self.get(self.keys.graph_nodes, q.to_parameters())
        return decode(data, GraphSnapshot).nodes

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()
