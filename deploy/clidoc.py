"""The CLI reference (docs/cli.md), generated from the argparse definitions of every ``argus`` command.

``python -m deploy.clidoc --write`` regenerates docs/cli.md; ``--check`` exits 1 when it has drifted (the docs
build and tests/test_docs.py run it). :func:`parse_only` parses a command line the way ``argus`` would,
without running the command: the docs test checks every ``argus`` line of README.md and docs/ with it.

Each command builds its parser inside its own ``main(argv)``; the parser is caught at its ``parse_args`` call
(which raises here instead of parsing), so nothing runs and no session opens.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from deploy.cli import COMMANDS, USAGE, main
from protocol.exits import EXIT_CODES

CLI_MD = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
WIDTH = "100"


class _Caught(Exception):
    def __init__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace | None = None) -> None:
        super().__init__(parser.prog)
        self.parser, self.namespace = parser, namespace


@contextlib.contextmanager
def _intercept(parse: bool) -> Iterator[None]:
    """Make every ``ArgumentParser.parse_args`` raise :class:`_Caught` (after parsing, when ``parse``)."""
    real = argparse.ArgumentParser.parse_args
    real_known = argparse.ArgumentParser.parse_known_args

    def fake(self: argparse.ArgumentParser, args: Any = None, namespace: Any = None) -> Any:
        if parse:
            raise _Caught(self, real(self, args, namespace))
        raise _Caught(self)

    def fake_known(self: argparse.ArgumentParser, args: Any = None, namespace: Any = None) -> Any:
        if parse:
            ns, _ = real_known(self, args, namespace)
            raise _Caught(self, ns)
        raise _Caught(self)

    argparse.ArgumentParser.parse_args = fake  # type: ignore[assignment,method-assign]
    argparse.ArgumentParser.parse_known_args = fake_known  # type: ignore[assignment,method-assign]
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH  # argparse wraps help text at $COLUMNS: the same page on every terminal
    try:
        yield
    finally:
        argparse.ArgumentParser.parse_args = real  # type: ignore[method-assign]
        argparse.ArgumentParser.parse_known_args = real_known  # type: ignore[method-assign]
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def parser_of(argv: list[str]) -> argparse.ArgumentParser | None:
    """The parser ``argus <argv>`` parses its arguments with (None: the command uses no argparse parser)."""
    with _intercept(parse=False), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(argv)
        except _Caught as c:
            return c.parser
    return None


def parse_only(argv: list[str]) -> argparse.Namespace | int:
    """Parse ``argus <argv>`` as the command would and stop there: the namespace, or the exit status of a
    command that returned before parsing (``--help`` listings, ``--version``). Raises SystemExit on bad
    arguments, like the command."""
    with _intercept(parse=True), contextlib.redirect_stdout(io.StringIO()):
        try:
            return main(argv)
        except _Caught as c:
            assert c.namespace is not None
            return c.namespace


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    out: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            out.update(action.choices)
    return out


def _help(parser: argparse.ArgumentParser) -> str:
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        return parser.format_help().rstrip()
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def _section(title: str, text: str, level: int = 2) -> str:
    return f"{'#' * level} `{title}`\n\n```text\n{text}\n```\n"


def _listing(argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        main(argv)
    return out.getvalue().rstrip()


def _edge_camera_extra() -> list[tuple[str, list[str]]]:
    return [("argus edge-camera calibrate", ["edge-camera", "calibrate", "--help"])]


def reference() -> str:
    """The whole of docs/cli.md."""
    width = max(len(n) for n in COMMANDS)
    listing = "\n".join(f"  {n.ljust(width)}  {h}" for n, (_, h) in COMMANDS.items())
    parts = [
        "# Command-line reference\n",
        "Generated from the argparse definitions by `python -m deploy.clidoc --write` (the docs build fails when "
        "this page is stale). After `make install` the command is `.venv/bin/argus`; `source .venv/bin/activate` "
        "puts `argus` on your PATH.\n",
        "## Exit status\n",
        "Every `argus` command exits with one of these (`protocol/exits.py`):\n",
        "| status | meaning |\n| --- | --- |\n" + "\n".join(f"| {code} | {text} |" for code, text in EXIT_CODES.items())
        + "\n",
        _section("argus", USAGE.format(commands=listing).rstrip()),
    ]
    for name in COMMANDS:
        if name == "bench":
            parts.append(_section("argus bench", _listing(["bench", "--help"])))
            # The bench command's own table, reached the way deploy.cli dispatches to it (by module name): deploy
            # does not import bench, which imports deploy.
            for bench in importlib.import_module(COMMANDS["bench"][0]).BENCHES:
                p = parser_of(["bench", bench, "--help"])
                if p is not None:
                    parts.append(_section(f"argus bench {bench}", _help(p), level=3))
            continue
        p = parser_of([name, "--help"])
        if p is None:
            parts.append(_section(f"argus {name}", _listing([name, "--help"])))
            continue
        parts.append(_section(f"argus {name}", _help(p)))
        for sub, sp in _subparsers(p).items():
            parts.append(_section(f"argus {name} {sub}", _help(sp), level=3))
        if name == "edge-camera":
            for title, argv in _edge_camera_extra():
                extra = parser_of(argv)
                if extra is not None:
                    parts.append(_section(title, _help(extra), level=3))
    return "\n".join(parts)


def main_cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.clidoc", description="Generate docs/cli.md.")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", action="store_true", help="regenerate docs/cli.md")
    g.add_argument("--check", action="store_true", help="exit 1 when docs/cli.md is stale")
    a = p.parse_args(argv)
    text = reference()
    if a.write:
        CLI_MD.write_text(text, encoding="utf-8")
        print(f"wrote {CLI_MD}")
        return 0
    if not CLI_MD.exists() or CLI_MD.read_text(encoding="utf-8") != text:
        print(f"{CLI_MD} is stale: python -m deploy.clidoc --write", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main_cli())
