"""One command line for every process (protocol.tomlconfig.ProcessCommand): flags declared once with their
config path, --describe, configuration errors as one line and exit status 2, the node module's run called."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest
from pydantic import Field

from protocol.tomlconfig import AgentConfig, Flag, ProcessCommand


class DemoConfig(AgentConfig):
    """A process config for these tests."""

    rate_hz: float = Field(default=1.0, gt=0, description="how often")
    out: Path | None = Field(default=None, description="where")
    mode_name: str = Field(default="a", description="which")


COMMAND = ProcessCommand(
    "demo", "A demo process.", "epilog text", what="demo", config_help="TOML config file", set_example="rate_hz=2",
    node_module="demo_node_for_tests",
    flags=(Flag("--rate", "rate_hz", "how often", float), Flag("--out", "out", "where", Path, metavar="FILE"),
           Flag("--mode-name", "mode_name", "which", choices=("a", "b"))),
)


LOGS: list[tuple[str, str]] = []


@pytest.fixture
def ran(monkeypatch: pytest.MonkeyPatch) -> list[DemoConfig]:
    """The configs the fake node module's ``run`` got; ``run`` raises what the config's id names."""
    got: list[DemoConfig] = []

    def run(config: DemoConfig) -> int:
        got.append(config)
        if config.id == "broken":
            raise ValueError("no such backend 'x'")
        if config.id == "unavailable":
            raise OSError("cannot reach the model server")
        return 7

    import protocol.runtime

    # the process logs as <name>[<id>]; recorded here instead of reconfiguring the test session's logging
    monkeypatch.setattr(protocol.runtime, "setup_logging", lambda name, level: LOGS.append((name, level)))
    module = types.ModuleType("demo_node_for_tests")
    module.run = run  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "demo_node_for_tests", module)
    return got


def test_own_flags_set_their_config_paths_and_unset_ones_are_none() -> None:
    a = COMMAND.parser().parse_args(["--rate", "2.5", "--out", "x/y.rrd", "--id", "d1"])
    values = COMMAND.values(a)
    assert values["rate_hz"] == 2.5 and values["out"] == "x/y.rrd" and values["id"] == "d1"
    assert values["mode_name"] is None
    with pytest.raises(SystemExit):
        COMMAND.parser().parse_args(["--mode-name", "c"])  # not one of the choices


def test_help_names_every_flag() -> None:
    text = COMMAND.parser().format_help()
    for flag in ("--rate", "--out FILE", "--mode-name {a,b}", "--connect", "--set PATH=VALUE", "--describe"):
        assert flag in text
    assert text.startswith("usage: argus demo")


def test_start_runs_the_node_module_with_the_loaded_config(ran: list[DemoConfig], tmp_path: Path) -> None:
    cfg = tmp_path / "demo.toml"
    cfg.write_text('id = "d2"\nrate_hz = 3.0\n')
    a = COMMAND.parser().parse_args(["--config", str(cfg), "--rate", "4", "--set", "mode_name=b"])
    assert COMMAND.start(a, DemoConfig) == 7
    assert [(c.id, c.rate_hz, c.mode_name) for c in ran] == [("d2", 4.0, "b")]  # flag over file, --set last
    assert LOGS[-1] == ("demo[d2]", "INFO")
    a = COMMAND.parser().parse_args(["--rate", "4"])
    assert COMMAND.start(a, DemoConfig, values={"rate_hz": 9.0}) == 7 and ran[-1].rate_hz == 9.0


def test_describe_prints_every_field_and_runs_nothing(ran: list[DemoConfig],
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert COMMAND.start(COMMAND.parser().parse_args(["--describe"]), DemoConfig) == 0
    out = capsys.readouterr().out
    assert out.startswith("argus demo configuration (TOML):\n\n") and "rate_hz (float, default 1.0): how often" in out
    assert COMMAND.start(COMMAND.parser().parse_args(["--describe"]), DemoConfig, lambda: "mine") == 0
    assert capsys.readouterr().out == "mine\n" and ran == []


def test_configuration_errors_are_one_line_and_exit_2(ran: list[DemoConfig],
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert COMMAND.start(COMMAND.parser().parse_args(["--rate", "-1"]), DemoConfig) == 2  # invalid before run
    err = capsys.readouterr().err
    assert err.startswith("argus demo: ") and "rate_hz" in err and ran == []
    a = COMMAND.parser().parse_args(["--id", "broken"])
    assert COMMAND.start(a, DemoConfig, config_errors=(ValueError,)) == 2
    assert capsys.readouterr().err == "argus demo: configuration error: no such backend 'x'\n"
    a = COMMAND.parser().parse_args(["--id", "unavailable"])
    assert COMMAND.start(a, DemoConfig, errors=(OSError,)) == 2
    assert capsys.readouterr().err == "argus demo: cannot reach the model server\n"
    with pytest.raises(OSError):  # not declared: a bug, not a configuration error
        COMMAND.start(a, DemoConfig, config_errors=(ValueError,))
