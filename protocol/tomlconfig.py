"""TOML config files for Argus processes: load, apply ``--set a.b=value`` overrides, validate, describe.

Every process has a pydantic config model (``extra="forbid"``, a description on every field). A run
is configured by a TOML file, then command-line overrides, then validation, in that order::

    cfg = load_config(EdgeCameraConfig, Path("cam.toml"), {"id": "cam1"}, ["source.rate_hz=2"])

Overrides use dotted paths; a value is parsed as a TOML value when it can be (``2``, ``true``,
``[1, 2]``, ``"x"``) and is taken as a plain string otherwise (``source.path=/data/imgs``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tomllib
import types
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, NamedTuple, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

if TYPE_CHECKING:
    from protocol.plugins import BackendRegistry

from protocol.keys import SiteName, validate_id
from protocol.session import ZenohSettings, default_endpoints, default_site

C = TypeVar("C", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration that cannot be used: unreadable file, bad TOML, unknown or invalid field."""


def load_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file into a dict; raises :class:`ConfigError` with the reason."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {e}") from None
    except UnicodeDecodeError as e:  # found by tests/test_fuzz.py: tomllib decodes before parsing
        raise ConfigError(f"config file {path} is not UTF-8 text: {e}") from None


def parse_value(text: str) -> Any:
    """A TOML value (``2``, ``1.5``, ``true``, ``[1, 2]``, ``"s"``), else the text itself."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def set_path(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``data[a][b][c] = value`` for ``dotted = "a.b.c"``, creating tables on the way."""
    parts = dotted.split(".")
    if not all(parts):
        raise ConfigError(f"bad config path {dotted!r}")
    node = data
    for p in parts[:-1]:
        nxt = node.setdefault(p, {})
        if not isinstance(nxt, dict):
            raise ConfigError(f"config path {dotted!r}: {p!r} is not a table")
        node = nxt
    node[parts[-1]] = value


def load_config(
    model: type[C],
    path: Path | None = None,
    values: dict[str, Any] | None = None,
    overrides: list[str] | None = None,
) -> C:
    """File, then ``values`` (dotted path -> value, ``None`` skipped), then ``a.b=v`` overrides."""
    data: dict[str, Any] = load_toml(path) if path is not None else {}
    for dotted, value in (values or {}).items():
        if value is not None:
            set_path(data, dotted, value)
    for item in overrides or []:
        dotted, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"override {item!r} is not of the form path=value")
        set_path(data, dotted.strip(), parse_value(text.strip()))
    try:
        return model.model_validate(data)
    except ValidationError as e:
        lines = [f"  {'.'.join(str(p) for p in err['loc']) or '(top)'}: {err['msg']}" for err in e.errors()]
        where = f" in {path}" if path is not None else ""
        raise ConfigError(f"invalid configuration{where}:\n" + "\n".join(lines)) from None


def _type_name(annotation: Any) -> str:
    origin = get_origin(annotation)
    if origin is None:
        return "none" if annotation is type(None) else getattr(annotation, "__name__", str(annotation))
    args = get_args(annotation)
    if origin in (Union, types.UnionType):
        return " | ".join(_type_name(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is Annotated:
        return _type_name(args[0])
    return f"{getattr(origin, '__name__', str(origin))}[{', '.join(_type_name(a) for a in args)}]"


def describe(model: type[BaseModel], prefix: str = "") -> list[str]:
    """One line per field (nested models expanded): ``path (type, default): description``."""
    lines: list[str] = []
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            lines.append(f"[{path}]  {field.description or ''}".rstrip())
            lines.extend(describe(ann, prefix=f"{path}."))
            continue
        default = "required" if field.is_required() else repr(field.get_default(call_default_factory=True))
        lines.append(f"{path} ({_type_name(ann)}, default {default}): {field.description or ''}")
    return lines


def process_parser(prog: str, description: str, epilog: str, *, what: str, config_help: str,
                   set_example: str, listen: bool = False) -> argparse.ArgumentParser:
    """The flags every Argus process shares: --config --id --site --connect [--listen] --mode
    --zenoh-config --insecure --set --describe --log-level. Each process adds its own flags;
    :func:`process_values` maps the shared ones onto config paths."""
    p = argparse.ArgumentParser(prog=prog, description=description, epilog=epilog,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, default=None, help=config_help)
    p.add_argument("--id", default=None, help=f"{what} id")
    p.add_argument("--site", default=None, help="Argus site name")
    p.add_argument("--connect", action="append", default=None, help="Zenoh endpoint to connect to (repeatable)")
    if listen:
        p.add_argument("--listen", action="append", default=None, help="Zenoh endpoint to listen on (peer mode)")
    p.add_argument("--mode", choices=["client", "peer"], default=None, help="Zenoh mode (default client)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE.json5",
                   help="Zenoh json5 config applied first (TLS, user/password: deploy/zenoh/client-tls.json5)")
    p.add_argument("--insecure", action="store_true",
                   help="allow a plaintext listen endpoint on a non-loopback address (peer mode; warns)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help=f"override any config field, e.g. --set {set_example} (repeatable)")
    p.add_argument("--describe", action="store_true", help="print every config field and exit")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def process_values(a: argparse.Namespace, id_field: str = "id") -> dict[str, Any]:
    """Config paths of the shared flags of :func:`process_parser` (unset flags are ``None``)."""
    values: dict[str, Any] = {
        id_field: a.id,
        "site": a.site,
        "zenoh.connect": a.connect,
        "zenoh.mode": a.mode,
        "log_level": a.log_level.upper() if a.log_level else None,
    }
    if getattr(a, "listen", None) is not None:
        values["zenoh.listen"] = a.listen
    if getattr(a, "zenoh_config", None) is not None:
        values["zenoh.config_file"] = str(a.zenoh_config)
    if getattr(a, "insecure", False):
        values["zenoh.insecure"] = True
    return values


def add_consumer_flags(p: argparse.ArgumentParser) -> None:
    """``--connect`` (repeatable) and ``--site`` of the consumer commands (query, goal); unset, they
    fall back to ``ARGUS_CONNECT`` / ``ARGUS_SITE``, then to ``tcp/127.0.0.1:7447`` / ``default``."""
    p.add_argument("--connect", action="append", default=None,
                   help="router endpoint (repeatable; default $ARGUS_CONNECT or tcp/127.0.0.1:7447)")
    p.add_argument("--site", default=None, help="Argus site name (default $ARGUS_SITE or default)")
    p.add_argument("--zenoh-config", type=Path, default=None, metavar="FILE.json5",
                   help="Zenoh json5 config applied first (TLS and user/password of a secure site)")


def consumer_values(a: argparse.Namespace) -> tuple[ZenohSettings, str]:
    """The client settings and site of :func:`add_consumer_flags`."""
    settings = ZenohSettings(mode="client", connect=a.connect or default_endpoints(), config_file=a.zenoh_config)
    return settings, a.site or default_site()


class AgentConfig(BaseModel):
    """Fields every edge agent (camera, robot) shares: identity on the wire, status, Zenoh, logging.

    Subclasses redeclare ``id`` with their own default and description.
    """

    model_config = ConfigDict(extra="forbid")
    id: str = Field(default="agent0", description="id (a single key chunk: letters, digits, _ . -)")
    site: SiteName = Field(
        default_factory=default_site,
        validate_default=True,
        description="Argus site name (key prefix argus/<site>/...; default $ARGUS_SITE or default)",
    )
    key_prefix: str = Field(default="argus", description="top-level key prefix")
    status_period_s: float = Field(default=2.0, gt=0, description="seconds between Status messages")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="how to join the Zenoh network")
    log_level: str = Field(default="INFO", description="DEBUG, INFO, WARNING or ERROR")

    @field_validator("id")
    @classmethod
    def _chunk(cls, v: str) -> str:
        return validate_id(v)


class Flag(NamedTuple):
    """One of a process's own command-line flags and the config path it sets (a path value is set as a string)."""

    name: str
    path: str
    help: str
    type: Callable[[str], Any] = str
    choices: tuple[str, ...] | None = None
    metavar: str | None = None

    @property
    def dest(self) -> str:
        return self.name.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class ProcessCommand:
    """One process's command line: the flags every process shares (:func:`process_parser`), its own
    :class:`Flag` s, and the module whose ``run(config)`` it starts (imported only then)."""

    name: str
    description: str
    epilog: str
    what: str
    config_help: str
    set_example: str
    node_module: str
    flags: tuple[Flag, ...] = ()
    listen: bool = False
    id_field: str = "id"

    def parser(self) -> argparse.ArgumentParser:
        p = process_parser(f"argus {self.name}", self.description, self.epilog, what=self.what,
                           config_help=self.config_help, set_example=self.set_example, listen=self.listen)
        for f in self.flags:
            p.add_argument(f.name, type=f.type, choices=f.choices, default=None, metavar=f.metavar, help=f.help)
        return p

    def values(self, a: argparse.Namespace) -> dict[str, Any]:
        """Config paths of the shared flags and of this process's own (unset flags are ``None``)."""
        values = process_values(a, self.id_field)
        for f in self.flags:
            value = getattr(a, f.dest)
            values[f.path] = str(value) if isinstance(value, Path) else value
        return values

    def describe(self, model: type[BaseModel], backends: BackendRegistry | None = None) -> str:
        """``--describe``: every field of ``model``; with ``backends``, the fields of its table per backend type."""
        lines = [f"argus {self.name} configuration (TOML):", ""]
        if backends is None:
            return "\n".join(lines + describe(model))
        lines += [ln for ln in describe(model) if not ln.startswith(f"{backends.table} ")]
        return "\n".join(lines + backends.describe(describe))

    def start(
        self,
        a: argparse.Namespace,
        model: type[C],
        describe_all: Callable[[], str] | None = None,
        *,
        values: dict[str, Any] | None = None,
        config_errors: tuple[type[Exception], ...] = (),
        errors: tuple[type[Exception], ...] = (),
    ) -> int:
        """The end of every process's ``main``: ``--describe`` prints ``describe_all()`` (default: every field of
        ``model``); otherwise load the config
        (file, then flags and ``values``, then ``--set``), log as ``<name>[<id>]`` and call ``run(config)`` of the
        node module. A bad config, or one of ``config_errors`` raised while the process builds its parts, is one
        line on stderr and exit status 2 (``errors`` likewise, without the words "configuration error")."""
        from protocol.runtime import setup_logging

        if a.describe:
            print(describe_all() if describe_all is not None else self.describe(model))
            return 0
        try:
            config = load_config(model, a.config, {**self.values(a), **(values or {})}, a.overrides)
        except ConfigError as e:
            print(f"argus {self.name}: {e}", file=sys.stderr)
            return 2
        setup_logging(f"{self.name}[{getattr(config, self.id_field)}]", getattr(config, "log_level", "INFO"))
        try:
            return int(importlib.import_module(self.node_module).run(config))
        except errors as e:
            print(f"argus {self.name}: {e}", file=sys.stderr)
        except config_errors as e:
            print(f"argus {self.name}: configuration error: {e}", file=sys.stderr)
        return 2
