"""The bar of the wire contract: a stranger with only ``eclipse-zenoh`` + ``msgpack`` (or only ``eclipse-zenoh``)
uses a live Argus site with nothing but the example code of docs/WIRE.md.

The examples are cut out of WIRE.md by this test and run verbatim in a fresh virtual environment whose
site-packages holds exactly those packages (linked from this interpreter's install: no download), with
``python -I``, outside the repository: Argus, numpy and pydantic are not importable there (asserted).
They read the snapshot, a node and a selection, follow deltas, and send a goal that a real robot agent
answers; the JSON variant does the same through the mapper's JSON view and the robot's JSON answers.
About 5 s on a quiet machine (oracle geometry, a small simulated room), so it runs in the fast tier.
"""

from __future__ import annotations

import ast
import importlib.metadata
import os
import re
import subprocess
import sys
import time
import venv
from pathlib import Path

from protocol.wire import WIRE_MD
from tests.support.procs import Proc, wait_for

SITE = "wire"
ROBOT = "robot0"
EXAMPLE = re.compile(r"```python\n# example: ([\w-]+)\n(.*?)```", re.S)
MSGPACK_SCRIPT = ["preamble", "snapshot", "node", "rooms", "follow", "goal"]
JSON_SCRIPT = ["json-preamble", "json-snapshot", "json-goal"]
STDLIB = set(sys.stdlib_module_names)


def examples() -> dict[str, str]:
    found = EXAMPLE.findall(WIRE_MD.read_text(encoding="utf-8"))
    out = dict(found)
    assert len(out) == len(found), "two WIRE.md examples share a name"
    return out


def script(names: list[str]) -> str:
    ex = examples()
    return "\n".join(f"# --- WIRE.md example: {n}\n{ex[n]}" for n in names)


def imported(code: str) -> set[str]:
    mods = set()
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Import):
            mods |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            mods.add(node.module.split(".")[0])
    return mods


# --- fast tier: the examples exist, compile and need nothing but zenoh (+ msgpack) -------------------
def test_wire_md_examples_compile_and_import_only_zenoh_msgpack_and_the_stdlib() -> None:
    ex = examples()
    assert set(MSGPACK_SCRIPT + JSON_SCRIPT) <= set(ex)
    assert set(ex) == set(MSGPACK_SCRIPT + JSON_SCRIPT), "a new WIRE.md example must be run by this test"
    compile(script(MSGPACK_SCRIPT), "wire-msgpack", "exec")
    compile(script(JSON_SCRIPT), "wire-json", "exec")
    assert imported(script(MSGPACK_SCRIPT)) - STDLIB == {"zenoh", "msgpack"}
    assert imported(script(JSON_SCRIPT)) - STDLIB == {"zenoh"}


# --- the bar: a real site, a bare venv -------------------------------------------------------------
def bare_venv(root: Path, distributions: list[str]) -> Path:
    """A venv (no pip) whose site-packages links exactly the top-level entries of ``distributions``."""
    venv.EnvBuilder(with_pip=False, symlinks=True).create(root)
    (site,) = root.glob("lib/python*/site-packages")
    for name in distributions:
        dist = importlib.metadata.distribution(name)
        tops = {Path(str(f)).parts[0] for f in dist.files or [] if not str(f).startswith("..")}
        for top in tops:
            src = Path(str(dist.locate_file(top)))
            if src.exists() and not (site / top).exists():
                (site / top).symlink_to(src, target_is_directory=src.is_dir())
    return root / "bin" / "python"


def run_isolated(python: Path, code: str, cwd: Path, env: dict[str, str], timeout: float = 120) -> str:
    path = cwd / "client.py"
    path.write_text(code, encoding="utf-8")
    r = subprocess.run([str(python), "-I", str(path)], cwd=str(cwd), env=env, capture_output=True, text=True,
                       timeout=timeout)
    assert r.returncode == 0, f"stdout:\n{r.stdout}\nstderr:\n{r.stderr}"
    return r.stdout


def check_isolation(python: Path, cwd: Path, present: list[str], absent: list[str]) -> None:
    for mod in present:
        subprocess.run([str(python), "-I", "-c", f"import {mod}"], cwd=str(cwd), check=True, timeout=60)
    for mod in absent:
        r = subprocess.run([str(python), "-I", "-c", f"import {mod}"], cwd=str(cwd), capture_output=True,
                           text=True, timeout=60)
        assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, f"{mod} is importable in the bare venv"


def snapshot_nodes(router: str) -> int:
    from deploy.query import QueryError, get_snapshot
    from protocol.keys import Keys
    from protocol.session import client, open_session

    with open_session(client(router)) as s:
        try:
            return len(get_snapshot(s, Keys(SITE), timeout_s=2.0).nodes)
        except QueryError:
            return -1


def test_a_stranger_uses_the_site_with_only_the_wire_md_examples(router: str, procs: list[Proc], tmp_path) -> None:  # noqa: ANN001
    t0 = time.monotonic()
    mapper = Proc(["mapper", "--connect", router, "--site", SITE, "--geometry", "oracle", "--segmenter", "sim",
                   "--embedder", "sim", "--set", "publish.snapshot_period_s=0", "--set", "torch_threads=1"])
    robot = Proc(["robot-agent", "--connect", router, "--site", SITE, "--id", ROBOT, "--body", "sim",
                  "--set", "body.oracle=true", "--set", "body.family=furnished_room", "--set", "body.width=320",
                  "--set", "body.height=240", "--time-scale", "20", "--set", "frames.idle_period_s=1"])
    procs += [mapper, robot]
    msgpack_py = bare_venv(tmp_path / "venv-msgpack", ["eclipse-zenoh", "msgpack"])
    json_py = bare_venv(tmp_path / "venv-json", ["eclipse-zenoh"])
    work = tmp_path / "work"
    work.mkdir()
    check_isolation(msgpack_py, work, ["zenoh", "msgpack"], ["protocol", "numpy", "pydantic", "deploy"])
    check_isolation(json_py, work, ["zenoh"], ["msgpack", "protocol", "numpy"])
    wait_for(lambda: snapshot_nodes(router) > 0, 120,
             what=f"a graph with nodes\nmapper:\n{mapper.output}\nrobot:\n{robot.output}")
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "ARGUS_CONNECT": router, "ARGUS_SITE": SITE,
           "ARGUS_ROBOT": ROBOT}

    out = run_isolated(msgpack_py, script(MSGPACK_SCRIPT), work, env)
    assert "encoding: application/msgpack;argus/graph_snapshot/" in out, out
    version, n_nodes = map(int, re.search(r"graph version (\d+): (\d+) nodes", out).groups())  # type: ignore[union-attr]
    assert n_nodes > 0, out
    assert re.search(r"^node \S+: .+ seen \d+ times$", out, re.M), out
    assert re.search(r"^embedding <f4 \[\d+\]: \[", out, re.M), out  # an array read without numpy
    assert re.search(r"^selection: [1-9]\d* node\(s\)", out, re.M), out
    assert re.search(r"^room_layer at graph version \d+: [1-9]\d* room\(s\)$", out, re.M), out
    assert re.search(r"^room room\d+: \w+ \(\d\.\d\d\), [\d.]+ m2, \d+ % seen, \d+ object\(s\)", out, re.M), out
    assert re.search(r"^room selection: \d+ node\(s\) in room\d+$", out, re.M), out
    deltas = [int(v) for v in re.findall(r"^delta v(\d+):", out, re.M)]
    assert deltas and deltas[0] > 0, out
    assert re.search(r"^goal my-goal-\d+: accepted=True reason=''$", out, re.M), out + robot.output

    print(out)
    out = run_isolated(json_py, script(JSON_SCRIPT), work, env)
    print(out)
    m = re.search(r"graph version (\d+): (\d+) nodes", out)
    assert m and int(m.group(1)) >= version and int(m.group(2)) > 0, out
    assert re.search(r"^node \S+: .+; [1-9]\d* node\(s\) labelled like it$", out, re.M), out
    # The robot answers the plain JSON goal: accepted, or refused with a reason (e.g. unreachable in this room).
    assert re.search(r"^goal json-goal-\d+: accepted=(True reason=''|False reason='.+')$", out, re.M), out
    print(f"stranger test took {time.monotonic() - t0:.1f} s")
