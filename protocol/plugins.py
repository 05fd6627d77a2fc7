"""Backend registries by name: built-in modules plus third-party modules named by entry points.

Each backend is one module defining ``Config`` (a pydantic model with a ``type`` field) and
``create(config)``. Modules are imported only when their type is used, so a registry costs nothing
at import time and a heavy backend never loads unless chosen.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any

from pydantic import BaseModel


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
