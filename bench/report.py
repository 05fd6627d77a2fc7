"""Benchmark output: a JSON file and a Markdown table side by side, plus machine facts."""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


def key_values(items: Sequence[str], flag: str, error: Callable[[str], Any]) -> dict[str, Any]:
    """``KEY=VALUE`` command-line items as a dict, each VALUE parsed as JSON when it is JSON, else kept as text;
    a malformed item goes to ``error`` (argparse's ``parser.error``) naming ``flag``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            error(f"{flag} needs KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "system": platform.system()}


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[str] | None = None) -> str:
    """Render rows (dicts) as a Markdown table; floats get 4 significant digits."""
    if not rows:
        return "(no rows)\n"
    cols = list(columns or rows[0].keys())

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write_report(
    out_dir: str | Path, name: str, results: dict[str, Any], rows: Sequence[dict[str, Any]], title: str = ""
) -> tuple[Path, Path]:
    """Write ``<out_dir>/<name>.json`` and ``<name>.md``; returns both paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    payload = {"benchmark": name, "machine": machine(), **results}
    json_path = out / f"{name}.json"
    json_path.write_text(json.dumps(payload, indent=2, default=float) + "\n")
    md_path = out / f"{name}.md"
    md_path.write_text(f"# {title or name}\n\n{markdown_table(rows)}\nMachine: {payload['machine']}\n")
    return json_path, md_path
