"""Registry of reconstructor backends; heavy imports happen only inside the chosen factory."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

from mapper.geometry.contract import Reconstructor

# name -> "module:factory"; the factory takes keyword options and returns a Reconstructor.
RECONSTRUCTORS: dict[str, str] = {
    "mvs": "mapper.geometry.mvs:MvsReconstructor",
    "oracle": "mapper.geometry.oracle:OracleReconstructor",
    "mapanything": "mapper.geometry.mapanything_adapter:MapAnythingReconstructor",
    "da3": "mapper.geometry.da3:Da3Reconstructor",
}


ENTRY_POINT_GROUP = "argus.reconstructors"


def _load(target: str) -> Callable[..., Reconstructor]:
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)  # type: ignore[no-any-return]


def available() -> dict[str, str]:
    """Built-in backends plus third-party ones registered under the ``argus.reconstructors`` entry points."""
    found = dict(RECONSTRUCTORS)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep.value)
    return found


def make_reconstructor(name: str = "mvs", **opts: Any) -> Reconstructor:
    """Build the backend registered as ``name`` with its options (see each backend's config)."""
    backends = available()
    if name not in backends:
        raise ValueError(f"unknown reconstructor {name!r}; choose one of {sorted(backends)}")
    return _load(backends[name])(**opts)
