"""The embedded indoor prior: which objects occur in which rooms, what stands on what, sizes.

Authored by hand as data (``protocol/data/indoor_prior.json``) from general knowledge of homes, and
deliberately independent of the simulator's generator so the benchmark does not grade the planner
on a copy of its answer key.

It lives in ``protocol/`` because two processes that may not import each other read it: the planner
(completion sampling, room kinds of viewpoints) and the mapper (room labels from the objects a room holds,
mapper.rooms). ``planner.prior`` re-exports it.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

DEFAULT_PRIOR_PATH = Path(__file__).resolve().parent / "data" / "indoor_prior.json"
FORMAT = "argus-indoor-prior"
DEFAULT_SIZE_M = (0.4, 0.4, 0.4)
ABSENT_P = 0.03
"""Likelihood of an object kind in a room whose table does not list it (room-kind inference)."""


@dataclass(frozen=True)
class PriorEntry:
    """One row of a room or support table."""

    label: str
    p_present: float
    min_count: int
    max_count: int


@dataclass(frozen=True)
class CatalogItem:
    size_m: tuple[float, float, float]
    placement: str  # floor, floor_wall, wall_mounted, ceiling, on


@dataclass(frozen=True)
class IndoorPrior:
    """Parsed prior tables plus label and room-name canonicalisation."""

    rooms: dict[str, tuple[PriorEntry, ...]]
    on: dict[str, tuple[PriorEntry, ...]]
    catalog: dict[str, CatalogItem]
    label_aliases: dict[str, str]
    room_aliases: dict[str, str]
    room_kind_prior: dict[str, float]

    # -- labels -------------------------------------------------------------------------------
    def canonical_label(self, label: str) -> str:
        """Map a free-form label onto the prior's vocabulary (unknown labels come back normalised)."""
        s = _norm(label)
        words = s.split()
        # Longest suffix first: "small wooden dining chair" -> "wooden dining chair" -> ... -> "chair".
        for i in range(len(words)):
            cand = " ".join(words[i:])
            if cand in self.label_aliases:
                return self.label_aliases[cand]
            if cand in self.catalog:
                return cand
            if cand.endswith("s") and cand[:-1] in self.catalog:
                return cand[:-1]
        return s

    def item(self, label: str) -> CatalogItem:
        return self.catalog.get(label, CatalogItem(DEFAULT_SIZE_M, "floor"))

    def detect_size_m(self, label: str) -> float:
        """Characteristic size for detection (square root of the larger visible face)."""
        w, d, h = self.item(label).size_m
        return float(max(0.05, (max(w, d) * max(h, 0.5 * min(w, d))) ** 0.5))

    # -- rooms --------------------------------------------------------------------------------
    def room_kind(self, room_name: str | None) -> str | None:
        """Room kind from a room name such as ``bedroom_2`` or ``Living Room`` (None if unknown)."""
        if not room_name:
            return None
        s = re.sub(r"[\s\-]+", "_", room_name.strip().lower())
        s = re.sub(r"_?\d+$", "", s).strip("_")
        if s in self.rooms:
            return s
        if s in self.room_aliases:
            return self.room_aliases[s]
        for part in reversed(s.split("_")):
            if part in self.rooms:
                return part
            if part in self.room_aliases:
                return self.room_aliases[part]
        return None

    def kind_log_posterior(self, labels: list[str]) -> dict[str, float]:
        """log P(kind | furniture seen in the room), unnormalised, from presence probabilities."""
        out: dict[str, float] = {}
        for kind, entries in self.rooms.items():
            table = {e.label: e.p_present for e in entries}
            lp = float(_log(self.room_kind_prior.get(kind, 0.05)))
            for lab in labels:
                if any(lab in {e.label for e in es} for es in self.rooms.values()):
                    lp += _log(table.get(lab, ABSENT_P))
            out[kind] = lp
        return out


def _log(x: float) -> float:
    import math

    return math.log(max(x, 1e-9))


def _norm(label: str) -> str:
    s = label.strip().lower().replace("_", " ").replace("-", " ")
    s = re.sub(r"\d+", " ", s)
    return re.sub(r"\s+", " ", s).strip()


def _entries(rows: list) -> tuple[PriorEntry, ...]:
    out = []
    for r in rows:
        label, p, lo, hi = r
        if not (0.0 <= float(p) <= 1.0) or int(lo) < 0 or int(hi) < int(lo):
            raise ValueError(f"bad prior row {r!r}")
        out.append(PriorEntry(str(label), float(p), int(lo), int(hi)))
    return tuple(out)


def load_prior(path: Path | None = None) -> IndoorPrior:
    """Load and validate the prior JSON (``path`` defaults to the packaged one)."""
    p = Path(path) if path is not None else DEFAULT_PRIOR_PATH
    data = json.loads(p.read_text())
    if data.get("format") != FORMAT or int(data.get("version", 0)) != 1:
        raise ValueError(f"{p}: not an {FORMAT} v1 file")
    catalog = {}
    for label, (size, placement) in data["catalog"].items():
        if len(size) != 3 or min(size) <= 0:
            raise ValueError(f"{p}: bad size for {label!r}")
        catalog[label] = CatalogItem((float(size[0]), float(size[1]), float(size[2])), str(placement))
    return IndoorPrior(
        rooms={k: _entries(v["objects"]) for k, v in data["rooms"].items()},
        on={k: _entries(v) for k, v in data["on"].items()},
        catalog=catalog,
        label_aliases={_norm(k): v for k, v in data.get("label_aliases", {}).items()},
        room_aliases=dict(data.get("room_aliases", {})),
        room_kind_prior={k: float(v) for k, v in data.get("room_kind_prior", {}).items()},
    )
