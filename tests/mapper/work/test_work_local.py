"""The mapper's local worker processes (``[workers] local``): where they join, their settings, restarts with a
back-off, a clean stop; and one real child on loopback that takes its settings on stdin and stops when its
stdin closes (the mapper closed it or died)."""

from __future__ import annotations

import threading
from typing import Any, ClassVar

import pytest

from mapper.work import local
from mapper.work.config import OffloadConfig, default_local_workers
from mapper.work.local import LocalWorkers, local_endpoints, local_worker_config
from protocol.keys import Keys
from protocol.session import ZenohSettings, open_session
from protocol.transport import Counters
from tests.support.procs import wait_for


def test_a_client_mapper_s_workers_join_its_router() -> None:
    z = ZenohSettings(mode="client", connect=["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"])
    assert local_endpoints(z) == ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]


def test_a_listening_mapper_s_workers_join_it_on_loopback() -> None:
    z = ZenohSettings(mode="peer", listen=["tcp/0.0.0.0:7450", "tcp/[::]:7451"], connect=[], insecure=True)
    assert local_endpoints(z) == ["tcp/127.0.0.1:7450", "tcp/[::1]:7451"]
    z = ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:0"], connect=["tcp/127.0.0.1:7447"])
    assert local_endpoints(z) == ["tcp/127.0.0.1:7447"]  # a random port cannot be joined: its router then
    assert local_endpoints(ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:0"], connect=[])) == []


def test_local_worker_settings() -> None:
    z = ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:7450"], connect=["tcp/127.0.0.1:7447"],
                      overrides={"transport/link/tx/lease": 5000})
    z = z.model_copy(update={"config_file": "/etc/argus/mapper/zenoh.json5"})
    cfg = local_worker_config("m1", "lab", "argus", z, 1, 3, "WARNING")
    assert cfg is not None
    assert (cfg.id, cfg.site, cfg.key_prefix, cfg.torch_threads, cfg.log_level) == ("m1-local1", "lab", "argus", 3,
                                                                                      "WARNING")
    assert (cfg.zenoh.mode, cfg.zenoh.connect, cfg.zenoh.listen) == ("client", ["tcp/127.0.0.1:7450"], [])
    # the rest of the mapper's Zenoh settings, its login (config file) included: the ACL gives it their keys
    assert cfg.zenoh.overrides == {"transport/link/tx/lease": 5000}
    assert str(cfg.zenoh.config_file) == "/etc/argus/mapper/zenoh.json5"
    assert local_worker_config("m1", "lab", "argus", ZenohSettings(mode="peer", connect=[]), 0, 1, "INFO") is None


def test_default_count_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARGUS_LOCAL_WORKERS", "2")
    assert default_local_workers() == 2 and OffloadConfig().local == 2
    monkeypatch.setenv("ARGUS_LOCAL_WORKERS", "many")
    assert default_local_workers() == 1
    monkeypatch.delenv("ARGUS_LOCAL_WORKERS")
    assert default_local_workers() == 1
    assert OffloadConfig(local=0).local == 0  # explicit settings win


class FakePopen:
    """Stands in for a child process: ``code`` None while it runs."""

    started: ClassVar[list[FakePopen]] = []

    def __init__(self, argv: list[str], stdin: Any = None) -> None:
        self.argv, self.code, self.pid = argv, None, 1000 + len(FakePopen.started)
        self.stdin = FakeStdin()
        self.signals: list[str] = []
        FakePopen.started.append(self)

    def poll(self) -> int | None:
        return self.code

    def wait(self, timeout: float | None = None) -> int:
        if self.stdin.closed and self.code is None:
            self.code = 0  # it stops by itself once its stdin closes
        assert self.code is not None
        return self.code

    def terminate(self) -> None:
        self.signals.append("TERM")

    def kill(self) -> None:
        self.signals.append("KILL")


class FakeStdin:
    def __init__(self) -> None:
        self.data, self.closed = b"", False

    def write(self, b: bytes) -> None:
        self.data += b

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def test_an_exited_child_is_restarted_after_a_growing_back_off(monkeypatch: pytest.MonkeyPatch) -> None:
    FakePopen.started = []
    monkeypatch.setattr(local.subprocess, "Popen", FakePopen)
    cfg = local_worker_config("m", "lab", "argus", ZenohSettings(connect=["tcp/127.0.0.1:7447"]), 0, 1, "INFO")
    assert cfg is not None
    counters = Counters()
    pool = LocalWorkers([cfg], counters)
    pool.start()
    first = FakePopen.started[0]
    assert first.argv[1:] == ["-m", "mapper.work.local"]
    assert type(cfg).model_validate_json(first.stdin.data) == cfg  # its settings, one JSON line on stdin
    assert pool.alive() == 1
    pool.check(now=100.0)
    assert len(FakePopen.started) == 1  # running: left alone
    first.code = 1
    pool.check(now=100.0)
    assert pool.alive() == 0 and counters.get("local_worker_exits") == 1 and first.stdin.closed
    pool.check(now=101.9)
    assert len(FakePopen.started) == 1  # 2 s back-off after the first exit
    pool.check(now=102.0)
    assert len(FakePopen.started) == 2 and counters.get("local_worker_restarts") == 1 and pool.alive() == 1
    FakePopen.started[1].code = 1
    pool.check(now=110.0)
    pool.check(now=113.9)
    assert len(FakePopen.started) == 2  # 4 s after the second exit
    pool.check(now=114.0)
    assert len(FakePopen.started) == 3
    pool.children[0].started = 114.0  # then it runs for 10 minutes: the doubling starts afresh
    FakePopen.started[2].code = 1
    pool.check(now=714.0)
    pool.check(now=715.9)
    assert len(FakePopen.started) == 3
    pool.check(now=716.0)
    assert len(FakePopen.started) == 4
    pool.close()
    last = FakePopen.started[3]
    assert last.stdin.closed and last.code == 0 and last.signals == []  # stopped by its stdin, no signal needed
    last.code = 3
    pool.check(now=1000.0)
    assert len(FakePopen.started) == 4 and counters.get("local_worker_exits") == 3  # closed: never restarted


@pytest.mark.integration
def test_a_real_child_joins_the_router_and_stops_when_its_stdin_closes(router: str) -> None:
    keys = Keys("localtest")
    cfg = local_worker_config("m", "localtest", "argus", ZenohSettings(mode="client", connect=[router]), 0, 1,
                              "INFO")
    assert cfg is not None
    session = open_session(ZenohSettings(mode="client", connect=[router]))
    seen: set[str] = set()
    lock = threading.Lock()

    def on_alive(sample: Any) -> None:
        with lock:
            if str(sample.kind).endswith("PUT"):
                seen.add(str(sample.key_expr))
            else:
                seen.discard(str(sample.key_expr))

    sub = session.liveliness().declare_subscriber(keys.all_alive_of("worker"), on_alive, history=True)
    pool = LocalWorkers([cfg], Counters())
    try:
        pool.start()
        token = keys.alive("worker", "m-local0")
        wait_for(lambda: token in seen, 60, what="the local worker's liveliness token")
        popen = pool.children[0].popen
        assert popen is not None
        pool.close()
        assert popen.returncode == 0  # a clean exit on end of stdin, not a signal
        wait_for(lambda: token not in seen, 10, what="the token gone")
    finally:
        pool.close()
        sub.undeclare()
        session.close()


def test_no_local_worker_where_it_could_not_join() -> None:
    from mapper.config import MapperConfig
    from mapper.node import MapperNode

    peer = {"mode": "peer", "connect": [], "listen": ["tcp/127.0.0.1:0"]}
    node = MapperNode(MapperConfig.model_validate({"site": "t", "workers": {"local": 1}, "zenoh": peer}))
    assert node._start_local_workers() is None
    assert node.counters.get("local_workers_unreachable") == 1
    node = MapperNode(MapperConfig(site="t", workers={"local": 0}))  # type: ignore[arg-type]
    assert node._start_local_workers() is None and not node.counters.snapshot()


def test_oracle_perception_offloads_geometry_only() -> None:
    """The semantic camera's masks come with the frame's ORACLE sample, which jobs do not carry: the worker
    computes the geometry, the mapper the masks. True geometry (ORACLE depth) is not offloaded at all."""
    from mapper.config import MapperConfig
    from mapper.node import MapperNode

    sim = {"segmenter": "sim", "embedder": "sim"}
    node = MapperNode(MapperConfig.model_validate({"site": "t", "geometry": {"backend": "mvs"}, "perception": sim}))
    assert node.offloader is not None and node.offloader.perception is False
    node = MapperNode(MapperConfig.model_validate({"site": "t", "geometry": {"backend": "mvs"}}))
    assert node.offloader is not None and node.offloader.perception is True
    node = MapperNode(MapperConfig.model_validate({"site": "t", "geometry": {"backend": "oracle"}}))
    assert node.offloader is None
