"""Registry of reconstructor backends: each name has a factory and a pydantic options model.

``geometry.options`` of the mapper config is validated against the chosen backend's model when the
config loads (``mapper.config.GeometryConfig``); heavy imports (torch models, mapanything) happen only
inside the chosen factory. Third parties add backends through the ``argus.reconstructors`` entry points
(name -> ``module:Class``; the class's ``Config`` attribute, if any, is its options model).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from mapper.geometry.contract import Reconstructor
from protocol.plugins import FactoryRegistry

ENTRY_POINT_GROUP = "argus.reconstructors"

RECONSTRUCTORS = FactoryRegistry("reconstructor", {
    "mvs": ("mapper.geometry.mvs:MvsReconstructor", "mapper.geometry.mvs:MvsConfig"),
    "oracle": ("mapper.geometry.oracle:OracleReconstructor", "mapper.geometry.oracle:OracleConfig"),
    "mapanything": ("mapper.geometry.mapanything_adapter:MapAnythingReconstructor",
                    "mapper.geometry.mapanything_adapter:MapAnythingConfig"),
    "da3": ("mapper.geometry.da3:Da3Reconstructor", "mapper.geometry.da3:Da3Config"),
    "probe": ("mapper.geometry.probe:ProbeReconstructor", "mapper.geometry.probe:ProbeConfig"),
}, ENTRY_POINT_GROUP)
"""Name -> (factory, options model)."""

ORACLE_RECONSTRUCTORS = frozenset({"oracle", "probe"})
"""Backends that read simulator ground truth (``View.oracle``): sim frames only."""


def available() -> dict[str, str]:
    """Built-in backends plus third-party ones registered under the ``argus.reconstructors`` entry points."""
    return RECONSTRUCTORS.available()


def make_reconstructor(name: str = "mvs", options: BaseModel | None = None, **opts: Any) -> Reconstructor:
    """Build the backend registered as ``name`` with its options: a validated options model (the mapper
    config's ``geometry.options``) or keywords. Raises ``ValueError`` naming a bad option."""
    rec: Reconstructor = RECONSTRUCTORS.create(name, options if options is not None else opts)
    return rec
