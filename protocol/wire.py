"""The wire contract as data: JSON Schemas of every message and the generated parts of docs/WIRE.md.

``python -m protocol.wire --write`` regenerates ``protocol/schema/*.json`` and the blocks of docs/WIRE.md
between ``<!-- generated:NAME -->`` and ``<!-- /generated:NAME -->`` from the pydantic models and
:class:`protocol.keys.Keys`; ``--check`` exits 1 when either has drifted (tests/protocol/test_wire.py does the same).
Everything else in WIRE.md is prose, and its example code blocks are run by the tests.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from protocol.codec import MAGIC, MSGPACK_MIME, REGISTRY
from protocol.keys import Keys
from protocol.messages import ALL_MESSAGES, Message, PlainGoal
from protocol.rooms import ROOM_MESSAGES

WIRE_MESSAGES: tuple[type[Message], ...] = ALL_MESSAGES + ROOM_MESSAGES
"""Every message of the contract: protocol.messages' and the room layer's (protocol.rooms)."""

SCHEMA_DIR = Path(__file__).resolve().parent / "schema"
WIRE_MD = Path(__file__).resolve().parents[1] / "docs" / "WIRE.md"
SCHEMA_BASE = "argus"
"""Schema names: ``argus/<kind>/<major>.<minor>`` (the Zenoh encoding's schema suffix and the JSON Schema $id)."""

COMMON_FIELDS: dict[str, str] = {
    "robot_id": "robot id (a single key chunk: letters, digits, _ . -)",
    "stamp_ns": "time, integer nanoseconds since the Unix epoch",
    "version": "graph version: +1 per graph change; the version this message reflects",
    "nodes": "object nodes, sorted by node_id",
    "edges": "relations between the nodes, sorted by (subject_id, predicate, object_id)",
    "upserted": "nodes added or changed since version - 1 (whole nodes: replace by node_id)",
    "removed": "ids of nodes removed since version - 1",
    "edges_added": "relations added since version - 1",
    "edges_removed": "relations removed since version - 1",
}
"""Meaning of field names used alike by several messages, for fields whose model gives no description."""


def schema_name(cls: type[Message]) -> str:
    major, minor = cls.SCHEMA
    return f"{SCHEMA_BASE}/{cls.KIND}/{major}.{minor}"


def _describe_common(schema: dict[str, Any]) -> None:
    for name, prop in schema.get("properties", {}).items():
        if "description" not in prop and name in COMMON_FIELDS:
            prop["description"] = COMMON_FIELDS[name]


def json_schema(cls: type[BaseModel]) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a message body or of :class:`PlainGoal`, with Argus ids."""
    schema = cls.model_json_schema(mode="validation")
    _describe_common(schema)
    for sub in schema.get("$defs", {}).values():
        _describe_common(sub)
    head: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema"}
    if isinstance(cls, type) and issubclass(cls, Message):
        major, minor = cls.SCHEMA
        head.update({"$id": schema_name(cls), "x-argus-kind": cls.KIND, "x-argus-schema": [major, minor]})
    else:
        head["$id"] = f"{SCHEMA_BASE}/plain_goal"
    return {**head, **schema}


def schema_files() -> dict[str, str]:
    """File name -> JSON text of every shipped schema (one per message kind, plus plain_goal.json)."""
    out = {f"{cls.KIND}.json": json.dumps(json_schema(cls), indent=2, sort_keys=True) + "\n" for cls in WIRE_MESSAGES}
    out["plain_goal.json"] = json.dumps(json_schema(PlainGoal), indent=2, sort_keys=True) + "\n"
    return out


# --- markdown --------------------------------------------------------------------------------------
def _bounds(s: dict[str, Any]) -> str:
    marks = [("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<")]
    out = [f"{sym} {s[k]:g}" if isinstance(s[k], float) else f"{sym} {s[k]}" for k, sym in marks if k in s]
    if "minLength" in s or "maxLength" in s:
        out.append(f"length {s.get('minLength', 0)}..{s.get('maxLength', '')}")
    return f" ({', '.join(out)})" if out else ""


def type_text(s: dict[str, Any]) -> str:
    """A short human name of a JSON Schema type (``ndarray`` for numpy arrays)."""
    if any({"dtype", "shape", "data"} <= set(x.get("properties", {})) for x in s.get("anyOf", [])):
        return "ndarray"
    if "$ref" in s:
        return s["$ref"].rsplit("/", 1)[-1]
    if "anyOf" in s:
        return " or ".join(type_text(x) for x in s["anyOf"])
    if "enum" in s:
        return " | ".join(json.dumps(v) for v in s["enum"])
    if "const" in s:
        return json.dumps(s["const"])
    t = s.get("type")
    if t == "array":
        if "prefixItems" in s:
            return "[" + ", ".join(type_text(x) for x in s["prefixItems"]) + "]"
        if "items" in s and s.get("minItems") is not None and s.get("minItems") == s.get("maxItems"):
            return f"{type_text(s['items'])}[{s['minItems']}]"
        if "items" in s:
            return f"array of {type_text(s['items'])}{_bounds(s)}"
        return "array"
    if t == "object":
        extra = s.get("additionalProperties")
        return f"map string → {type_text(extra)}" if isinstance(extra, dict) else "object"
    if t == "string" and s.get("format") == "binary":
        return "bytes (msgpack bin)"
    names = {"integer": "int", "number": "float", "string": "string", "boolean": "bool", "null": "null"}
    return names.get(str(t), str(t)) + _bounds(s)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def field_table(cls: type[BaseModel]) -> str:
    """Markdown table of a model's fields: name, type, required/default, meaning and units."""
    schema = json_schema(cls)
    required = set(schema.get("required", []))
    rows = ["| field | type | required / default | meaning, units |", "| --- | --- | --- | --- |"]
    for name, prop in schema["properties"].items():
        need = "required" if name in required else f"default `{json.dumps(_default(cls, name, prop))}`"
        rows.append(f"| `{name}` | {_cell(type_text(prop))} | {need} | {_cell(str(prop.get('description', '')))} |")
    return "\n".join(rows)


def _default(cls: type[BaseModel], name: str, prop: dict[str, Any]) -> Any:
    field = cls.model_fields.get(name)
    if field is not None and field.default_factory is not None:
        return field.default_factory()  # type: ignore[call-arg]
    return prop.get("default")


def _doc(cls: type) -> str:
    return " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())


def messages_block() -> str:
    parts = []
    for cls in WIRE_MESSAGES:
        major, minor = cls.SCHEMA
        parts.append(f"### `{cls.KIND}` ({cls.__name__}, schema {major}.{minor})\n\n{_doc(cls)} "
                     f"JSON Schema: `protocol/schema/{cls.KIND}.json`.\n\n{field_table(cls)}\n")
    return "\n".join(parts).rstrip()


def kinds_block() -> str:
    rows = ["| kind | message | schema (major.minor) | Zenoh encoding of its samples |", "| --- | --- | --- | --- |"]
    for kind, cls in REGISTRY.items():
        major, minor = cls.SCHEMA
        rows.append(f"| `{kind}` | {cls.__name__} | {major}.{minor} | `{MSGPACK_MIME};{schema_name(cls)}` |")
    return "\n".join(rows)


def keys_block() -> str:
    """Every key, built by :class:`Keys` itself (placeholders substituted back)."""
    k = Keys("SITE")
    rows = [
        (k.cam_frame("CAM"), "put", "JPEG bytes (`image/jpeg`), attachment: `frame_header` envelope"),
        (k.robot_frame("ROBOT"), "put", "JPEG bytes (`image/jpeg`), attachment: `frame_header` envelope"),
        (k.oracle("robot", "ROBOT"), "put", "`oracle_frame` (simulated sources only; also under cam/)"),
        (k.robot_state("ROBOT"), "put + query", "`robot_state` (a query gets the newest one: late joiners)"),
        (k.robot_goal("ROBOT"), "put (you send)", "`nbv_goal` envelope, or a plain goal as JSON / msgpack map"),
        (k.robot_goal_status("ROBOT"), "put", "`goal_status`: the robot's answer to every goal payload"),
        (k.robot_goal_status_json("ROBOT"), "put", "the same `goal_status` as a JSON object"),
        (k.robot_viewpoints("ROBOT"), "put + query", "`viewpoint_set`"),
        (k.graph_snapshot, "put + query", "`graph_snapshot` (the whole graph)"),
        (k.graph_delta, "put", "`graph_delta` (one per graph version)"),
        (k.graph_node("NODE"), "put/delete + query",
         "`graph_node` (deleted when the node is removed; a query for a missing node: `not_found` error reply)"),
        (k.graph_nodes, "query", "`graph_snapshot` of the selected nodes (parameters below)"),
        (k.graph_json(k.graph_snapshot), "query", "JSON `graph_snapshot`"),
        (k.graph_json(k.graph_nodes), "query", "JSON `graph_snapshot` of the selected nodes"),
        (k.graph_json(k.graph_node("NODE")), "query", "JSON `graph_node`"),
        (k.map_points, "put + query", "`point_map`, the whole map each time (a query gets the newest one)"),
        (k.status("ROLE", "ID"), "put + query",
         "`status` (at start, then every `status_period_s`: see Status below; a query gets the newest one)"),
        (k.alive("ROLE", "ID"), "liveliness token", "present while the process runs"),
        (k.work_job("WORKER"), "put (mapper)", "`work_job`: a keyframe job for one `argus worker`"),
        (k.work_ack("WORKER"), "put (worker)", "`work_ack`: the worker took a job"),
        (k.work_result("WORKER"), "put (worker)", "`work_result`: a job's depth, confidence, pose, detections"),
        (k.work_keyframe("SOURCE", 0), "query (mapper answers)", "a stored keyframe's JPEG bytes (`image/jpeg`)"),
    ]
    subst = {"SITE": "<site>", "CAM": "<camera_id>", "ROBOT": "<robot_id>", "NODE": "<node_id>", "ROLE": "<role>",
             "ID": "<id>", "WORKER": "<worker_id>", "SOURCE": "<source_id>", "0": "<seq>"}
    pattern = re.compile(r"(?<=/)(" + "|".join(subst) + r")(?=/|$)")
    lines = ["| key | how | payload |", "| --- | --- | --- |"]
    for key, how, what in rows:
        lines.append(f"| `{pattern.sub(lambda m: subst[m.group(1)], key)}` | {how} | {what} |")
    return "\n".join(lines)


def blocks() -> dict[str, str]:
    """Name -> generated markdown of every generated block of WIRE.md."""
    return {
        "envelope": f'`["{MAGIC}", kind, major, minor, body]`',
        "keys": keys_block(),
        "kinds": kinds_block(),
        "messages": messages_block(),
        "plain_goal": field_table(PlainGoal),
    }


_BLOCK = re.compile(r"(<!-- generated:(\w+) -->\n)(.*?)(<!-- /generated:\2 -->)", re.S)


def render(markdown: str) -> str:
    """``markdown`` with every generated block replaced by its current content (unknown names: error)."""
    gen = blocks()

    def sub(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in gen:
            raise KeyError(f"WIRE.md names an unknown generated block {name!r}")
        return f"{m.group(1)}{gen[name]}\n{m.group(4)}"

    return _BLOCK.sub(sub, markdown)


def drift(schema_dir: Path = SCHEMA_DIR, wire_md: Path = WIRE_MD) -> list[str]:
    """Files that differ from what the models generate (empty: all current)."""
    out = []
    want = schema_files()
    have = {p.name for p in schema_dir.glob("*.json")} if schema_dir.is_dir() else set()
    for name, text in want.items():
        p = schema_dir / name
        if not p.is_file() or p.read_text(encoding="utf-8") != text:
            out.append(str(p))
    out += [str(schema_dir / n) + " (no such message)" for n in sorted(have - set(want))]
    md = wire_md.read_text(encoding="utf-8")
    if render(md) != md:
        out.append(str(wire_md))
    return out


def write(schema_dir: Path = SCHEMA_DIR, wire_md: Path = WIRE_MD) -> None:
    schema_dir.mkdir(parents=True, exist_ok=True)
    want = schema_files()
    for p in schema_dir.glob("*.json"):
        if p.name not in want:
            p.unlink()
    for name, text in want.items():
        (schema_dir / name).write_text(text, encoding="utf-8")
    wire_md.write_text(render(wire_md.read_text(encoding="utf-8")), encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m protocol.wire", description=__doc__.split("\n\n")[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", action="store_true", help="regenerate protocol/schema/*.json and docs/WIRE.md blocks")
    g.add_argument("--check", action="store_true", help="exit 1 listing the files that drifted from the models")
    a = p.parse_args(argv)
    if a.write:
        write()
        print(f"wrote {len(schema_files())} schemas to {SCHEMA_DIR} and the generated blocks of {WIRE_MD}")
        return 0
    stale = drift()
    for s in stale:
        print(f"stale: {s}", file=sys.stderr)
    if stale:
        print("run: python -m protocol.wire --write", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
