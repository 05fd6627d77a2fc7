"""Exit statuses and one-line error messages shared by every ``argus`` command.

A script that runs ``argus query`` or ``argus goal`` can tell the causes apart by the exit status alone;
docs/cli.md lists the table (generated from :data:`EXIT_CODES`).
"""

from __future__ import annotations

import re

OK = 0
FAILED = 1
USAGE = 2
NOT_FOUND = 3
UNREACHABLE = 4
NOT_INSTALLED = 5

EXIT_CODES: dict[int, str] = {
    OK: "done (a query answered, a goal accepted, a process stopped by SIGINT/SIGTERM)",
    FAILED: "the request was answered with a failure (a goal refused, a demo that did not finish) or the process "
    "stopped on an error",
    USAGE: "bad arguments or configuration (a wrong flag, a bad endpoint, a value out of range, a bad config file)",
    NOT_FOUND: "what was asked for does not exist (a node id not in the graph)",
    UNREACHABLE: "no answer: no router reachable at the endpoint, or nobody (mapper, robot) answered in time",
    NOT_INSTALLED: "the command needs the server install (pip install 'argus-scenegraph[server]' or make install)",
}
"""Every exit status an ``argus`` command returns, with its meaning."""

_RUST_DEBUG_MSG = re.compile(r'msg: "((?:[^"\\]|\\.)*)"')
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def one_line(e: BaseException) -> str:
    """A user-facing single line for ``e``: pydantic validation errors as ``field: message``, Zenoh's Rust
    debug text (``Json5Err(Message { msg: "...", ... })``) as its message, never a URL or a traceback."""
    errors = getattr(e, "errors", None)
    if callable(errors) and type(e).__name__ == "ValidationError":
        parts = []
        for err in errors():
            where = ".".join(str(x) for x in err.get("loc", ()))
            msg = str(err.get("msg", "invalid"))
            msg = msg.removeprefix("Value error, ")
            parts.append(f"{where}: {msg}" if where else msg)
        return "; ".join(parts) or type(e).__name__
    text = str(e).strip()
    if not text:
        return type(e).__name__
    inner = _RUST_DEBUG_MSG.search(text)
    if inner is not None:
        head = text[: text.find("Json5Err")] if "Json5Err" in text else ""
        text = head + inner.group(1).replace('\\"', '"')
    return _RUST_LOCATION.sub("", text.splitlines()[0]).strip()
