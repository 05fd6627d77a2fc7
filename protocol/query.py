"""Graph query selectors: ``.../graph/nodes?label=chair;near=1.0,2.0,0.5;radius=1.5``.

Zenoh separates selector parameters with ``;``. Both the mapper (parsing) and consumers (building)
use this module, so the two sides cannot drift apart.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from protocol.messages import GraphNode

_FLAGS = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}


class GraphQuery(BaseModel):
    """A node selection. Empty fields select everything."""

    model_config = ConfigDict(extra="forbid")
    label: str | None = Field(default=None, description="substring of the node label (case-insensitive)")
    near: tuple[float, float, float] | None = Field(default=None, description="centre x,y,z of a ball")
    radius: float | None = Field(default=None, gt=0.0, description="ball radius in metres (default 1.0)")
    id: str | None = Field(default=None, description="one node id")
    since_version: int | None = Field(default=None, ge=0, description="only nodes changed after it")
    room: str | None = Field(default=None, min_length=1, description="only nodes in this room (a room id)")
    include_retired: bool | None = Field(
        default=None,
        description="also answer with the retired nodes (seen gone, kept for a while) that the other parameters "
        "select, in the reply's retired list",
    )

    def to_parameters(self) -> str:
        """Selector parameter string (without the leading ``?``)."""
        parts: list[str] = []
        if self.label is not None:
            parts.append(f"label={self.label}")
        if self.near is not None:
            parts.append("near=" + ",".join(f"{v:g}" for v in self.near))
        if self.radius is not None:
            parts.append(f"radius={self.radius:g}")
        if self.id is not None:
            parts.append(f"id={self.id}")
        if self.since_version is not None:
            parts.append(f"since_version={self.since_version}")
        if self.room is not None:
            parts.append(f"room={self.room}")
        if self.include_retired is not None:
            parts.append(f"include_retired={'true' if self.include_retired else 'false'}")
        return ";".join(parts)

    @classmethod
    def from_parameters(cls, params: str) -> GraphQuery:
        """Parse a parameter string; raises ``ValueError`` on unknown names or bad values."""
        fields: dict[str, object] = {}
        for part in filter(None, params.split(";")):
            name, sep, value = part.partition("=")
            if not sep:
                raise ValueError(f"parameter {part!r} has no value")
            if name == "near":
                xyz = tuple(float(v) for v in value.split(","))
                if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
                    raise ValueError("near needs three finite numbers x,y,z")
                fields["near"] = xyz
            elif name == "radius":
                fields["radius"] = float(value)
            elif name == "since_version":
                fields["since_version"] = int(value)
            elif name in ("label", "id", "room"):
                fields[name] = value
            elif name == "include_retired":
                flag = _FLAGS.get(value.lower())
                if flag is None:
                    raise ValueError("include_retired needs true or false")
                fields[name] = flag
            else:
                raise ValueError(f"unknown query parameter {name!r}")
        return cls.model_validate(fields)

    def matches(self, node: GraphNode) -> bool:
        """Whether ``node`` is selected (``since_version`` and ``room`` are checked by the graph holder)."""
        if self.id is not None and node.node_id != self.id:
            return False
        if self.label is not None and self.label.lower() not in node.label.lower():
            return False
        if self.near is not None:
            r = self.radius if self.radius is not None else 1.0
            if math.dist(self.near, node.centroid) > r:
                return False
        return True
