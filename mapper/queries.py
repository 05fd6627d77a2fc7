"""Graph queries the mapper answers: ``graph/snapshot``, ``graph/nodes?label=..;near=..;radius=..;id=..;
since_version=..;room=..;include_retired=..``, ``graph/node/<id>``, ``graph/rooms`` (the room layer) and
wildcards such as ``graph/**`` (msgpack envelopes), and the same keys below ``graph/json/`` (JSON objects). A
bad query gets an error reply, never a crash.

Error replies (Zenoh ``reply_err``, encoding ``text/plain``) are one UTF-8 line ``<code>: <detail>``; codes:
``not_found`` (``graph/node/<id>`` of a node the graph does not hold) and ``bad_query`` (a parameter that does
not parse or is out of range). docs/WIRE.md, "Error replies", is the contract."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from mapper.core import MapperCore
from protocol.codec import encode
from protocol.keys import Keys
from protocol.messages import GraphSnapshot, Message
from protocol.query import GraphQuery
from protocol.transport import Counters, message_encoding

if TYPE_CHECKING:
    import zenoh


class NotFound(LookupError):
    """What the query names does not exist: answered with a ``not_found`` error reply."""


def error_reply_text(e: Exception) -> str:
    """The one-line ``<code>: <detail>`` payload of the error reply to a query that raised ``e``."""
    from protocol.exits import one_line

    if isinstance(e, NotFound):
        return f"not_found: {e}"
    return f"bad_query: {one_line(e)}"


class GraphQueries:
    """Answers queries from ``core`` (callbacks on Zenoh threads); ``refuse(reason, msg, *args)`` counts and logs
    a bad one."""

    def __init__(self, core: MapperCore, keys: Keys, counters: Counters,
                 refuse: Callable[..., None]) -> None:
        self.core, self.keys, self.counters, self.refuse = core, keys, counters, refuse
        # The encoded whole-graph snapshot of the newest graph (MapperCore.snapshot_key): consumers that poll it get
        # the same bytes until the graph changes.
        self._snapshot_bytes: tuple[tuple[str, int, int | None], bytes] | None = None

    def on_query(self, query: zenoh.Query) -> None:
        self._guarded_answer(query, json_view=False)

    def on_json_query(self, query: zenoh.Query) -> None:
        self._guarded_answer(query, json_view=True)

    def _guarded_answer(self, query: zenoh.Query, json_view: bool) -> None:
        try:
            self._answer(query, json_view)
        except NotFound as e:
            self.counters.add("queries_not_found")
            self._reply_err(query, error_reply_text(e))
        except Exception as e:  # noqa: BLE001 - a bad query gets an error reply, never a crash
            self.refuse("query_errors", "bad query %s?%s: %s: %s", query.key_expr, query.parameters,
                         type(e).__name__, e)
            self._reply_err(query, error_reply_text(e))

    @staticmethod
    def _reply_err(query: zenoh.Query, text: str) -> None:
        import zenoh

        try:
            query.reply_err(text, encoding=zenoh.Encoding.TEXT_PLAIN)
        except Exception:  # noqa: BLE001 - the querier may be gone
            pass

    def _answer(self, query: zenoh.Query, json_view: bool = False) -> None:
        """Reply with msgpack envelopes, or (``json_view``, keys under ``graph/json/``) with JSON objects."""
        import zenoh

        t0 = time.perf_counter()
        key = str(query.key_expr)
        if json_view:
            if not zenoh.KeyExpr(self.keys.graph_json_all).includes(zenoh.KeyExpr(key)):
                return  # e.g. graph/**: the msgpack queryable answers that; formats never mix in one reply set
            self.counters.add("json_queries")
            for reply_key, msg in self._select(self.keys.from_graph_json(key), str(query.parameters)):
                query.reply(self.keys.graph_json(reply_key), msg.model_dump_json(),
                            encoding=message_encoding(type(msg), "application/json"))
        elif key == self.keys.graph_snapshot:
            self.counters.add("queries")
            query.reply(key, self.snapshot_bytes(), encoding=message_encoding(GraphSnapshot))
        else:
            self.counters.add("queries")
            for reply_key, msg in self._select(key, str(query.parameters)):
                query.reply(reply_key, encode(msg), encoding=message_encoding(type(msg)))
        self.counters.set("last_query_ms", (time.perf_counter() - t0) * 1e3)

    def snapshot_bytes(self) -> bytes:
        """The encoded :meth:`MapperCore.snapshot`, encoded once per graph change (``snapshot_encodes`` counts)."""
        k = self.core.snapshot_key()
        cached = self._snapshot_bytes
        if cached is not None and cached[0] == k:
            return cached[1]
        snap, k = self.core.keyed_snapshot()
        data = encode(snap)
        self._snapshot_bytes = (k, data)
        self.counters.add("snapshot_encodes")
        return data

    def _select(self, key: str, params: str) -> list[tuple[str, Message]]:
        """What a query on ``key`` (under ``graph/``) answers: ``(reply key, message)`` pairs."""
        import zenoh

        if key == self.keys.graph_snapshot:
            return [(key, self.core.snapshot())]
        if key == self.keys.graph_rooms:
            layer = self.core.room_layer()
            if layer is None:
                raise NotFound("this mapper builds no rooms (rooms.enabled = false)")
            return [(key, layer)]
        if key == self.keys.graph_nodes:
            return [(key, self.core.select_graph(GraphQuery.from_parameters(params)))]
        try:
            node_id = self.keys.parse_node(key)
        except ValueError:
            node_id = None
        if node_id is not None:
            found: list[tuple[str, Message]] = [(key, n) for n in self.core.query(GraphQuery(id=node_id))]
            if not found:
                raise NotFound(f"node {node_id} is not in the graph (version {self.core.version}, "
                               f"epoch {self.core.epoch!r})")
            return found
        # A wildcard such as graph/**: answer with everything it covers, each under its own key.
        asked = zenoh.KeyExpr(key)
        out: list[tuple[str, Message]] = []
        if asked.intersects(zenoh.KeyExpr(self.keys.graph_snapshot)):
            out.append((self.keys.graph_snapshot, self.core.snapshot()))
        if asked.intersects(zenoh.KeyExpr(self.keys.graph_rooms)):
            layer = self.core.room_layer()
            if layer is not None:
                out.append((self.keys.graph_rooms, layer))
        for n in self.core.nodes():
            nk = self.keys.graph_node(n.node_id)
            if asked.intersects(zenoh.KeyExpr(nk)):
                out.append((nk, n))
        return out
