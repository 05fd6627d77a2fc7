"""What the mapper sends out: each GraphDelta, with every changed node under ``graph/node/<id>`` (removed ones
deleted); a GraphSnapshot and the PointMap at bounded rates (``config.publish``; the point map also answers
late joiners' queries); and, when configured, the Rerun log of each view fused."""

from __future__ import annotations

import logging
import time
from typing import Any

from mapper.config import MapperConfig
from mapper.core import MapperCore
from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphNode, GraphSnapshot, PointMap
from protocol.node import Node
from protocol.transport import Counters, message_encoding

log = logging.getLogger(__name__)


class GraphOutbox:
    """The mapper's publishers (declared by :meth:`open` on the process's node) and what it puts on them."""

    def __init__(self, core: MapperCore, config: MapperConfig, keys: Keys, counters: Counters) -> None:
        self.core, self.config, self.keys, self.counters = core, config, keys, counters
        self.session: Any = None  # where node keys are put and deleted (a zenoh.Session)
        self.pubs: dict[str, Any] = {}  # delta, snapshot, map
        self._last_snapshot: tuple[tuple[str, int], float] = (("", -1), 0.0)
        self._last_map = (-1, 0.0)
        self._rerun: Any = None

    def open(self, node: Node) -> None:
        k = self.keys
        self.session = node.session
        self.pubs = {
            "delta": node.publisher(k.graph_delta, message=GraphDelta),
            "snapshot": node.publisher(k.graph_snapshot, message=GraphSnapshot),
            # the point map answers queries with its newest value (late joiners)
            "map": node.latest(node.publisher(k.map_points, important=False, message=PointMap)),
        }
        self._open_rerun()

    def delta(self, delta: GraphDelta) -> None:
        self.pubs["delta"].put(encode(delta))
        for n in delta.upserted:
            self.session.put(self.keys.graph_node(n.node_id), encode(n), encoding=message_encoding(GraphNode))
        for node_id in delta.removed:
            self.session.delete(self.keys.graph_node(node_id))
        self.counters.add("deltas")

    def periodic(self, force: bool = False) -> None:
        """The snapshot and the point map, each when the graph changed and its period has passed (or ``force``)."""
        now = time.monotonic()
        version = self.core.version
        pc = self.config.publish
        seen, when = self._last_snapshot
        if (self.core.epoch, version) != seen and (force or now - when >= pc.snapshot_period_s):
            snap = self.core.snapshot()
            self.pubs["snapshot"].put(encode(snap))
            self._last_snapshot = ((snap.epoch, snap.version), now)
            self.counters.add("snapshots")
        v, when = self._last_map
        if version != v and (force or now - when >= pc.point_map_period_s) and len(self.core.voxels):
            self.pubs["map"].put(encode(self.core.point_map(pc.point_map_max_points)))
            self._last_map = (version, now)
            self.counters.add("point_maps")

    # -- Rerun -----------------------------------------------------------------------------------------
    def _open_rerun(self) -> None:
        rc = self.config.rerun
        if rc.file is None and not rc.serve:
            return
        from mapper.rerun_log import RerunLogger

        try:
            self._rerun = RerunLogger(rc)
        except Exception as e:  # noqa: BLE001 - visualisation must never stop mapping
            log.error("Rerun output disabled: %s", e)
            self._rerun = None

    def rerun(self) -> None:
        """Log the core's state to Rerun (when configured); a failure is counted, never raised."""
        if self._rerun is None:
            return
        try:
            self._rerun.log(self.core)
        except Exception as e:  # noqa: BLE001
            self.counters.add("rerun_errors")
            log.debug("Rerun logging failed: %s", e)

    def close(self) -> None:
        if self._rerun is not None:
            self._rerun.close()
