"""The README and the docs site: short README, fresh generated pages, and every ``argus`` command they print
parses as printed (the quick ones, ``--help`` and ``--version``, run)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from deploy.clidoc import CLI_MD, parse_only, reference

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SH_BLOCK = re.compile(r"```sh\n(.*?)```", re.S)
INLINE = re.compile(r"`(argus [^`]+)`")
PLACEHOLDER = re.compile(r"[<>\[\]|]|\.\.\.|\b(DIR|FILE|F|N|NAME|S|E|PORT|ID)\b|/path|\bfoo\b")


def commands() -> list[tuple[str, str]]:
    """(page, command) for every ``argus`` / ``make`` line of a ``sh`` block and every inline ``argus ...`` span
    without a placeholder; docs/cli.md (generated help texts) is not a page of examples."""
    out = []
    for page in PAGES:
        if page == CLI_MD:
            continue
        text = page.read_text(encoding="utf-8")
        found = [line.split(" #")[0].strip() for block in SH_BLOCK.findall(text) for line in block.splitlines()]
        # Inline spans of two words name a command (`argus query`), of three ending in a flag name a flag
        # (`argus up --secure`): neither is a command line.
        found += [" ".join(m.split()) for m in INLINE.findall(text)
                  if len(m.split()) > 3 or (len(m.split()) == 3 and not m.split()[-1].startswith("-"))]
        out += [(page.name, c) for c in found if c.startswith(("argus ", "make ")) and not PLACEHOLDER.search(c)]
    return sorted(set(out))


def test_readme_is_short() -> None:
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 150


def test_cli_reference_is_fresh() -> None:
    assert CLI_MD.read_text(encoding="utf-8") == reference(), "stale docs/cli.md: python -m deploy.clidoc --write"


def test_there_are_commands_to_check() -> None:
    found = {c for _, c in commands()}
    assert {"make demo", "argus query snapshot", "argus demo --port 7447"} <= found, found
    assert len(found) > 40


@pytest.mark.parametrize(("page", "command"), commands())
def test_documented_command_parses_as_printed(page: str, command: str) -> None:
    argv = shlex.split(command)
    if argv[0] == "make":
        targets = set(re.findall(r"^([a-z-]+):", (ROOT / "Makefile").read_text(), re.M))
        assert set(argv[1:]) <= targets, f"{page}: {command}"
        return
    try:
        result = parse_only(argv[1:])
    except SystemExit as e:  # --help prints and exits 0; a bad flag exits 2
        assert e.code in (0, None), f"{page}: {command!r} does not parse (exit {e.code})"
        return
    assert not isinstance(result, int) or result == 0, f"{page}: {command!r} exits {result}"


@pytest.mark.integration
def test_quick_commands_run_as_printed() -> None:
    quick = sorted({c for _, c in commands() if c.startswith("argus ") and c.endswith(("--help", "--version"))})
    quick += ["argus --version", "argus --help", "argus bench --help"]
    for command in quick:
        r = subprocess.run([sys.executable, "-m", "deploy.cli", *shlex.split(command)[1:]], cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0 and r.stdout.strip(), f"{command}: {r.stderr}"


@pytest.mark.integration
def test_the_site_builds_strict(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=120, env={"NO_MKDOCS_2_WARNING": "1",
                                                                                   "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stdout + r.stderr
    assert (tmp_path / "site" / "cli.html").exists() and (tmp_path / "site" / "WIRE.html").exists()
