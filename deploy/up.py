"""``argus up``: start a whole Argus stack from one launch file.

Every entry of the launch file (router, mapper, planner, robots, edge cameras, ...) runs as its own
``python -m deploy.cli <command> ...`` process in its own process group. Their output comes back line
by line with a ``[name]`` prefix, health comes from the liveliness tokens every Argus process declares
(``argus/<site>/alive/<role>/<id>``), and Ctrl-C / SIGTERM stops them all: SIGINT to every process
group (the router last), a grace period, then SIGKILL for stragglers, so no orphan survives.

Example::

    argus up deploy/launch/demo.toml
    argus up deploy/launch/multi-machine.toml --only router,mapper,planner   # this machine's share

Launch file (TOML)::

    site = "default"
    endpoint = "tcp/127.0.0.1:7447"      # the router every process connects to

    [[process]]
    name = "router"
    command = "router"
    args = ["--listen", "{endpoint}"]

    [[process]]
    name = "mapper"
    command = "mapper"
    config = "mapper.toml"               # passed as --config (relative to the launch file)
    # or an inline table, written to a temporary TOML file and passed as --config:
    # [process.settings]
    # ...

Strings in ``args`` and ``settings`` may use ``{endpoint}``, ``{site}``, ``{launch_dir}`` and, with a
``[world]`` table (``family``, ``seed`` of the simulated scene), ``{family}`` and ``{seed}``; a setting
that is exactly ``"{seed}"`` becomes an integer.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from deploy.query import query_hint
from deploy.secure import SecureSite, SecuritySpec, prepare
from protocol.keys import Keys, validate_id
from protocol.runtime import kill_with_parent
from sim.config import Family

# The liveliness role a command declares (``alive/<role>/<id>``) when it differs from the command
# name; used when a launch entry does not name its role.
DEFAULT_ROLES: dict[str, str] = {}


class WorldSpec(BaseModel):
    """The embedded simulated world a stack runs in (for sim sources and for scoring)."""

    model_config = ConfigDict(extra="forbid")
    family: Family = Field(
        default="apartment", description="scene family ({family} in args/settings)"
    )
    seed: int = Field(default=0, ge=0, description="scene seed ({seed} in args/settings)")


class ProcessSpec(BaseModel):
    """One process of a stack."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(description="unique name; prefixes the process's log lines, e.g. [mapper]")
    command: str = Field(description="argus sub-command: router, mapper, planner, robot-agent, ...")
    args: list[str] = Field(default_factory=list, description="extra arguments ({endpoint} expanded)")
    config: Path | None = Field(
        default=None, description="config file passed as --config (relative: from the launch file's folder)"
    )
    settings: dict[str, Any] | None = Field(
        default=None, description="inline config table, written to a temporary TOML file passed as --config"
    )
    role: str | None = Field(
        default=None, description="liveliness role it declares (default: from the command); '' = none"
    )
    node_id: str | None = Field(default=None, description="liveliness id to expect exactly (default: any id)")
    host: str = Field(default="local", description="where it runs (documentation for multi-machine files)")
    env: dict[str, str] = Field(default_factory=dict, description="extra environment variables")
    restart: Literal["never", "on-failure", "always"] = Field(
        default="never", description="restart policy when the process exits on its own"
    )
    max_restarts: int = Field(default=3, ge=0, description="restarts allowed before giving up")
    required: bool = Field(
        default=True, description="when it exits for good, stop the whole stack (false: carry on without it)"
    )

    @field_validator("name")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        return validate_id(v, "process name")

    @model_validator(mode="after")
    def _one_config(self) -> ProcessSpec:
        if self.config is not None and self.settings is not None:
            raise ValueError(f"process {self.name!r}: give either config or settings, not both")
        return self

    @property
    def expected_role(self) -> str | None:
        role = self.role if self.role is not None else DEFAULT_ROLES.get(self.command, self.command)
        return role or None


class LaunchFile(BaseModel):
    """A whole stack: the site, the router endpoint and the processes."""

    model_config = ConfigDict(extra="forbid")
    site: str = Field(default="default", description="Argus site name (key prefix argus/<site>/...)")
    endpoint: str = Field(
        default="tcp/127.0.0.1:7447", description="router endpoint the launcher (and {endpoint}) connect to"
    )
    health_timeout_s: float = Field(default=120.0, gt=0, description="warn when not all roles are up by then")
    stop_timeout_s: float = Field(default=10.0, gt=0, description="grace after SIGINT before SIGKILL")
    world: WorldSpec | None = Field(
        default=None, description="simulated world, if the stack runs on sim/ (demo scoring uses it)"
    )
    process: list[ProcessSpec] = Field(description="the processes, started in this order")
    security: SecuritySpec | None = Field(
        default=None, description="[security]: TLS, a certificate and password per process and an ACL "
        "(as argus up --secure; docs/SECURITY.md)",
    )

    @model_validator(mode="after")
    def _unique(self) -> LaunchFile:
        names = [p.name for p in self.process]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate process names: {sorted(dup)}")
        if not self.process:
            raise ValueError("a launch file needs at least one [[process]]")
        validate_id(self.site, "site")
        return self


def load_launch(path: Path) -> LaunchFile:
    """Read and validate a launch file (raises ``ValueError`` with the reason)."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"cannot read launch file {path}: {e}") from None
    return LaunchFile.model_validate(data)


def with_endpoint(launch: LaunchFile, endpoint: str | None = None, port: int | None = None) -> LaunchFile:
    """``launch`` with its router endpoint replaced (``endpoint``) or moved to another ``port``."""
    new = endpoint or launch.endpoint
    if port is not None:
        if not 0 < port < 65536:
            raise ValueError(f"--port {port} is not a TCP port")
        head, sep, _ = new.rpartition(":")
        if not sep or "/" not in head:
            raise ValueError(f"cannot set a port on endpoint {new!r} (expected proto/host:port)")
        new = f"{head}:{port}"
    return launch if new == launch.endpoint else launch.model_copy(update={"endpoint": new})


def _expand(value: Any, subs: dict[str, str]) -> Any:
    if value == "{seed}" and "seed" in subs:
        return int(subs["seed"])
    if isinstance(value, str):
        for k, v in subs.items():
            value = value.replace("{" + k + "}", v)
        return value
    if isinstance(value, list):
        return [_expand(v, subs) for v in value]
    if isinstance(value, dict):
        return {k: _expand(v, subs) for k, v in value.items()}
    return value


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else _toml_value(k)


def dump_toml(data: dict[str, Any]) -> str:
    """Write a plain dict (scalars, lists, nested tables) as TOML (enough for config files)."""
    lines: list[str] = []

    def table(prefix: str, d: dict[str, Any]) -> None:
        subs = {k: v for k, v in d.items() if isinstance(v, dict)}
        for k, v in d.items():
            if not isinstance(v, dict):
                lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
        for k, v in subs.items():
            name = f"{prefix}.{_toml_key(k)}" if prefix else _toml_key(k)
            lines.append("")
            lines.append(f"[{name}]")
            table(name, v)

    table("", data)
    return "\n".join(lines) + "\n"


TMP_PREFIX = "argus-up-"


def _pid_alive(pid: int) -> bool:
    return _exists(os.kill, pid)


def sweep_stale_tmp_dirs(root: Path | None = None) -> list[Path]:
    """Remove the temporary folders (``argus-up-<pid>-*``) of launchers that died without cleaning up.

    A SIGKILLed ``argus up`` cannot remove its folder of generated configs; the next start does, for
    every folder of this user whose launcher pid is gone. Returns the folders removed.
    """
    root = Path(tempfile.gettempdir() if root is None else root)
    removed: list[Path] = []
    for d in root.glob(f"{TMP_PREFIX}*-*"):
        pid = d.name[len(TMP_PREFIX):].split("-", 1)[0]
        try:
            mine = d.is_dir() and not d.is_symlink() and d.stat().st_uid == os.getuid()
        except OSError:
            continue
        if mine and pid.isdigit() and not _pid_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


def _group_alive(pgid: int) -> bool:
    return _exists(os.killpg, pgid)


def _exists(send: Callable[[int, int], None], ident: int) -> bool:
    """Whether a process (``os.kill``) or process group (``os.killpg``) exists: signal 0 probes it."""
    try:
        send(ident, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, it is just not ours
        return True
    return True


class Child:
    """One running process of the stack (a process-group leader) and its log reader."""

    def __init__(self, spec: ProcessSpec, argv: list[str], env: dict[str, str], emit: Callable[[str], None]):
        self.spec = spec
        self.argv = argv
        self.restarts = 0
        self._env = env
        self._emit = emit
        self.popen: subprocess.Popen[str] | None = None
        self._reader: threading.Thread | None = None
        self.started_at = 0.0
        self.finished = False

    def start(self) -> None:
        self.finished = False
        self.popen = subprocess.Popen(
            self.argv,
            env=self._env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            bufsize=1,
            start_new_session=True,
            preexec_fn=kill_with_parent(),  # if argus up dies without cleaning up, no child is orphaned
        )
        self.started_at = time.monotonic()
        self._reader = threading.Thread(target=self._read, args=(self.popen,), daemon=True,
                                        name=f"log-{self.spec.name}")
        self._reader.start()

    def _read(self, popen: subprocess.Popen[str]) -> None:
        assert popen.stdout is not None
        prefix = f"[{self.spec.name}] "
        for line in popen.stdout:
            self._emit(prefix + line.rstrip("\n"))

    @property
    def pid(self) -> int | None:
        return self.popen.pid if self.popen is not None else None

    def poll(self) -> int | None:
        return None if self.popen is None else self.popen.poll()

    def signal_group(self, sig: int) -> None:
        if self.popen is None:
            return
        try:
            os.killpg(self.popen.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def group_alive(self) -> bool:
        return self.popen is not None and (self.popen.poll() is None or _group_alive(self.popen.pid))

    def join_reader(self, timeout: float = 2.0) -> None:
        if self._reader is not None:
            self._reader.join(timeout)


class Health:
    """Liveliness-token view of a site: which ``(role, id)`` pairs are alive right now."""

    def __init__(self, keys: Keys) -> None:
        self.keys = keys
        self._lock = threading.Lock()
        self.alive: set[tuple[str, str]] = set()
        self.changed = threading.Event()
        self.events: list[tuple[str, str, str]] = []  # (+ or -, role, id)

    def on_sample(self, sample: Any) -> None:
        import zenoh

        try:
            role, node_id = self.keys.parse_alive(str(sample.key_expr))
        except ValueError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add((role, node_id))
                self.events.append(("+", role, node_id))
            else:
                self.alive.discard((role, node_id))
                self.events.append(("-", role, node_id))
        self.changed.set()

    def take_events(self) -> list[tuple[str, str, str]]:
        with self._lock:
            out, self.events = self.events, []
            return out

    def missing(self, specs: list[ProcessSpec]) -> list[str]:
        """Names of the processes whose role (and id, if pinned) has no live token."""
        with self._lock:
            alive = set(self.alive)
        missing: list[str] = []
        pinned = {(s.expected_role, s.node_id) for s in specs if s.node_id and s.expected_role}
        free_ids: dict[str, list[str]] = {}
        for role, nid in alive:
            if (role, nid) not in pinned:
                free_ids.setdefault(role, []).append(nid)
        for s in specs:
            expected = s.expected_role
            if expected is None:
                continue
            if s.node_id:
                if (expected, s.node_id) not in alive:
                    missing.append(s.name)
            elif free_ids.get(expected):
                free_ids[expected].pop()
            else:
                missing.append(s.name)
        return missing

    def summary(self) -> str:
        with self._lock:
            alive = sorted(self.alive)
        return ", ".join(f"{r}/{i}" for r, i in alive) or "(none)"


def _tcp_host_port(endpoint: str) -> tuple[str, int] | None:
    if not endpoint.startswith(("tcp/", "tls/")):  # both listen on a TCP port
        return None
    host, _, port = endpoint[4:].rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        return None


def _port_open(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.3)
        return s.connect_ex((host, port)) == 0


class Stack:
    """A running stack. ``start()``, then ``wait_healthy()``, ``step()`` in a loop, and ``stop()``.

    ``emit`` receives every output line (the launcher's own lines are prefixed ``[up]``).
    """

    def __init__(
        self,
        launch: LaunchFile,
        launch_dir: Path,
        only: list[str] | None = None,
        emit: Callable[[str], None] | None = None,
        log_dir: Path | None = None,
        python: str = sys.executable,
        extra_env: dict[str, str] | None = None,
        secure: SecureSite | None = None,
    ) -> None:
        self.launch = launch
        self.launch_dir = Path(launch_dir).resolve()
        self.keys = Keys(launch.site)
        names = [p.name for p in launch.process]
        if only:
            unknown = sorted(set(only) - set(names))
            if unknown:
                raise ValueError(f"--only names not in the launch file: {unknown} (have {names})")
        self.local = [p for p in launch.process if not only or p.name in only]
        self._print_lock = threading.Lock()
        self._log_files: dict[str, Any] = {}
        self._user_emit = emit or (lambda line: print(line, flush=True))
        self.log_dir = log_dir
        self.python = python
        self.extra_env = extra_env or {}
        self.secure = secure
        self.children: list[Child] = []
        self.health = Health(self.keys)
        self._session: Any = None
        self._liveliness_sub: Any = None
        sweep_stale_tmp_dirs()
        self._tmp = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{os.getpid()}-"))
        self.healthy_at: float | None = None
        self.failed: list[str] = []
        self.started_at = time.monotonic()

    # --- output -------------------------------------------------------------------------------
    def emit(self, line: str) -> None:
        with self._print_lock:
            self._user_emit(line)
            if self.log_dir is not None:
                name = line[1 : line.index("]")] if line.startswith("[") and "]" in line else "up"
                f = self._log_files.get(name)
                if f is None:
                    self.log_dir.mkdir(parents=True, exist_ok=True)
                    f = self._log_files[name] = open(self.log_dir / f"{name}.log", "a")  # noqa: SIM115
                f.write(line + "\n")
                f.flush()

    def say(self, msg: str) -> None:
        self.emit(f"[up] {msg}")

    # --- commands -----------------------------------------------------------------------------
    def argv_for(self, spec: ProcessSpec) -> list[str]:
        """The full command line of one process."""
        subs = self.substitutions()
        argv = [self.python, "-m", "deploy.cli", spec.command, *_expand(spec.args, subs)]
        if spec.config is not None:
            cfg = Path(_expand(str(spec.config), subs))
            argv += ["--config", str(cfg if cfg.is_absolute() else self.launch_dir / cfg)]
        elif spec.settings is not None:
            path = self._tmp / f"{spec.name}.toml"
            path.write_text(dump_toml(_expand(spec.settings, subs)))
            argv += ["--config", str(path)]
        if self.secure is not None:  # TLS + this process's own login (its Zenoh config file)
            if spec.command == "router":
                argv += ["--config", str(self.secure.router_file)]
            else:
                argv += ["--zenoh-config", str(self.secure.client_file(spec.name))]
        return argv

    def substitutions(self) -> dict[str, str]:
        subs = {"endpoint": self.launch.endpoint, "site": self.launch.site, "launch_dir": str(self.launch_dir)}
        if self.launch.world is not None:
            subs.update(family=self.launch.world.family, seed=str(self.launch.world.seed))
        return subs

    def _env_for(self, spec: ProcessSpec) -> dict[str, str]:
        env = dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"
        # Child processes import the argus packages from the same tree as the launcher.
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.update(self.extra_env)
        env.update(spec.env)
        return env

    # --- lifecycle ----------------------------------------------------------------------------
    def start(self) -> None:
        """Start every local process in launch-file order (a local router first, waited for)."""
        for spec in self.local:
            child = Child(spec, self.argv_for(spec), self._env_for(spec), self.emit)
            self.say(f"start {spec.name}: {shlex.join(child.argv[2:])}")
            child.start()
            self.children.append(child)
            if spec.command == "router":
                self._wait_router(child)
        self._open_health()

    def _wait_router(self, child: Child, timeout: float = 20.0) -> None:
        hp = _tcp_host_port(self.launch.endpoint)
        if hp is None:
            return
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and child.poll() is None:
            if _port_open(*hp):
                return
            time.sleep(0.05)
        if child.poll() is not None:
            raise RuntimeError(
                f"router exited with code {child.poll()} before listening on {self.launch.endpoint}")
        self.say(f"warning: router not listening on {self.launch.endpoint} after {timeout:.0f}s")

    def _open_health(self, timeout: float = 20.0) -> None:
        from protocol.session import ZenohSettings, open_session

        settings = ZenohSettings(mode="client", connect=[self.launch.endpoint],
                                 config_file=None if self.secure is None else self.secure.client_file("launcher"))
        deadline = time.monotonic() + timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                self._session = open_session(settings)
                break
            except Exception as e:  # noqa: BLE001 - router may not be up yet (remote): retry
                last = e
                time.sleep(0.5)
        if self._session is None:
            self.say(f"warning: no health view, cannot reach {self.launch.endpoint}: {last}")
            return
        self._liveliness_sub = self._session.liveliness().declare_subscriber(
            self.keys.all_alive, self.health.on_sample, history=True
        )

    @property
    def expected(self) -> list[ProcessSpec]:
        """Every process of the launch file (liveliness is site-wide, so remote ones count too)."""
        return self.launch.process

    def wait_healthy(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Block until every expected role is alive (True), a timeout, a stop request or a failure."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if stop is not None and stop.is_set():
                return False
            if not self.step():
                return False
            if self.healthy_at is not None:
                return True
            self.health.changed.wait(0.2)
        return self.healthy_at is not None

    def step(self) -> bool:
        """Poll children (restarts, failures) and health. False when a required process ended for good."""
        self._check_health()
        ok = True
        for child in self.children:
            code = child.poll()
            if code is None or child.finished:
                continue
            spec = child.spec
            want = spec.restart == "always" or (spec.restart == "on-failure" and code != 0)
            if want and child.restarts < spec.max_restarts:
                child.restarts += 1
                self.say(f"{spec.name} exited with code {code}; restart {child.restarts}/{spec.max_restarts}")
                child.join_reader(1.0)
                child.start()
                continue
            child.finished = True
            self.say(f"{spec.name} exited with code {code}")
            if spec.required:
                self.failed.append(spec.name)
                ok = False
        return ok

    def _check_health(self) -> None:
        self.health.changed.clear()
        for sign, role, nid in self.health.take_events():
            if sign == "-" and self.healthy_at is not None:
                self.say(f"health: {role}/{nid} went away")
        missing = self.health.missing(self.expected)
        if not missing and self.healthy_at is None:
            self.healthy_at = time.monotonic()
            roles = sorted({s.expected_role for s in self.expected if s.expected_role})
            self.say(
                f"health: all {len(self.expected)} processes up after "
                f"{self.healthy_at - self.started_at:.1f}s"
                f" (roles {', '.join(roles)}; alive: {self.health.summary()})"
            )
            self.say(f"read the graph: {query_hint(self.launch.endpoint, self.launch.site)}")
        elif missing and self.healthy_at is not None:
            self.healthy_at = None
            self.say(f"health: degraded, missing {', '.join(missing)}")

    def missing(self) -> list[str]:
        return self.health.missing(self.expected)

    def stop(self, timeout: float | None = None) -> None:
        """SIGINT every process group (router last), wait, SIGKILL stragglers; close the health view."""
        timeout = self.launch.stop_timeout_s if timeout is None else timeout
        if self._liveliness_sub is not None:
            try:
                self._liveliness_sub.undeclare()
            except Exception:  # noqa: BLE001 - a closing session must not stop the children being stopped
                pass
        if self._session is not None:
            try:
                self._session.close()
            except Exception:  # noqa: BLE001 - as above
                pass
            self._session = None
        routers = [c for c in self.children if c.spec.command == "router"]
        others = [c for c in self.children if c.spec.command != "router"]
        for batch in (others, routers):
            for c in batch:
                c.signal_group(signal.SIGINT)
            self._wait_groups(batch, timeout)
            for c in batch:
                if c.group_alive():
                    self.say(f"{c.spec.name} did not stop in {timeout:.0f}s: SIGKILL")
                    c.signal_group(signal.SIGKILL)
            self._wait_groups(batch, 5.0)
        for c in self.children:
            if c.popen is not None:
                try:
                    c.popen.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    pass
            c.join_reader(2.0)
        for f in self._log_files.values():
            f.close()
        self._log_files.clear()
        shutil.rmtree(self._tmp, ignore_errors=True)

    @staticmethod
    def _wait_groups(children: list[Child], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for c in children:
                c.poll()  # reap the leader so its group can disappear
            if not any(c.group_alive() for c in children):
                return
            time.sleep(0.05)

    def pids(self) -> list[int]:
        return [c.pid for c in self.children if c.pid is not None]


def run(
    launch_path: Path,
    only: list[str] | None = None,
    duration_s: float | None = None,
    log_dir: Path | None = None,
    ready_file: Path | None = None,
    dry_run: bool = False,
    endpoint: str | None = None,
    port: int | None = None,
    secure: bool = False,
    secure_dir: Path | None = None,
) -> int:
    """Start the stack of ``launch_path`` and keep it up until SIGINT/SIGTERM (or ``duration_s``).

    ``endpoint`` replaces the launch file's router endpoint; ``port`` only its port. ``secure`` (or an
    enabled ``[security]`` table): TLS, per-process logins and an ACL (deploy/secure.py).
    """
    from protocol.runtime import install_stop_handlers

    launch = with_endpoint(load_launch(launch_path), endpoint, port)
    site = _secure_site(launch, launch_path.parent, only, secure, secure_dir)
    stack = Stack(launch, launch_path.parent, only=only, log_dir=log_dir, secure=site)
    if site is not None:
        stack.say(f"secure: TLS on {launch.endpoint}, one login per process, ACL; material in {site.dir}")
    if dry_run:
        for spec in stack.local:
            argv = stack.argv_for(spec)
            print(f"[{spec.name}] ({spec.host}) {shlex.join(argv)}")
            if spec.settings is not None:  # the generated config file is temporary: show it
                cfg = Path(argv[argv.index("--config") + 1])
                print("\n".join(f"    | {line}" for line in cfg.read_text().splitlines()))
        stack.stop()
        return 0
    stop = install_stop_handlers()
    code = 0
    if ready_file is not None:  # left by a launcher that was killed: it names processes long gone
        ready_file.unlink(missing_ok=True)
    try:
        stack.start()
        stack.say(f"{len(stack.children)} processes started; waiting for liveliness of "
                  f"{len(stack.expected)} (Ctrl-C stops all)")
        deadline = None if duration_s is None else time.monotonic() + duration_s
        warned = False
        while not stop.is_set():
            if not stack.step():
                stack.say(f"required process(es) ended: {', '.join(stack.failed)}; stopping the stack")
                code = 1
                break
            if stack.healthy_at is not None and ready_file is not None and not ready_file.exists():
                # Atomic: a watcher polling for the file must never read it half-written.
                tmp = ready_file.with_name(ready_file.name + ".tmp")
                tmp.write_text(",".join(str(p) for p in stack.pids()))
                os.replace(tmp, ready_file)
            waited_s = time.monotonic() - stack.started_at
            if not warned and stack.healthy_at is None and waited_s > launch.health_timeout_s:
                warned = True
                stack.say(f"health: still missing after {waited_s:.0f}s: {', '.join(stack.missing())}")
            if deadline is not None and time.monotonic() >= deadline:
                stack.say(f"duration of {duration_s:g}s reached")
                break
            stop.wait(0.2)
    except Exception as e:  # noqa: BLE001 - any launcher failure still stops what was started
        stack.say(f"error: {e}")
        code = 1
    finally:
        stack.say("stopping all processes")
        stack.stop()
        if ready_file is not None:
            ready_file.unlink(missing_ok=True)
        stack.say("all stopped")
    return code


def _secure_site(launch: LaunchFile, launch_dir: Path, only: list[str] | None, secure: bool,
                 secure_dir: Path | None) -> SecureSite | None:
    sec = launch.security
    if sec is None or not sec.enabled:
        if not secure:
            return None
        sec = SecuritySpec()
    local = [p.name for p in launch.process if not only or p.name in only]
    return prepare(launch, launch_dir.resolve(), sec, local, secure_dir)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus up",
        description="Start a whole Argus stack (router, mapper, planner, robots, cameras) from one TOML "
        "launch file; each process in its own process group with [name]-prefixed logs. Ctrl-C stops all.",
        epilog="example: argus up deploy/launch/demo.toml",
    )
    p.add_argument("launch", type=Path, help="launch file (TOML), e.g. deploy/launch/demo.toml")
    p.add_argument("--only", default=None, help="comma-separated process names to start on this machine")
    p.add_argument("--duration", type=float, default=None, help="stop everything after this many seconds")
    p.add_argument("--log-dir", type=Path, default=None, help="also write one <name>.log per process here")
    p.add_argument("--ready-file", type=Path, default=None, help="write the pids here once all are healthy")
    p.add_argument("--dry-run", action="store_true", help="print the command lines and exit")
    p.add_argument("--endpoint", default=None, help="router endpoint instead of the launch file's ({endpoint})")
    p.add_argument("--port", type=int, default=None, help="the launch file's router endpoint on this port instead")
    p.add_argument("--secure", action="store_true",
                   help="TLS + a certificate and password per process + an ACL (needs a tls/ endpoint; "
                   "also a launch file's [security] table); see docs/SECURITY.md")
    p.add_argument("--secure-dir", type=Path, default=None,
                   help="folder of the CA, certificates and passwords (default ~/.local/state/argus/secure/<site>)")
    a = p.parse_args(argv)
    only = [s.strip() for s in a.only.split(",") if s.strip()] if a.only else None
    try:
        return run(a.launch, only, a.duration, a.log_dir, a.ready_file, a.dry_run,
                   endpoint=a.endpoint, port=a.port, secure=a.secure, secure_dir=a.secure_dir)
    except ValueError as e:
        print(f"argus up: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
