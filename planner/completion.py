"""Scene completions: what the unobserved part of the scene may hold, given the current graph.

A :class:`CompletionSampler` turns a :class:`SceneContext` (graph nodes assigned to rooms, the rooms of
the mapper's room layer, or else those known from the robots' published viewpoints) into K
:class:`Completion`\\ s, each a list of hypothesised objects (label, room, support parent, optional
position). Placement and consistency with what was already seen happen afterwards, the same for every sampler
(planner.hypotheses).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from planner.prior import IndoorPrior
from protocol.messages import GraphEdge, GraphNode
from protocol.rooms import UNKNOWN_ROOM_LABEL, RoomLayer

log = logging.getLogger(__name__)

ROOM_MARGIN_M = 0.45
"""Rooms extend this far beyond their outermost navigable viewpoints (robot radius, wall furniture)."""


@dataclass(frozen=True)
class RoomInfo:
    """A room as the planner knows it: from the mapper's room layer (:func:`rooms_from_layer`), or from the
    viewpoints published with that room name (:func:`rooms_from_viewpoints`)."""

    name: str
    kind: str | None
    xy_min: np.ndarray
    xy_max: np.ndarray
    vp_xy: np.ndarray

    @property
    def area_m2(self) -> float:
        d = self.xy_max - self.xy_min
        return float(max(d[0], 0.0) * max(d[1], 0.0))


@dataclass(frozen=True)
class KnownObject:
    """A graph node with its canonical label and room."""

    node: GraphNode
    label: str
    room: str | None
    parent_id: str | None


@dataclass(frozen=True)
class SceneContext:
    """What a sampler may condition on: the graph and the rooms published with the viewpoints."""

    objects: tuple[KnownObject, ...]
    edges: tuple[GraphEdge, ...]
    rooms: tuple[RoomInfo, ...]
    graph_version: int = 0

    def room(self, name: str | None) -> RoomInfo | None:
        for r in self.rooms:
            if r.name == name:
                return r
        return None

    def by_id(self) -> dict[str, KnownObject]:
        return {o.node.node_id: o for o in self.objects}


@dataclass(frozen=True)
class HypObject:
    """One hypothesised, not yet observed object of a completion.

    ``parent`` is a graph node id, or ``"new:<i>"`` for object ``i`` of the same completion.
    ``xyz`` is optional: when absent the object is placed from its room / parent and the prior's
    catalogue (sizes, placement).
    """

    label: str
    room: str | None = None
    parent: str | None = None
    xyz: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Completion:
    objects: tuple[HypObject, ...]
    source: str = ""


@dataclass
class SamplerInfo:
    """What the last ``sample`` call did (for status, logs and tests)."""

    requested: int = 0
    produced: int = 0
    fallback: bool = False
    error: str | None = None
    latency_s: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)


class CompletionSampler(Protocol):
    """Proposes K plausible completions of the unobserved scene."""

    name: str
    info: SamplerInfo

    def sample(self, ctx: SceneContext, k: int, rng: np.random.Generator) -> list[Completion]: ...


# --- context -------------------------------------------------------------------------------------


UNEXPLORED = "unexplored"
"""The region of the viewpoints in no room of the mapper's layer: space the map has not made a room of yet."""


def in_polygon(xy: np.ndarray, polygon: Sequence[tuple[float, float]]) -> np.ndarray:
    """(N,) bool: which of the points ``xy`` (N, 2) lie inside ``polygon`` (P corners, x, y)."""
    from skimage.measure import points_in_poly

    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(polygon) < 3 or xy.shape[0] == 0:
        return np.zeros(xy.shape[0], dtype=bool)
    return np.asarray(points_in_poly(xy, np.asarray(polygon, dtype=np.float64)), dtype=bool)


def room_of_points(xy: np.ndarray, layer: RoomLayer) -> list[str | None]:
    """The mapper room (id) each point ``xy`` (N, 2) lies in, None outside every room's outline."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out: list[str | None] = [None] * xy.shape[0]
    for r in layer.rooms:
        for i in np.flatnonzero(in_polygon(xy, r.polygon)):
            if out[int(i)] is None:
                out[int(i)] = r.room_id
    return out


def rooms_from_layer(layer: RoomLayer, vp_xy: np.ndarray, min_confidence: float = 0.5) -> tuple[RoomInfo, ...]:
    """Rooms from the mapper's room layer (built from its own map): each room's outline's bounding box, its label
    as the kind when at least ``min_confidence`` (else unknown: inferred from the objects, like an unnamed room),
    the viewpoints inside its outline. The viewpoints in no room make one more region, ``unexplored``: rooms the
    map has not reached count too."""
    vp_xy = np.asarray(vp_xy, dtype=np.float64).reshape(-1, 2)
    where = np.array([r or "" for r in room_of_points(vp_xy, layer)], dtype=object)
    out = []
    for r in layer.rooms:
        poly = np.asarray(r.polygon, dtype=np.float64).reshape(-1, 2)
        if poly.shape[0] < 3:
            continue
        kind = r.label if r.label != UNKNOWN_ROOM_LABEL and r.label_confidence >= min_confidence else None
        out.append(RoomInfo(name=r.room_id, kind=kind, xy_min=poly.min(axis=0), xy_max=poly.max(axis=0),
                            vp_xy=vp_xy[where == r.room_id]))
    rest = vp_xy[where == ""]
    if rest.shape[0]:
        out.append(RoomInfo(name=UNEXPLORED, kind=None, xy_min=rest.min(axis=0) - ROOM_MARGIN_M,
                            xy_max=rest.max(axis=0) + ROOM_MARGIN_M, vp_xy=rest))
    return tuple(out)


def rooms_from_viewpoints(
    room_of_vp: Sequence[str | None], xy: np.ndarray, prior: IndoorPrior
) -> tuple[RoomInfo, ...]:
    """Rooms (extent = viewpoints' bounding box grown by a margin) from named viewpoints."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    names = sorted({r for r in room_of_vp if r})
    out = []
    arr = np.array([r or "" for r in room_of_vp], dtype=object)
    for name in names:
        pts = xy[arr == name]
        if pts.shape[0] == 0:
            continue
        out.append(
            RoomInfo(
                name=name,
                kind=prior.room_kind(name),
                xy_min=pts.min(axis=0) - ROOM_MARGIN_M,
                xy_max=pts.max(axis=0) + ROOM_MARGIN_M,
                vp_xy=pts,
            )
        )
    if not out and xy.shape[0]:
        # No room names published: one region over all navigable space, kind inferred from objects.
        out.append(
            RoomInfo("space", None, xy.min(axis=0) - ROOM_MARGIN_M, xy.max(axis=0) + ROOM_MARGIN_M, xy)
        )
    return tuple(out)


def assign_room(points_xy: np.ndarray, rooms: Sequence[RoomInfo]) -> list[str | None]:
    """Room of each point: the room of the nearest viewpoint, if within its extent (else nearest anyway). A room
    with no viewpoint inside (a mapper room the navigation graph does not reach) is as near as its extent."""
    P = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if not rooms or P.shape[0] == 0:
        return [None] * P.shape[0]
    best = np.full(P.shape[0], np.inf)
    out: list[str | None] = [None] * P.shape[0]
    for r in rooms:
        if len(r.vp_xy):
            d = np.min(np.linalg.norm(P[:, None, :] - r.vp_xy[None, :, :], axis=2), axis=1)
        else:
            d = np.linalg.norm(P - np.clip(P, r.xy_min, r.xy_max), axis=1)
        inside = np.all((P >= r.xy_min) & (P <= r.xy_max), axis=1)
        score = d - 10.0 * inside  # prefer rooms whose extent contains the point
        for i in np.flatnonzero(score < best):
            out[i] = r.name
        best = np.minimum(best, score)
    return out


def support_parent(node: GraphNode, nodes: Sequence[GraphNode], edges: Sequence[GraphEdge]) -> str | None:
    """The node a node stands on: an ``on_top_of`` edge, else the box it sits on geometrically."""
    for e in edges:
        if e.subject_id == node.node_id and e.predicate == "on_top_of":
            return e.object_id
    c = np.asarray(node.centroid)
    best, best_gap = None, 0.35
    for other in nodes:
        if other.node_id == node.node_id:
            continue
        oc = np.asarray(other.box.center)
        ext = np.asarray(other.box.extent)
        top = oc[2] + ext[2] / 2
        bottom_of_node = c[2] - node.box.extent[2] / 2
        gap = bottom_of_node - top
        if -0.1 <= gap <= best_gap and np.all(np.abs(c[:2] - oc[:2]) <= ext[:2] / 2 + 0.05):
            best, best_gap = other.node_id, gap
    return best


def build_context(
    nodes: Sequence[GraphNode],
    edges: Sequence[GraphEdge],
    rooms: tuple[RoomInfo, ...],
    prior: IndoorPrior,
    graph_version: int = 0,
) -> SceneContext:
    xy = np.array([n.centroid[:2] for n in nodes], dtype=np.float64).reshape(-1, 2)
    node_rooms = assign_room(xy, rooms)
    known = tuple(
        KnownObject(n, prior.canonical_label(n.label), node_rooms[i], support_parent(n, nodes, edges))
        for i, n in enumerate(nodes)
    )
    return SceneContext(known, tuple(edges), rooms, graph_version)


# --- the prior sampler ---------------------------------------------------------------------------


def _count(rng: np.random.Generator, p: float, lo: int, hi: int, n_obs: int) -> int:
    """Total count of one entry given ``n_obs`` already seen (seen once means present)."""
    if n_obs > 0:
        return max(n_obs, int(rng.integers(lo, hi + 1)))
    return int(rng.integers(lo, hi + 1)) if rng.random() < p else 0


class PriorSampler:
    """Completions from the embedded common-sense indoor prior (no network)."""

    name = "prior"

    def __init__(self, prior: IndoorPrior) -> None:
        self.prior = prior
        self.info = SamplerInfo()

    def _room_kind(self, room: RoomInfo, labels: list[str], rng: np.random.Generator) -> str:
        if room.kind is not None and room.kind in self.prior.rooms:
            return room.kind
        lp = self.prior.kind_log_posterior(labels)
        kinds = list(lp)
        v = np.array([lp[k] for k in kinds])
        p = np.exp(v - v.max())
        return kinds[int(rng.choice(len(kinds), p=p / p.sum()))]

    def sample(self, ctx: SceneContext, k: int, rng: np.random.Generator) -> list[Completion]:
        self.info = SamplerInfo(requested=k)
        out = [self._one(ctx, rng) for _ in range(k)]
        self.info.produced = len(out)
        return out

    def _items_on(
        self,
        support_label: str,
        support_ref: str,
        room: str | None,
        observed_children: list[str],
        rng: np.random.Generator,
        out: list[HypObject],
    ) -> None:
        for e in self.prior.on.get(support_label, ()):
            n_obs = observed_children.count(e.label)
            n = _count(rng, e.p_present, e.min_count, e.max_count, n_obs)
            out.extend(HypObject(e.label, room, support_ref) for _ in range(n - n_obs))

    def _one(self, ctx: SceneContext, rng: np.random.Generator) -> Completion:
        objs: list[HypObject] = []
        children: dict[str, list[str]] = {}
        for o in ctx.objects:
            if o.parent_id is not None:
                children.setdefault(o.parent_id, []).append(o.label)
        for room in ctx.rooms:
            in_room = [o for o in ctx.objects if o.room == room.name]
            labels = [o.label for o in in_room if o.parent_id is None]
            kind = self._room_kind(room, labels, rng)
            for e in self.prior.rooms.get(kind, ()):
                n_obs = labels.count(e.label)
                n = _count(rng, e.p_present, e.min_count, e.max_count, n_obs)
                for _ in range(n - n_obs):
                    objs.append(HypObject(e.label, room.name, None))
                    idx = len(objs) - 1
                    self._items_on(e.label, f"new:{idx}", room.name, [], rng, objs)
            for o in in_room:
                self._items_on(
                    o.label, o.node.node_id, room.name, children.get(o.node.node_id, []), rng, objs
                )
        if not ctx.rooms:
            for o in ctx.objects:
                self._items_on(o.label, o.node.node_id, None, children.get(o.node.node_id, []), rng, objs)
        return Completion(tuple(objs), source=self.name)


def make_prior_sampler(config: Any, prior: IndoorPrior) -> CompletionSampler:
    """Factory of the ``prior`` sampler (``config``: the PlannerConfig)."""
    return PriorSampler(prior)


SAMPLERS: dict[str, str] = {
    "prior": "planner.completion:make_prior_sampler",
    "llm": "planner.llm:make_llm_sampler",
}
"""Registry of completion samplers: name -> ``module:factory(config, prior)``, imported lazily."""
