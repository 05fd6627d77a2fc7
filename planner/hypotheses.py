"""Placing sampled completions in the world, consistently with what was already seen (pure numpy).

Every hypothesised object gets a few candidate placements (from its support parent, its room and
the prior's catalogue: size, floor / wall / on-top placement). A placement is ruled out (with
probability ``detect_reject``) when a past view would have detected an object of that size there,
or, for floor-standing objects, when the map has seen bare floor at that spot. The first surviving
placement is kept; an object with none is dropped from that completion: the evidence says it is
not there. This is where completions become consistent with the observation history, so a
region that was looked at closely stops attracting the robot.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from planner.completion import Completion, HypObject, SceneContext
from planner.prior import IndoorPrior

SHELF_LIKE = frozenset({"bookshelf", "shelf", "cabinet", "wardrobe", "shoe rack"})
CEILING_Z_M = 2.4
WALL_Z_M = (1.1, 1.7)


@dataclass(frozen=True)
class Hypotheses:
    """Flattened hypotheses of all samples: sample ``s = k * n_jitter + j``."""

    labels: tuple[str, ...]
    label_idx: np.ndarray  # (H,)
    xyz: np.ndarray  # (H,3)
    size_m: np.ndarray  # (H,)
    room: tuple[str | None, ...]  # (H,)
    sample_idx: np.ndarray  # (H,)
    n_completions: int
    n_jitter: int
    dropped: int = 0

    @property
    def size(self) -> int:
        return int(self.label_idx.shape[0])


Evidence = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""(targets (T,3), sizes (T,)) -> (T,) bool: ruled out by what was already seen."""


@dataclass
class _Pending:
    comp: int
    obj: HypObject
    label: str
    w: float
    d: float
    h: float
    props: np.ndarray  # (P,3)
    floor: bool


def _footprint_props(
    center: np.ndarray,
    ext: np.ndarray,
    yaw: float,
    item_h: float,
    n: int,
    shelf: bool,
    rng: np.random.Generator,
) -> np.ndarray:
    half = np.maximum(ext[:2] / 2 - 0.05, 0.0)
    local = rng.uniform(-1, 1, size=(n, 2)) * half
    c, s = np.cos(yaw), np.sin(yaw)
    xy = center[:2] + local @ np.array([[c, s], [-s, c]])
    top = center[2] + ext[2] / 2
    if shelf:
        z = rng.uniform(min(0.3, top), top, size=n) + item_h / 2
    else:
        z = np.full(n, top + item_h / 2)
    return np.column_stack([xy, z])


def _room_props(
    lo: np.ndarray,
    hi: np.ndarray,
    placement: str,
    w: float,
    d: float,
    h: float,
    n: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, bool]:
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.maximum(np.asarray(hi, dtype=np.float64), lo + 1e-3)
    if placement in ("floor", "ceiling"):
        pad = np.minimum(np.array([w, w]) / 2, (hi - lo) / 2)
        # A room narrower than the object: its middle, where lo + pad may round past hi - pad
        low = lo + pad
        xy = rng.uniform(low, np.maximum(hi - pad, low), size=(n, 2))
        z = np.full(n, CEILING_Z_M if placement == "ceiling" else h / 2)
        return np.column_stack([xy, z]), placement == "floor"
    # floor_wall, wall_mounted, on (no parent): along one of the four sides of the room
    side = rng.integers(0, 4, size=n)
    t = rng.uniform(0, 1, size=n)
    inset = 0.05 if placement == "wall_mounted" else d / 2 + 0.05
    x = np.where(side < 2, lo[0] + t * (hi[0] - lo[0]), np.where(side == 2, lo[0] + inset, hi[0] - inset))
    y = np.where(side >= 2, lo[1] + t * (hi[1] - lo[1]), np.where(side == 0, lo[1] + inset, hi[1] - inset))
    if placement == "wall_mounted":
        z = rng.uniform(*WALL_Z_M, size=n)
    elif placement == "on":
        z = np.full(n, 0.9 + h / 2)
    else:
        z = np.full(n, h / 2)
    return np.column_stack([x, y, z]), placement == "floor_wall"


def _overlaps_known(xy: np.ndarray, half: float, known_xy: np.ndarray, known_half: np.ndarray) -> np.ndarray:
    if known_xy.shape[0] == 0:
        return np.zeros(xy.shape[0], bool)
    d = np.abs(xy[:, None, :] - known_xy[None, :, :])
    lim = 0.6 * (half + known_half[None, :, :])
    return np.any(np.all(d < lim, axis=2), axis=1)


def realize(
    completions: list[Completion],
    ctx: SceneContext,
    prior: IndoorPrior,
    *,
    n_jitter: int,
    jitter_m: float,
    proposals: int,
    detect_reject: float,
    seen: Evidence,
    floor_seen: Callable[[np.ndarray], np.ndarray],
    rng: np.random.Generator,
) -> Hypotheses:
    """Place every completion's objects; returns the flattened, jittered hypotheses."""
    K = len(completions)
    known = ctx.by_id()
    floor_known = [o for o in ctx.objects if o.parent_id is None]
    known_xy = np.array([o.node.box.center[:2] for o in floor_known]).reshape(-1, 2)
    known_half = np.array([np.asarray(o.node.box.extent[:2]) / 2 for o in floor_known]).reshape(-1, 2)
    placed: dict[tuple[int, int], tuple[np.ndarray, tuple[float, float, float]]] = {}
    out_label: list[str] = []
    out_xyz: list[np.ndarray] = []
    out_size: list[float] = []
    out_room: list[str | None] = []
    out_comp: list[int] = []
    dropped = 0

    def proposals_for(k: int, i: int, obj: HypObject) -> _Pending | None:
        label = prior.canonical_label(obj.label)
        item = prior.item(label)
        w, d, h = item.size_m
        if obj.xyz is not None:
            base = np.asarray(obj.xyz, dtype=np.float64).copy()
            if base[2] <= 0.0:  # no height given: from the catalogue's placement
                base[2] = {"wall_mounted": 1.4, "ceiling": CEILING_Z_M, "on": 0.9 + h / 2}.get(
                    item.placement, h / 2
                )
            props = base + np.column_stack([rng.normal(0, 0.3, (proposals, 2)), np.zeros(proposals)])
            props[0] = base
            return _Pending(k, obj, label, w, d, h, props, item.placement in ("floor", "floor_wall"))
        if obj.parent is not None:
            if obj.parent.startswith("new:"):
                j = int(obj.parent[4:])
                if (k, j) not in placed:
                    return None
                center, (pw, pd, ph) = placed[(k, j)]
                ext, yaw = np.array([pw, pd, ph]), 0.0
                parent_label = prior.canonical_label(completions[k].objects[j].label)
            else:
                par = known.get(obj.parent)
                if par is None:
                    return None
                center = np.asarray(par.node.box.center, dtype=np.float64)
                ext = np.asarray(par.node.box.extent, dtype=np.float64)
                yaw, parent_label = par.node.box.yaw_rad, par.label
            props = _footprint_props(center, ext, yaw, h, proposals, parent_label in SHELF_LIKE, rng)
            return _Pending(k, obj, label, w, d, h, props, False)
        room = ctx.room(obj.room) if obj.room else None
        if room is None:
            if not ctx.rooms:
                return None
            room = ctx.rooms[int(rng.integers(len(ctx.rooms)))]
        props, floor = _room_props(room.xy_min, room.xy_max, item.placement, w, d, h, proposals, rng)
        return _Pending(k, obj, label, w, d, h, props, floor)

    # Two passes: objects first, then the ones standing on objects placed in the first pass.
    for pass_new in (False, True):
        pend: list[tuple[int, int, _Pending]] = []
        for k, comp in enumerate(completions):
            for i, obj in enumerate(comp.objects):
                on_new = obj.parent is not None and obj.parent.startswith("new:")
                if on_new != pass_new:
                    continue
                p = proposals_for(k, i, obj)
                if p is None:
                    dropped += 1
                    continue
                pend.append((k, i, p))
        if not pend:
            continue
        all_props = np.concatenate([p.props for _, _, p in pend])
        sizes = np.concatenate([np.full(p.props.shape[0], prior.detect_size_m(p.label)) for _, _, p in pend])
        bad = seen(all_props, sizes)
        is_floor = np.concatenate([np.full(p.props.shape[0], p.floor) for _, _, p in pend])
        if is_floor.any():
            bad[is_floor] |= floor_seen(all_props[is_floor, :2])
        off = 0
        for k, i, p in pend:
            n = p.props.shape[0]
            b = bad[off : off + n].copy()
            if p.floor:
                b |= _overlaps_known(p.props[:, :2], max(p.w, p.d) / 2, known_xy, known_half)
            off += n
            ok = np.flatnonzero(~b)
            if ok.size:
                xyz = p.props[ok[0]]
            elif rng.random() >= detect_reject:
                xyz = p.props[0]  # every placement was seen, but detections can miss: keep a few anyway
            else:
                dropped += 1
                continue
            placed[(k, i)] = (xyz, (p.w, p.d, p.h))
            out_label.append(p.label)
            out_xyz.append(xyz)
            out_size.append(prior.detect_size_m(p.label))
            out_room.append(p.obj.room)
            out_comp.append(k)

    labels = tuple(sorted(set(out_label)))
    lidx = {lab: j for j, lab in enumerate(labels)}
    H = len(out_label)
    J = max(1, n_jitter)
    xyz = np.array(out_xyz, dtype=np.float64).reshape(H, 3)
    rep_xyz = np.repeat(xyz[:, None, :], J, axis=1)
    if J > 1 and jitter_m > 0:
        noise = rng.normal(0.0, jitter_m, size=(H, J - 1, 2))
        rep_xyz[:, 1:, :2] += noise
    comp_of = np.array(out_comp, dtype=np.int64)
    sample = comp_of[:, None] * J + np.arange(J)[None, :]
    return Hypotheses(
        labels=labels,
        label_idx=np.repeat(np.array([lidx[lab] for lab in out_label], dtype=np.int64), J),
        xyz=rep_xyz.reshape(H * J, 3),
        size_m=np.repeat(np.array(out_size, dtype=np.float64), J),
        room=tuple(r for r in out_room for _ in range(J)),
        sample_idx=sample.reshape(-1),
        n_completions=K,
        n_jitter=J,
        dropped=dropped,
    )
