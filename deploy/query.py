"""``argus query``: the scene graph as a consumer sees it, from any machine on the Zenoh network.

Examples::

    argus query nodes --label chair --near 1,2,0 --radius 2
    argus query nodes --room room2 --label cup
    argus query nodes --label chair --include-retired   # and the chairs seen gone
    argus query rooms
    argus query snapshot --json > graph.json
    argus query watch                      # live deltas; Ctrl-C exits

``nodes``, ``rooms`` and ``snapshot`` are Zenoh queries answered by the mapper's queryable (``graph/nodes`` with
:class:`protocol.query.GraphQuery` parameters, ``graph/rooms``, ``graph/snapshot``); ``watch`` subscribes to
``graph/delta``. A consumer never blocks the mapper: queries are answered from the mapper's latest
graph and each consumer only waits on its own reply.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import shutil
import sys
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

from protocol import exits
from protocol.codec import DecodeError, decode, peek_kind
from protocol.keys import Keys
from protocol.messages import GraphDelta, GraphEdge, GraphNode, GraphSnapshot, RetiredNode
from protocol.query import GraphQuery
from protocol.rooms import RoomLayer
from protocol.session import ZenohConfigError, ZenohUnavailable, open_session
from protocol.tomlconfig import add_consumer_flags, consumer_values


class QueryError(RuntimeError):
    """No usable answer: nobody answered (``exit_code`` 4), only error replies or undecodable ones (1),
    or the mapper refused the query's values (2)."""

    def __init__(self, message: str, exit_code: int = exits.UNREACHABLE) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class NodeNotFound(QueryError):
    """The node id asked for is not in the graph (exit status 3)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, exits.NOT_FOUND)


def _refusal(errors: list[str], where: str) -> QueryError:
    """The QueryError for a query answered with error replies only (docs/WIRE.md, "Error replies")."""
    why = "; ".join(errors)
    if any(e.startswith("not_found:") for e in errors):
        return NodeNotFound(why)
    code = exits.USAGE if any(e.startswith("bad_query:") for e in errors) else exits.FAILED
    return QueryError(f"{why} (on {where})", code)


def _reply_payloads(replies: Iterable[Any]) -> tuple[list[bytes], list[str]]:
    ok: list[bytes] = []
    errors: list[str] = []
    for reply in replies:
        if reply.ok is not None:
            ok.append(reply.ok.payload.to_bytes())
        else:
            try:
                errors.append(reply.err.payload.to_string())
            except Exception:  # noqa: BLE001 - an error reply with an odd payload is still an error
                errors.append("error reply")
    return ok, errors


def get_nodes(session: Any, keys: Keys, query: GraphQuery, timeout_s: float = 5.0) -> list[GraphNode]:
    """Nodes selected by ``query``: one Zenoh ``get`` on ``graph/nodes?<parameters>``.

    The mapper may answer with one ``GraphSnapshot`` (the selection) or one ``GraphNode`` per reply;
    both are accepted. Raises :class:`QueryError` when nobody answered or the mapper refused.
    """
    return get_selection(session, keys, query, timeout_s)[0]


def get_selection(session: Any, keys: Keys, query: GraphQuery,
                  timeout_s: float = 5.0) -> tuple[list[GraphNode], list[RetiredNode]]:
    """:func:`get_nodes`, with the retired nodes the answer carries (newest first; only when
    ``query.include_retired``). A missing ``--id`` is not found only when neither list has it."""
    import zenoh

    params = query.to_parameters()
    selector = zenoh.Selector(keys.graph_nodes, params) if params else keys.graph_nodes
    # No reply consolidation: Zenoh's default keeps one reply per key, so a peer answering later
    # (a stale storage, a broken replier) could hide the mapper's answer. Every reply is judged here.
    payloads, errors = _reply_payloads(
        session.get(selector, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE))
    nodes: dict[str, GraphNode] = {}
    retired: dict[str, RetiredNode] = {}
    bad = 0
    for data in payloads:
        try:
            kind = peek_kind(data)
            if kind == GraphNode.KIND:
                n = decode(data, GraphNode)
                nodes[n.node_id] = n
            elif kind == GraphSnapshot.KIND:
                snap = decode(data, GraphSnapshot)
                for n in snap.nodes:
                    nodes[n.node_id] = n
                for r in snap.retired:
                    retired[r.node.node_id] = r
            else:
                bad += 1
        except DecodeError:
            bad += 1
    if not payloads:
        if errors:
            raise _refusal(errors, keys.graph_nodes)
        raise QueryError(f"no answer on {keys.graph_nodes} within {timeout_s:g} s (is a mapper running?)")
    if bad == len(payloads):
        raise QueryError(f"{bad} undecodable replies on {keys.graph_nodes}", exits.FAILED)
    found = sorted(nodes.values(), key=lambda n: n.node_id)
    gone = sorted(retired.values(), key=lambda r: (-r.retired_ns, r.node.node_id))
    if query.id is not None and not found and not gone:
        raise NodeNotFound(f"node {query.id!r} is not in the graph")
    return found, gone


def get_node(session: Any, keys: Keys, node_id: str, timeout_s: float = 5.0) -> GraphNode:
    """One node by id: a ``get`` on ``graph/node/<id>``. Raises :class:`NodeNotFound` when the mapper answers
    ``not_found`` (or its node selection holds no such node), :class:`QueryError` when nobody answered."""
    import zenoh

    key = keys.graph_node(node_id)
    payloads, errors = _reply_payloads(
        session.get(key, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE))
    for data in payloads:
        try:
            return decode(data, GraphNode)
        except DecodeError:
            continue
    if errors:
        raise _refusal(errors, key)
    if payloads:
        raise QueryError(f"{len(payloads)} undecodable replies on {key}", exits.FAILED)
    raise QueryError(f"no answer on {key} within {timeout_s:g} s (is a mapper running?)")


M = TypeVar("M", GraphSnapshot, RoomLayer)  # versioned graph messages a query picks the newest of


def _newest(session: Any, key: str, message: type[M], timeout_s: float, **get_options: Any) -> M:
    """The newest ``version`` of ``message`` among the replies on ``key``; QueryError for a refusal, replies that
    do not decode, or no answer."""
    payloads, errors = _reply_payloads(session.get(key, timeout=timeout_s, **get_options))
    best: M | None = None
    for data in payloads:
        try:
            msg = decode(data, message)
        except DecodeError:
            continue
        if best is None or msg.version > best.version:
            best = msg
    if best is None:
        if errors:
            raise _refusal(errors, key)
        if payloads:
            raise QueryError(f"{len(payloads)} undecodable replies on {key}", exits.FAILED)
        raise QueryError(f"no answer on {key} within {timeout_s:g} s (is a mapper running?)")
    return best


def get_snapshot(session: Any, keys: Keys, timeout_s: float = 5.0) -> GraphSnapshot:
    """The latest full graph (the newest valid version among all replies, unconsolidated)."""
    import zenoh

    return _newest(session, keys.graph_snapshot, GraphSnapshot, timeout_s,
                   consolidation=zenoh.ConsolidationMode.NONE)


def get_rooms(session: Any, keys: Keys, timeout_s: float = 5.0) -> RoomLayer:
    """The room layer (the newest graph version among all replies)."""
    return _newest(session, keys.graph_rooms, RoomLayer, timeout_s)


# --- formatting -----------------------------------------------------------------------------------
def _fmt_xyz(v: Iterable[float]) -> str:
    return "(" + ", ".join(f"{x:6.2f}" for x in v) + ")"


def format_nodes(nodes: list[GraphNode], near: tuple[float, float, float] | None = None) -> str:
    """A fixed-width table of nodes (distance column when ``near`` is given)."""
    head = f"{'id':<12} {'label':<22} {'conf':>5} {'centroid (m)':<24} {'size (m)':<24} {'obs':>4}  sources"
    if near is not None:
        head += "  dist_m"
    lines = [head]
    for n in nodes:
        line = (f"{n.node_id:<12} {n.label[:22]:<22} {n.label_confidence:5.2f} {_fmt_xyz(n.centroid):<24} "
                f"{_fmt_xyz(n.box.extent):<24} {n.observation_count:>4}  {','.join(n.sources)}")
        if near is not None:
            line += f"  {math.dist(near, n.centroid):.2f}"
        lines.append(line)
    lines.append(f"{len(nodes)} node(s)")
    return "\n".join(lines)


def format_retired(retired: list[RetiredNode]) -> str:
    """A fixed-width table of retired nodes (seen gone), newest first: where each was last seen and when."""
    lines = [f"{'id':<12} {'label':<22} {'last seen at (m)':<24} {'retired (UTC)':<20} {'reason':<8} sources"]
    for r in retired:
        n = r.node
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r.retired_ns / 1e9))
        lines.append(f"{n.node_id:<12} {n.label[:22]:<22} {_fmt_xyz(n.centroid):<24} {when:<20} {r.reason:<8} "
                     f"{','.join(n.sources)}")
    lines.append(f"{len(retired)} retired node(s)")
    return "\n".join(lines)


def format_edges(edges: list[GraphEdge], nodes: list[GraphNode]) -> str:
    label = {n.node_id: n.label for n in nodes}
    return "\n".join(
        f"  {label.get(e.subject_id, '?')} ({e.subject_id}) {e.predicate} "
        f"{label.get(e.object_id, '?')} ({e.object_id})"
        for e in edges
    )


def format_rooms(layer: RoomLayer) -> str:
    """A fixed-width table of rooms (objects in each), then the doorways."""
    lines = [f"{'id':<10} {'label':<14} {'conf':>5} {'area_m2':>8} {'seen':>5} {'objects':>7}  centre (m)"]
    for r in layer.rooms:
        lines.append(f"{r.room_id:<10} {r.label[:14]:<14} {r.label_confidence:5.2f} {r.area_m2:8.1f} "
                     f"{r.observed_fraction:5.2f} {len(layer.members(r.room_id)):>7}  "
                     f"({r.centroid[0]:.2f}, {r.centroid[1]:.2f})")
    lines.append(f"{len(layer.rooms)} room(s) at graph version {layer.version}")
    for e in layer.edges:
        if e.predicate == "connects" and e.position is not None:
            lines.append(f"  {e.subject_id} connects {e.object_id} through a doorway at "
                         f"({e.position[0]:.2f}, {e.position[1]:.2f}), {e.width_m or 0.0:.2f} m wide")
    return "\n".join(lines)


def format_delta(d: GraphDelta) -> str:
    up = ", ".join(f"{n.label}({n.node_id})" for n in d.upserted[:6])
    more = f" +{len(d.upserted) - 6} more" if len(d.upserted) > 6 else ""
    return (f"v{d.version}: {len(d.upserted)} upserted, {len(d.removed)} removed, "
            f"+{len(d.edges_added)}/-{len(d.edges_removed)} edges" + (f"  [{up}{more}]" if up else ""))


# --- commands -------------------------------------------------------------------------------------
def run_nodes(session: Any, keys: Keys, query: GraphQuery, as_json: bool, timeout_s: float) -> int:
    nodes, retired = get_selection(session, keys, query, timeout_s)
    if as_json:
        listed = [n.model_dump(mode="json", exclude={"embedding"}) for n in nodes]
        if query.include_retired:
            gone = [r.model_dump(mode="json", exclude={"node": {"embedding"}}) for r in retired]
            print(json.dumps({"nodes": listed, "retired": gone}, indent=1))
        else:
            print(json.dumps(listed, indent=1))
    else:
        print(format_nodes(nodes, query.near))
        if query.include_retired:
            print(format_retired(retired))
    return 0


def run_rooms(session: Any, keys: Keys, as_json: bool, timeout_s: float) -> int:
    layer = get_rooms(session, keys, timeout_s)
    print(layer.model_dump_json() if as_json else format_rooms(layer))
    return 0


def run_snapshot(session: Any, keys: Keys, as_json: bool, timeout_s: float) -> int:
    snap = get_snapshot(session, keys, timeout_s)
    if as_json:
        print(snap.model_dump_json(exclude={"nodes": {"__all__": {"embedding"}}}))
        return 0
    print(f"graph version {snap.version}: {len(snap.nodes)} nodes, {len(snap.edges)} edges"
          + (f" (mapper epoch {snap.epoch})" if snap.epoch else ""))
    print(format_nodes(snap.nodes))
    if snap.edges:
        print("edges:")
        print(format_edges(snap.edges, snap.nodes))
    return 0


def run_watch(
    session: Any, keys: Keys, as_json: bool, stop: threading.Event, count: int | None = None,
    timeout_s: float | None = None,
) -> int:
    """Print every delta until ``stop`` (Ctrl-C), ``count`` deltas, or ``timeout_s`` without any."""
    inbox: queue.Queue[bytes] = queue.Queue(maxsize=256)
    dropped = [0]

    def on_sample(sample: Any) -> None:
        try:
            inbox.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            dropped[0] += 1  # a slow terminal must never back-pressure the network

    sub = session.declare_subscriber(keys.graph_delta, on_sample)
    print(f"watching {keys.graph_delta} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    seen, bad, last = 0, 0, None
    last_at = time.monotonic()
    try:
        while not stop.is_set() and (count is None or seen < count):
            try:
                data = inbox.get(timeout=0.2)
            except queue.Empty:
                if timeout_s is not None and time.monotonic() - last_at > timeout_s:
                    print(f"no delta for {timeout_s:g}s", file=sys.stderr)
                    return 1
                continue
            last_at = time.monotonic()
            try:
                d = decode(data, GraphDelta)
            except DecodeError as e:
                bad += 1
                print(f"undecodable delta ({bad} so far): {e}", file=sys.stderr)
                continue
            seen += 1
            new_epoch = last is not None and d.epoch != last[0]
            gap = last is not None and not new_epoch and d.version != last[1] + 1
            last = (d.epoch, d.version)
            if as_json:
                print(d.model_dump_json(exclude={"upserted": {"__all__": {"embedding"}}}), flush=True)
            else:
                note = "  (gap: missed deltas, re-query the snapshot)" if gap else ""
                if new_epoch:
                    note = f"  (new mapper epoch {d.epoch!r}: versions restart, re-query the snapshot)"
                print(format_delta(d) + note, flush=True)
    finally:
        sub.undeclare()
        if dropped[0]:
            print(f"{dropped[0]} deltas dropped by this consumer (too slow)", file=sys.stderr)
    return 0


def argus_command() -> str:
    """How to run this install's ``argus`` from the current shell: ``argus`` when the PATH finds this one, else
    its path (``.venv/bin/argus`` after ``make install`` without ``source .venv/bin/activate``)."""
    here = Path(sys.executable).with_name("argus")
    if not here.exists():
        return "argus"
    found = shutil.which("argus")
    if found is not None and Path(found).resolve() == here.resolve():
        return "argus"
    rel = os.path.relpath(here)
    return rel if not rel.startswith("..") else str(here)


def query_hint(endpoint: str, site: str) -> str:
    """The exact ``argus query`` line that reads the graph of the stack on ``endpoint`` / ``site``, runnable as
    printed from the current directory."""
    return f"{argus_command()} query --connect {endpoint} --site {site} snapshot"


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so the interpreter's final flush into the closed pipe is silent too."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


EPILOG = """examples:
  argus query nodes --label chair --near 1,2,0 --radius 2
  argus query nodes --id n12 --json
  argus query nodes --room room2 --label cup
  argus query nodes --label chair --include-retired
  argus query rooms
  argus query snapshot --json > graph.json
  argus query watch --count 5

exit status: 0 answered, 2 bad arguments (a bad endpoint or query value), 3 node not found (--id),
4 no answer (no router at --connect, or no mapper on --site within --timeout), 1 any other failure."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus query",
        description="Query or watch the live scene graph (any number of consumers, from any machine).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_consumer_flags(p)
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for answers")
    sub = p.add_subparsers(dest="what", required=True)
    pn = sub.add_parser("nodes", help="nodes selected by label / position / id / room")
    pn.add_argument("--label", default=None, help="label substring, case-insensitive (e.g. chair)")
    pn.add_argument("--near", default=None, help="x,y,z centre in metres (world frame)")
    pn.add_argument("--radius", type=float, default=None, help="radius around --near in metres (default 1)")
    pn.add_argument("--id", default=None, help="one node id (exit status 3 when the graph has no such node)")
    pn.add_argument("--since-version", type=int, default=None, help="only nodes changed after this version")
    pn.add_argument("--room", default=None, help="only nodes in this room (a room id: argus query rooms)")
    pn.add_argument("--include-retired", action="store_true",
                    help="also the nodes retired because their place was seen empty (kept a while; newest first)")
    pn.add_argument("--json", action="store_true",
                    help="JSON list of nodes ({\"nodes\": [...], \"retired\": [...]} with --include-retired)")
    pr = sub.add_parser("rooms", help="the rooms: label, area, how much was seen, objects, doorways")
    pr.add_argument("--json", action="store_true", help="the RoomLayer as JSON")
    ps = sub.add_parser("snapshot", help="the whole latest graph")
    ps.add_argument("--json", action="store_true", help="the GraphSnapshot as JSON")
    pw = sub.add_parser("watch", help="print graph deltas as they happen (Ctrl-C exits)")
    pw.add_argument("--json", action="store_true", help="one JSON delta per line")
    pw.add_argument("--count", type=int, default=None, help="exit after this many deltas")
    pw.add_argument("--idle-timeout", type=float, default=None, help="exit 1 after this long without a delta")
    return p


def _parse_near(text: str) -> tuple[float, float, float]:
    try:
        xyz = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--near: {text!r} is not x,y,z in metres") from None
    if len(xyz) != 3:
        raise ValueError(f"--near: {text!r} is not x,y,z in metres")
    return xyz[0], xyz[1], xyz[2]


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    try:
        settings, site = consumer_values(a)
        keys = Keys(site)
        query = None
        if a.what == "nodes":
            near = _parse_near(a.near) if a.near is not None else None
            query = GraphQuery(label=a.label, near=near, radius=a.radius, id=a.id,
                               since_version=a.since_version, room=a.room,
                               include_retired=True if a.include_retired else None)
    except ValueError as e:  # pydantic's ValidationError included: one line per field, no URL
        print(f"argus query: {exits.one_line(e)}", file=sys.stderr)
        return exits.USAGE

    from protocol.runtime import install_stop_handlers

    stop = install_stop_handlers()
    try:
        with open_session(settings) as session:
            if a.what == "nodes":
                assert query is not None
                return run_nodes(session, keys, query, a.json, a.timeout)
            if a.what == "snapshot":
                return run_snapshot(session, keys, a.json, a.timeout)
            if a.what == "rooms":
                return run_rooms(session, keys, a.json, a.timeout)
            return run_watch(session, keys, a.json, stop, a.count, a.idle_timeout)
    except BrokenPipeError:  # the reader went away (argus query ... | head): not an error
        _silence_stdout()
        return exits.OK
    except QueryError as e:
        print(f"argus query: {e}", file=sys.stderr)
        return e.exit_code
    except ZenohConfigError as e:
        print(f"argus query: {exits.one_line(e)}", file=sys.stderr)
        return exits.USAGE
    except ZenohUnavailable as e:
        print(f"argus query: {e}", file=sys.stderr)
        return exits.UNREACHABLE
    except Exception as e:  # noqa: BLE001 - anything else: a message, not a traceback
        print(f"argus query: {type(e).__name__}: {exits.one_line(e)}", file=sys.stderr)
        return exits.FAILED

if __name__ == "__main__":
    sys.exit(main())
