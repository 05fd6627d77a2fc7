"""``argus up``: launch-file parsing, health from liveliness, clean shutdown with no orphans."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import tomllib
from pathlib import Path

import pytest

from deploy.query import query_hint
from deploy.up import Health, LaunchFile, ProcessSpec, Stack, dump_toml, load_launch
from protocol.keys import Keys
from tests.support.procs import REPO, Proc, endpoint, free_port, wait_for


def _pid_gone(pid: int) -> bool:
    """True when ``pid`` no longer exists (or is only a zombie awaiting its reaper)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z"
    except OSError:
        return True


def _tiny_launch(tmp_path: Path, extra: str = "") -> tuple[Path, str]:
    """Two routers of one site (the second connects to the first): two processes, two tokens."""
    ep, ep2 = endpoint(free_port()), endpoint(free_port())
    text = f'''
site = "uptest"
endpoint = "{ep}"
stop_timeout_s = 5
[[process]]
name = "router"
command = "router"
args = ["--listen", "{{endpoint}}", "--site", "{{site}}"]
[[process]]
name = "edge"
command = "router"
args = ["--listen", "{ep2}", "--connect", "{{endpoint}}", "--site", "{{site}}"]
{extra}
'''
    path = tmp_path / "tiny.toml"
    path.write_text(text)
    return path, ep


def test_shipped_launch_files_parse() -> None:
    for path in sorted((REPO / "deploy" / "launch").glob("*.toml")):
        launch = load_launch(path)
        assert launch.process, path
        for p in launch.process:
            stack_argv = Stack(launch, path.parent).argv_for(p)
            assert stack_argv[3] == p.command
            for a in stack_argv:
                assert "0.0.0.0" not in a, "shipped configs use loopback only"  # noqa: S104 - asserts its absence
            if p.config is not None:
                assert (path.parent / p.config).is_file(), f"{path.name}: {p.config} missing"


CONFIG_MODELS = {
    "mapper": "mapper.config:MapperConfig",
    "planner": "planner.config:PlannerNodeConfig",
    "robot-agent": "robot_agent.config:RobotAgentConfig",
    "edge-camera": "edge_camera.config:EdgeCameraConfig",
}


def test_shipped_launch_settings_validate_against_each_process_config(tmp_path: Path) -> None:
    import importlib

    from protocol.tomlconfig import load_config

    for path in sorted((REPO / "deploy" / "launch").glob("*.toml")):
        launch = load_launch(path)
        stack = Stack(launch, path.parent)
        try:
            for p in launch.process:
                if p.settings is None or p.command not in CONFIG_MODELS:
                    continue
                module, _, name = CONFIG_MODELS[p.command].partition(":")
                try:
                    model = getattr(importlib.import_module(module), name)
                    cfg = load_config(model, Path(stack.argv_for(p)[-1]))
                except ImportError as e:  # a backend package not built yet in this checkout
                    pytest.skip(f"{module}: {e}")
                assert cfg.site == launch.site, f"{path.name}:{p.name}"
        finally:
            stack.stop()


def test_launch_validation(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="duplicate"):
        LaunchFile.model_validate({"process": [{"name": "a", "command": "x"}, {"name": "a", "command": "y"}]})
    with pytest.raises(ValueError, match="either config or settings"):
        ProcessSpec(name="a", command="mapper", config=Path("m.toml"), settings={"x": 1})
    with pytest.raises(ValueError):
        ProcessSpec(name="a/b", command="mapper")
    with pytest.raises(ValueError):
        LaunchFile.model_validate({"process": [{"name": "a", "command": "x", "bogus": 1}]})
    bad = tmp_path / "bad.toml"
    bad.write_text("[[process]\n")
    with pytest.raises(ValueError, match="cannot read"):
        load_launch(bad)


def test_settings_become_a_config_file_with_placeholders(tmp_path: Path) -> None:
    launch = LaunchFile.model_validate({
        "site": "s1", "endpoint": "tcp/127.0.0.1:9999", "world": {"family": "furnished_room", "seed": 3},
        "process": [{"name": "m", "command": "mapper", "args": ["--connect", "{endpoint}"],
                     "settings": {"site": "{site}", "zenoh": {"connect": ["{endpoint}"]}, "rate": 2.5,
                                  "on": True, "names": ["a", "b"], "seed": "{seed}", "fam": "{family}"}}],
    })
    stack = Stack(launch, tmp_path)
    argv = stack.argv_for(launch.process[0])
    assert argv[3:6] == ["mapper", "--connect", "tcp/127.0.0.1:9999"] and argv[6] == "--config"
    written = tomllib.loads(Path(argv[7]).read_text())
    assert written == {"site": "s1", "zenoh": {"connect": ["tcp/127.0.0.1:9999"]}, "rate": 2.5, "on": True,
                       "names": ["a", "b"], "seed": 3, "fam": "furnished_room"}
    stack.stop()


def test_dump_toml_round_trip() -> None:
    data = {"a": 1, "b": "x\"y", "c": [1.5, 2], "t": {"u": {"v": False}, "w": 'q\\n'}}
    assert tomllib.loads(dump_toml(data)) == data


def test_health_counts_roles_and_pinned_ids() -> None:
    specs = [ProcessSpec(name="r", command="router"), ProcessSpec(name="c1", command="edge-camera"),
             ProcessSpec(name="c2", command="edge-camera", node_id="cam_b"),
             ProcessSpec(name="log", command="query", role="")]
    h = Health(Keys("s"))
    assert h.missing(specs) == ["r", "c1", "c2"]
    h.alive = {("router", "z1"), ("edge-camera", "cam_b")}
    assert h.missing(specs) == ["c1"]
    h.alive.add(("edge-camera", "cam_a"))
    assert h.missing(specs) == []
    h.alive.discard(("edge-camera", "cam_b"))
    assert h.missing(specs) == ["c2"]


def _port_free(port: int) -> bool:
    """Nothing listens on the port (SO_REUSEADDR: connections in TIME_WAIT are not a holder)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM])
def test_up_starts_reports_healthy_and_stops_all(tmp_path: Path, procs: list[Proc], how: signal.Signals) -> None:
    launch, _ = _tiny_launch(tmp_path)
    port = free_port()  # --port moves the launch file's router endpoint
    ports = [port, int(load_launch(launch).process[1].args[1].rsplit(":", 1)[1])]
    ready = tmp_path / "ready"
    up = Proc(["up", str(launch), "--port", str(port), "--ready-file", str(ready), "--log-dir", str(tmp_path / "logs")])
    procs.append(up)
    wait_for(ready.exists, timeout=40, what="stack healthy")
    pids = [int(p) for p in ready.read_text().split(",")]
    assert len(pids) == 2 and all(not _pid_gone(p) for p in pids)
    assert "[up] health: all 2 processes up" in up.output
    with contextlib.chdir(REPO):  # the hint names `argus`, or .venv/bin/argus where PATH finds another (Proc's cwd)
        hint = query_hint(endpoint(port), "uptest")
    assert hint.endswith(f"argus query --connect {endpoint(port)} --site uptest snapshot")
    assert f"[up] read the graph: {hint}" in up.output
    assert not any(_port_free(p) for p in ports)  # both routers listen
    wait_for(lambda: "[router]" in up.output and "[edge]" in up.output, timeout=10, what="prefixed logs")
    assert (tmp_path / "logs" / "router.log").read_text().strip()

    os.kill(up.popen.pid, how)
    assert up.wait(30) == 0, up.output
    assert "[up] all stopped" in up.output
    for pid in pids:
        assert _pid_gone(pid), f"process {pid} survived argus up"
        with pytest.raises(ProcessLookupError):
            os.killpg(pid, 0)  # nothing left in its process group either
    assert all(_port_free(p) for p in ports), "a port of the stack is still held"


def test_up_killed_hard_leaves_no_orphans(tmp_path: Path, procs: list[Proc]) -> None:
    launch, _ = _tiny_launch(tmp_path)
    ready = tmp_path / "ready"
    up = Proc(["up", str(launch), "--ready-file", str(ready)])
    procs.append(up)
    wait_for(ready.exists, timeout=40, what="stack healthy")
    pids = [int(p) for p in ready.read_text().split(",")]
    os.kill(up.popen.pid, signal.SIGKILL)  # no chance to clean up: the kernel kills the children (PDEATHSIG)
    up.wait(10)
    try:
        wait_for(lambda: all(_pid_gone(p) for p in pids), timeout=20, what="children exit after launcher death")
    finally:
        for p in pids:  # never leave a stray router behind, even when the assertion fails
            if not _pid_gone(p):
                print(p, Path(f"/proc/{p}/status").read_text()[:400])
                os.killpg(p, signal.SIGKILL)


def test_required_process_failure_stops_the_stack_after_restarts(tmp_path: Path, procs: list[Proc]) -> None:
    extra = '''
[[process]]
name = "broken"
command = "router"
args = ["--config", "/nonexistent/zenoh.json5"]
restart = "on-failure"
max_restarts = 1
'''
    launch, _ = _tiny_launch(tmp_path, extra)
    up = Proc(["up", str(launch)])
    procs.append(up)
    assert up.wait(60) == 1, up.output
    assert "broken exited with code 2; restart 1/1" in up.output
    assert "required process(es) ended: broken" in up.output and "[up] all stopped" in up.output


def test_dry_run_prints_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from deploy.up import main

    launch, ep = _tiny_launch(tmp_path)
    assert main([str(launch), "--dry-run", "--only", "edge"]) == 0
    out = capsys.readouterr().out
    assert "[edge]" in out and f"--connect {ep}" in out and "[router]" not in out
    assert main([str(launch), "--only", "nope"]) == 2
    assert main([str(launch), "--dry-run", "--only", "edge", "--port", "7999"]) == 0
    assert "--connect tcp/127.0.0.1:7999" in capsys.readouterr().out
    assert main([str(launch), "--dry-run", "--endpoint", "tcp/127.0.0.1:7998"]) == 0
    assert "--listen tcp/127.0.0.1:7998" in capsys.readouterr().out
    assert main([str(launch), "--port", "70000"]) == 2


def test_up_killed_hard_then_started_again_cleans_temp_folder_and_ready_file(tmp_path: Path,
                                                                           procs: list[Proc]) -> None:
    """SIGKILL leaves the temp folder and the ready file; the next start removes both (no stale pids)."""
    launch, _ = _tiny_launch(tmp_path)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    ready = tmp_path / "ready"
    env = {"TMPDIR": str(tmp)}
    up = Proc(["up", str(launch), "--ready-file", str(ready)], env=env)
    procs.append(up)
    wait_for(ready.exists, timeout=40, what="stack healthy")
    old = ready.read_text()
    (stale,) = list(tmp.glob("argus-up-*"))
    os.kill(up.popen.pid, signal.SIGKILL)
    up.wait(10)
    wait_for(lambda: all(_pid_gone(int(p)) for p in old.split(",")), timeout=20, what="children gone")
    assert stale.exists() and ready.exists()  # what a SIGKILL leaves behind

    again = Proc(["up", str(launch), "--ready-file", str(ready)], env=env)
    procs.append(again)
    wait_for(lambda: not stale.exists(), timeout=20, what="the dead launcher's temp folder removed")
    def fresh() -> bool:  # the new launcher removes the stale file at any moment: read it once, or not at all
        try:
            return ready.read_text() != old
        except FileNotFoundError:
            return False

    wait_for(fresh, timeout=40, what="a fresh ready file")
    os.kill(again.popen.pid, signal.SIGINT)
    assert again.wait(30) == 0, again.output
    assert not ready.exists(), "a stopped stack left its ready file"
    assert not list(tmp.glob("argus-up-*")), "a stopped stack left its temp folder"
