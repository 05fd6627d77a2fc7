"""Backend registries by name: built-in backends plus third-party ones named by entry points.

Two shapes, one idea (a pydantic options model per backend, validated when the config loads, listed by
``--describe``, the backend itself imported only when chosen):

- :class:`BackendRegistry`: each backend is one module defining ``Config`` (a pydantic model with a
  ``type`` field, the whole ``[source]`` / ``[body]`` table) and ``create(config)``.
- :class:`FactoryRegistry`: each backend is a factory class picked by a name field next to an options
  table (``geometry.backend`` + ``geometry.options``: reconstructors, segmenters, embedders).

Modules are imported only when their backend is used, so a registry costs nothing at import time and
a heavy backend never loads unless chosen.
"""

from __future__ import annotations

import difflib
import importlib
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError


class BackendRegistry:
    """Name -> backend module, for one kind of backend (camera sources, robot bodies, ...)."""

    def __init__(self, kind: str, table: str, builtins: dict[str, str], entry_point_group: str,
                 error: type[ValueError]) -> None:
        self.kind = kind  # "source type", "body type"
        self.table = table  # the TOML table holding the config: "source", "body"
        self.builtins = builtins
        self.entry_point_group = entry_point_group
        self.error = error

    def available(self) -> dict[str, str]:
        """Built-in and plug-in types (name -> module)."""
        out = dict(self.builtins)
        for ep in entry_points(group=self.entry_point_group):
            out.setdefault(ep.name, ep.value)
        return out

    def module(self, name: str) -> ModuleType:
        """The module of type ``name``; raises the registry's error for an unknown type."""
        types = self.available()
        if name not in types:
            raise self.error(f"unknown {self.kind} {name!r} (known: {', '.join(sorted(types))})")
        return importlib.import_module(types[name])

    def parse_config(self, data: Any, base: type[BaseModel]) -> Any:
        """Validate a ``[table]`` with its backend's ``Config`` (pydantic errors propagate)."""
        if isinstance(data, base):
            return data
        if not isinstance(data, dict) or not isinstance(data.get("type"), str):
            raise self.error(f"[{self.table}] needs a string field 'type'")
        return self.module(data["type"]).Config.model_validate(data)

    def create(self, config: Any) -> Any:
        """Build the backend object for a validated config."""
        return self.module(config.type).create(config)

    def describe(self, describe_model: Any) -> list[str]:
        """``describe`` lines for every type's config (a broken plug-in is listed, not fatal)."""
        lines: list[str] = []
        for name in sorted(self.available()):
            try:
                cls = self.module(name).Config
            except Exception as e:  # noqa: BLE001 - a broken plug-in must not hide the others
                lines += ["", f"[{self.table}] type = {name!r}: unavailable ({e})"]
                continue
            lines += ["", f"[{self.table}] type = {name!r}"]
            lines += [f"  {ln}" for ln in describe_model(cls, prefix=f"{self.table}.")
                      if not ln.startswith(f"{self.table}.type ")]
        return lines


class FreeOptions(BaseModel):
    """Options of a plug-in backend that declares no ``Config``: passed through unchecked (the backend
    validates them when it is built)."""

    model_config = ConfigDict(extra="allow")


def _attr(target: str) -> Any:
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)


def _suggest(wrong: str, names: list[str]) -> str:
    close = difflib.get_close_matches(wrong, names, n=1)
    if close:
        return f"did you mean {close[0]!r}?"
    return f"its options: {', '.join(names)}" if len(names) <= 12 else "its options: see --describe"


class FactoryRegistry:
    """Name -> backend factory (``"module:Class"``) and its options model, for one kind of backend whose
    options sit in a table next to the name (``geometry.backend`` + ``geometry.options``).

    Built-ins name their options model (``"module:Config"``); a plug-in registered under the entry-point
    group names only its factory, whose ``Config`` attribute (a pydantic model) is its options model when
    it has one. Modules are imported when a name is used, so heavy backends cost nothing until chosen; the
    factory is called as ``Class(**options)`` and imports its model packages itself.
    """

    def __init__(self, kind: str, builtins: dict[str, tuple[str, str]], entry_point_group: str) -> None:
        self.kind = kind  # "reconstructor", "segmenter", "embedder"
        self.builtins = builtins  # name -> (factory target, options model target)
        self.entry_point_group = entry_point_group

    def available(self) -> dict[str, str]:
        """Built-in and plug-in backends (name -> factory target)."""
        out = {name: factory for name, (factory, _) in self.builtins.items()}
        for ep in entry_points(group=self.entry_point_group):
            out.setdefault(ep.name, ep.value)
        return out

    def factory_target(self, name: str) -> str:
        """``"module:Class"`` of backend ``name``; ``ValueError`` listing the known names if there is none."""
        if name in self.builtins:  # no entry-point scan for the common case
            return self.builtins[name][0]
        known = self.available()
        if name not in known:
            raise ValueError(f"unknown {self.kind} {name!r}; choose one of {sorted(known)}")
        return known[name]

    def options_model(self, name: str) -> type[BaseModel]:
        """The options model of backend ``name`` (:class:`FreeOptions` for a plug-in without ``Config``)."""
        if name in self.builtins:
            model: type[BaseModel] = _attr(self.builtins[name][1])
            return model
        config = getattr(_attr(self.factory_target(name)), "Config", None)
        return config if isinstance(config, type) and issubclass(config, BaseModel) else FreeOptions

    def parse_options(self, name: str, data: Any) -> BaseModel:
        """Validate ``data`` (a table or a model) as the options of backend ``name``. Raises ``ValueError``
        naming the backend and each bad option (an unknown name lists the valid ones)."""
        self.factory_target(name)
        try:
            model = self.options_model(name)
        except Exception as e:  # noqa: BLE001 - a broken plug-in is a configuration error, not a crash
            raise ValueError(f"{self.kind} {name!r} is unavailable: {e}") from None
        if isinstance(data, model):
            return data
        if isinstance(data, BaseModel):
            data = data.model_dump(exclude_unset=True)
        if not isinstance(data, dict):
            raise ValueError(f"the options of {self.kind} {name!r} must be a table, got {type(data).__name__}")
        try:
            return model.model_validate(data)
        except ValidationError as e:
            raise ValueError(self._explain(name, model, e)) from None

    def _explain(self, name: str, model: type[BaseModel], error: ValidationError) -> str:
        problems = []
        for err in error.errors():
            field = ".".join(str(p) for p in err["loc"]) or "(options)"
            if err["type"] == "extra_forbidden":
                problems.append(f"no option {field!r} ({_suggest(field, list(model.model_fields))})")
            else:
                problems.append(f"option {field!r}: {err['msg']}")
        return f"{self.kind} {name!r}: " + "; ".join(problems)

    def create(self, name: str, options: BaseModel | dict[str, Any] | None = None) -> Any:
        """Build backend ``name`` with its validated options."""
        parsed = self.parse_options(name, options if options is not None else {})
        return _attr(self.factory_target(name))(**parsed.model_dump(exclude_unset=True))

    def describe(self, describe_model: Any, path: str, name_field: str) -> list[str]:
        """``describe`` lines of every backend's options (a broken plug-in is listed, not fatal)."""
        lines: list[str] = []
        for name in sorted(self.available()):
            head = f"{name_field} = {name!r}"
            try:
                model = self.options_model(name)
            except Exception as e:  # noqa: BLE001 - a broken plug-in must not hide the others
                lines += ["", f"{head}: unavailable ({e})"]
                continue
            body = describe_model(model, prefix=f"{path}.")
            lines += ["", f"{head}: options {path}.* ({model.__name__})", *[f"  {ln}" for ln in body or ["(none)"]]]
        return lines
