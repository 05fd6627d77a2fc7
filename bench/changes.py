"""``argus eval changes``: how fast the graph follows a room that changes, and whether passers-by delete anything.

An apartment changes during an episode (:mod:`sim.changes`: objects moved within a room and to another room,
removed, added) while people walk between rooms (:mod:`sim.people`: person-sized occluders the ORACLE semantic
camera labels ``person``). Fixed cameras (1-3, calibrated, high in the largest rooms, where every other edit happens)
and one robot touring the apartment stream frames at ``fps`` into an in-process mapper per geometry (``oracle``: true
depth and poses; ``mvs``: RGB-only), all fed the same frames. Every ``score_every_s`` the graph the mapper publishes
(its live node list: a node it retires drops out, whatever the mapper calls it) is scored against the ground truth
of that instant:

- **time to right** per edit: from the edit until the graph is right about that object again: a moved object has a
  node within ``right_m`` at its new place (label-matched, :func:`sim.scoring.score_nodes`) and no node left at its
  old place; a removed object has no node left at its place; an added object has a node. With the robot frames
  that saw the place meanwhile, whether a fixed camera sees it, whether the graph knew the object before the edit,
  and for moves whether the node kept its id;
- **stale nodes** over time: nodes that match only what is no longer there (an old place, a removed object);
- **false retirements**: a node of an object that still exists, unchanged, disappears from the graph and no other
  node takes its place; those with a person within ``person_near_m`` of the object meanwhile are the people's;
- **F1 over time** (a plot), outside the ``settle_s`` after each edit against the same episode without edits and
  people (``reference``);
- **person nodes**: nodes labelled ``person`` are never objects (not scored as false positives) and are counted.

Time is the episode's: the mapper handles every frame before the next one is taken, so its compute time is not in
the figures (``realtime_factor`` says how many seconds of mapper wall time each simulated second cost here).

Example::

    argus eval changes --quick --out eval_out          # one furnished room, 1 camera, 30 s, oracle only
    argus eval changes --out eval_out                  # apartment, 2 cameras + robot, 8 edits, 2 people
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

PERSON_LABEL = "person"


class ChangesConfig(BaseModel):
    """The dynamic-scene experiment: an apartment that changes while cameras and a robot watch it."""

    model_config = ConfigDict(extra="forbid")
    family: str = Field(default="apartment", description="scene family")
    seeds: list[int] = Field(default_factory=lambda: [0], description="scene seeds (each also seeds its edits)")
    geometries: list[str] = Field(default_factory=lambda: ["oracle", "mvs"], description="reconstructors, fed the "
                                  "same frames")
    perception: str = Field(default="sim", description="2D perception (sim = ORACLE semantic camera)")
    cameras: int = Field(default=2, ge=0, le=3, description="fixed cameras (calibrated, largest rooms first)")
    robot: bool = Field(default=True, description="one robot touring the scene")
    duration_s: float = Field(default=120.0, gt=0.0, description="episode length, simulated seconds")
    fps: float = Field(default=2.0, gt=0.0, description="frames per second of every camera")
    edits: int = Field(default=8, ge=0, description="random edits over the episode")
    edit_kinds: list[str] = Field(default_factory=lambda: ["move", "remove", "add"], description="edit kinds in turn")
    edit_window: tuple[float, float] = Field(default=(0.15, 0.7), description="edits happen in this part of the "
                                             "episode (fractions)")
    script: list[dict[str, Any]] | None = Field(default=None, description="scripted edits instead of random ones "
                                                "(sim.changes.edits_from_spec)")
    people: int = Field(default=2, ge=0, description="people walking between rooms the whole episode")
    robot_speed_mps: float = Field(default=0.5, gt=0.0, description="robot speed along its tour")
    width: int = Field(default=320, ge=32, description="image width, px")
    height: int = Field(default=240, ge=24, description="image height, px")
    score_every_s: float = Field(default=1.0, gt=0.0, description="score the graph this often")
    right_m: float = Field(default=0.5, gt=0.0, description="a node this close to an object (label-matched) is it")
    settle_s: float = Field(default=5.0, ge=0.0, description="F1 after an edit is excused this long")
    person_near_m: float = Field(default=1.5, gt=0.0, description="a person this close to an object that lost its "
                                 "node is taken as the cause")
    reference: bool = Field(default=True, description="also run the episode without edits and people (the static "
                            "F1 the dynamic one is compared with)")
    prior_noise_m: float = Field(default=0.02, ge=0, description="robot odometry prior noise (std, metres)")
    prior_noise_deg: float = Field(default=1.0, ge=0, description="robot odometry prior noise (std, degrees yaw)")
    mapper: dict[str, Any] = Field(default_factory=dict, description="mapper configuration written over the "
                                   "defaults (nested tables, as in the mapper's TOML)")


def quick_changes() -> ChangesConfig:
    """A run small enough for a smoke test: one furnished room, one camera and the robot, 30 s, 3 edits, one
    person, oracle geometry, small frames."""
    return ChangesConfig(family="furnished_room", seeds=[0], geometries=["oracle"], cameras=1, duration_s=30.0,
                         edits=3, people=1, width=160, height=120, reference=False, edit_window=(0.2, 0.5))


# --- scoring (pure: no mapper, no renderer) ---------------------------------------------------------------------
def live_nodes(nodes: Sequence[Any]) -> list[Any]:
    """The nodes the graph still holds: any the mapper marks retired (``retired`` true, ``retired_ns`` set or
    ``status == "retired"``) are gone."""
    out = []
    for n in nodes:
        if getattr(n, "retired", False) or getattr(n, "retired_ns", None) or getattr(n, "status", None) == "retired":
            continue
        out.append(n)
    return out


def is_person(node: Any) -> bool:
    return " ".join(str(node.label).lower().replace("_", " ").split()) == PERSON_LABEL


def place_visible(center: Sequence[float] | np.ndarray, K: Any, T_world_cam: np.ndarray, depth_m: np.ndarray,
                  margin_m: float = 0.3) -> bool:
    """Whether the point ``center`` is in the image and not hidden: the rendered depth at its pixel is no nearer
    than the point less ``margin_m`` (a removed object's place shows what was behind it, which counts)."""
    T = np.linalg.inv(np.asarray(T_world_cam, np.float64))
    p = T[:3, :3] @ np.asarray(center, np.float64) + T[:3, 3]
    if p[2] <= 0.1:
        return False
    u, v = p[0] / p[2] * K.fx + K.cx, p[1] / p[2] * K.fy + K.cy
    if not (0 <= u < K.width and 0 <= v < K.height):
        return False
    d = float(depth_m[int(v), int(u)])
    return d == 0.0 or d >= p[2] - margin_m


def place_seen(box: Any, K: Any, T_world_cam: np.ndarray, depth_m: np.ndarray, min_visible: float = 0.5,
               occupied: bool = True) -> bool:
    """Whether a view sees an object's place (``box``, an oriented box): at least ``min_visible`` of 27 points
    spread through it are in the image and not hidden (:func:`place_visible`; where the object stands,
    ``occupied``, the margin grows by half the box's largest side: its own front hides its inside). The centre
    alone counts a view that sees it past the edge of what hides the rest (a table in front of a chair)."""
    c = np.asarray(box.center, float)
    ext = np.asarray(box.extent, float)
    cy, sy = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    R = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    f = np.array([-1.0, 0.0, 1.0]) / 3.0
    grid = np.stack(np.meshgrid(f, f, f, indexing="ij"), -1).reshape(-1, 3) * ext
    margin = 0.3 + (0.5 * float(ext.max()) if occupied else 0.0)
    seen = sum(place_visible(c + R @ g, K, T_world_cam, depth_m, margin) for g in grid)
    return seen >= min_visible * len(grid)


@dataclass
class _EditTrack:
    index: int
    edit: Any
    old: Any  # the object before the edit (None for an add)
    new: Any  # the object after it (None for a removal)
    places: list[tuple[Any, bool]]  # the boxes of the object's old and new place; whether it stands there
    known_before: bool | None = None
    node_before: str | None = None
    t_right: float | None = None
    node_after: str | None = None
    robot_views: int = 0  # robot frames that saw a place of the edit, from the edit until right
    fixed_views: int = 0
    robot_views_to_right: int | None = None


@dataclass
class ChangeScorer:
    """Scores a graph timeline against a :class:`sim.changes.ChangingScene`: call :meth:`note_view` for each frame
    (optional: which views saw an edit's place), :meth:`observe` with the graph's nodes at each scoring time (in
    time order), then :meth:`result`."""

    world: Any
    people: Any = None
    right_m: float = 0.5
    settle_s: float = 5.0
    person_near_m: float = 1.5
    similarity: Any = None
    samples: list[dict[str, Any]] = field(default_factory=list)
    retirements: list[dict[str, Any]] = field(default_factory=list)
    person_node_ids: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.tracks: list[_EditTrack] = []
        for i, e in enumerate(self.world.edits):
            before = self.world.states[i]
            old = before.object_by_id(e.obj_id) if e.kind != "add" else None
            new = e.obj
            places = [(o.box, o is new) for o in (old, new) if o is not None]  # (box, the object stands there)
            self.tracks.append(_EditTrack(i, e, old, new, places))
        self._prev: tuple[float, dict[int, str], int] | None = None  # time, obj -> node, state index

    def note_view(self, t_s: float, robot: bool, K: Any, T_world_cam: np.ndarray, depth_m: np.ndarray) -> None:
        """A frame taken at ``t_s``: counts, per pending edit, the views that saw one of its places."""
        for tr in self.tracks:
            if tr.edit.t_s > t_s or tr.t_right is not None:
                continue
            if any(place_seen(b, K, T_world_cam, depth_m, occupied=there) for b, there in tr.places):
                if robot:
                    tr.robot_views += 1
                else:
                    tr.fixed_views += 1

    def observe(self, t_s: float, nodes: Sequence[Any], retired: Iterable[str] = ()) -> dict[str, Any]:
        """Score the graph ``nodes`` at ``t_s``; returns the sample (also kept). ``retired``: the ids the mapper
        retired as seen gone so far (a false retirement among them is the absence evidence's; the others went by
        fusion: merged into another node, pruned)."""
        from sim.scoring import score_nodes, shared_similarity

        sim = self.similarity or shared_similarity()
        alive = live_nodes(nodes)
        persons = [n for n in alive if is_person(n)]
        self.person_node_ids.update(n.node_id for n in persons)
        objs_nodes = [n for n in alive if not is_person(n)]
        k_state = self.world.state_index(t_s)
        state = self.world.states[k_state]
        sc = score_nodes(objs_nodes, state, distance_m=self.right_m, similarity=sim)
        obj_node = {m.obj_id: m.node_id for m in sc.matches}
        # stale: nodes that match no object of now but an object as it was before an edit that has happened
        done = [tr for tr in self.tracks if tr.edit.t_s <= t_s and tr.old is not None]
        unmatched = [n for n in objs_nodes if n.node_id in set(sc.unmatched_pred)]
        ghost_node: dict[int, str] = {}  # edit index -> stale node
        if done and unmatched:
            ghosts = [_ghost(tr.index, tr.old) for tr in done]
            gs = score_nodes(unmatched, SimpleNamespace(objects=ghosts), distance_m=self.right_m, similarity=sim)
            ghost_node = {m.obj_id: m.node_id for m in gs.matches}
        for tr in self.tracks:
            e = tr.edit
            if e.t_s > t_s:
                if tr.old is not None:  # the last sample before the edit: did the graph know the object?
                    tr.node_before = obj_node.get(e.obj_id)
                    tr.known_before = tr.node_before is not None
                continue
            if tr.t_right is not None:
                continue
            found = e.kind == "remove" or e.obj_id in obj_node
            cleared = tr.old is None or tr.index not in ghost_node
            if found and cleared:
                tr.t_right = t_s
                tr.node_after = obj_node.get(e.obj_id)
                tr.robot_views_to_right = tr.robot_views
        self._retirements(t_s, k_state, obj_node, {n.node_id for n in alive}, set(retired))
        sample = {"t_s": round(float(t_s), 3), "nodes": len(objs_nodes), "person_nodes": len(persons),
                  "precision": sc.precision, "recall": sc.recall, "f1": sc.f1, "n_true": sc.n_true,
                  "stale": len(ghost_node), "edits_done": sum(tr.edit.t_s <= t_s for tr in self.tracks),
                  "edits_right": sum(tr.t_right is not None for tr in self.tracks)}
        self.samples.append(sample)
        self._prev = (t_s, obj_node, k_state)
        return sample

    def _retirements(self, t_s: float, k_state: int, obj_node: dict[int, str], alive: set[str],
                     retired: set[str]) -> None:
        if self._prev is None:
            return
        t0, prev, k0 = self._prev
        s0, s1 = self.world.states[k0], self.world.states[k_state]
        now = {o.obj_id: o for o in s1.objects}
        for obj_id, node_id in prev.items():
            o = now.get(obj_id)
            # only objects still there and untouched since (an edited object's node may rightly go)
            if o is None or o is not s0.object_by_id(obj_id) or obj_id in obj_node or node_id in alive:
                continue
            near = self._person_distance(t0, t_s, np.asarray(o.box.center, float))
            self.retirements.append({"t_s": round(float(t_s), 3), "obj_id": obj_id, "label": o.label,
                                     "node_id": node_id, "person_m": None if near is None else round(near, 2),
                                     "person": near is not None and near <= self.person_near_m,
                                     "seen_gone": node_id in retired})

    def _person_distance(self, t0: float, t1: float, xyz: np.ndarray) -> float | None:
        if self.people is None or not self.people.walks:
            return None
        ts = np.linspace(t0, t1, max(2, int(math.ceil((t1 - t0) / 0.25)) + 1))
        return float(min(np.min(np.hypot(*(self.people.positions(t) - xyz[:2]).T)) for t in ts))

    def result(self, reference: Sequence[dict[str, Any]] | None = None) -> dict[str, Any]:
        """Per-edit rows, the timeline and the summary figures (``reference``: the samples of the same episode
        without edits and people, for the F1 ratio)."""
        edits = []
        for tr in self.tracks:
            e = tr.edit
            ttr = None if tr.t_right is None else round(tr.t_right - e.t_s, 3)
            edits.append({"t_s": round(e.t_s, 3), "kind": e.kind, "obj_id": e.obj_id,
                          "label": (tr.new or tr.old).label, "note": e.note,
                          "where": "fixed" if tr.fixed_views else "robot",
                          "known_before": tr.known_before, "time_to_right_s": ttr,
                          "robot_views_to_right": tr.robot_views_to_right, "robot_views": tr.robot_views,
                          "fixed_views": tr.fixed_views,
                          # only a move of an object the graph knew, once right, says whether its node kept its id
                          "kept_id": tr.node_before == tr.node_after
                          if e.kind == "move" and tr.t_right is not None and tr.node_before is not None else None})
        f1 = np.array([s["f1"] for s in self.samples], float)
        ts = np.array([s["t_s"] for s in self.samples], float)
        calm = np.ones(len(ts), bool)
        for tr in self.tracks:
            calm &= ~((ts >= tr.edit.t_s) & (ts < tr.edit.t_s + self.settle_s))
        ratio = None
        if reference:
            ref = {round(s["t_s"], 3): s["f1"] for s in reference}
            r = [f / ref[t] for f, t in zip(f1[calm], ts[calm], strict=True) if ref.get(t, 0) > 0]
            ratio = float(min(r)) if r else None
        stale = np.array([s["stale"] for s in self.samples], float)
        return {"edits": edits, "timeline": self.samples, "false_retirements": self.retirements,
                "summary": {
                    **_edit_stats(edits),
                    "stale_mean": float(stale.mean()) if len(stale) else 0.0,
                    "stale_max": int(stale.max()) if len(stale) else 0,
                    "stale_end": int(stale[-1]) if len(stale) else 0,
                    "false_retirements": len(self.retirements),
                    "false_retirements_people": sum(r["person"] for r in self.retirements),
                    "false_retirements_seen_gone": sum(r["seen_gone"] for r in self.retirements),
                    "person_nodes": len(self.person_node_ids),
                    "f1_end": float(f1[-1]) if len(f1) else 0.0,
                    "f1_min_calm": float(f1[calm].min()) if calm.any() else None,
                    "f1_ratio_min_calm": ratio,
                }}


def _ghost(index: int, obj: Any) -> Any:
    """An object as it was before edit ``index``, under the edit's index as id (what a stale node matches)."""
    return SimpleNamespace(obj_id=index, label=obj.label, box=obj.box)


def _edit_stats(edits: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Time-to-right percentiles over all edits and per where they were seen; unresolved edits count as never."""
    out: dict[str, Any] = {"edits": len(edits), "right": sum(e["time_to_right_s"] is not None for e in edits)}
    for name, sel in (("all", edits), ("fixed", [e for e in edits if e["where"] == "fixed"]),
                      ("robot", [e for e in edits if e["where"] == "robot"])):
        t = [e["time_to_right_s"] for e in sel]
        done = [x for x in t if x is not None]
        out[f"{name}_n"] = len(sel)
        out[f"{name}_right"] = len(done)
        # a percentile over edits that never came right is at least "never": inf
        vals = np.array([x if x is not None else math.inf for x in t], float)
        out[f"{name}_p50_s"] = float(np.percentile(vals, 50, method="higher")) if len(vals) else None
        out[f"{name}_p90_s"] = float(np.percentile(vals, 90, method="higher")) if len(vals) else None
    rv = [e["robot_views_to_right"] for e in edits if e["where"] == "robot" and e["robot_views_to_right"] is not None]
    out["robot_views_to_right_max"] = max(rv) if rv else None
    moves = [e for e in edits if e["kind"] == "move" and e["kept_id"] is not None]
    out["moves_kept_id"] = f"{sum(bool(e['kept_id']) for e in moves)}/{len(moves)}"
    return out


# --- the episode --------------------------------------------------------------------------------------------------
def robot_poses(scene: Any, n: int, cfg: ChangesConfig, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` true robot camera poses (one per frame) of a tour of the scene (``bench.rooms.tour_walk``, walked
    back and forth when it ends early) and their odometry priors."""
    from bench.rooms import RoomsConfig, tour_walk

    rc = RoomsConfig(step_m=cfg.robot_speed_mps / cfg.fps, max_frames=max(n, 2), look_around=4,
                     prior_noise_m=cfg.prior_noise_m, prior_noise_deg=cfg.prior_noise_deg)
    poses, priors = tour_walk(scene, rc, seed)
    while len(poses) < n:
        poses, priors = poses + poses[::-1], priors + priors[::-1]
    return poses[:n], priors[:n]


def run_episode(family: str, seed: int, cfg: ChangesConfig, torch_threads: int, log: Callable[[str], None],
                dynamic: bool = True) -> dict[str, Any]:
    """One episode, every geometry fed the same frames; per geometry the scorer's result (no edits and no
    people when ``dynamic`` is False: the reference)."""
    from bench.explore import mapper_config
    from mapper.core import MapperCore
    from mapper.geometry.contract import OracleData, View
    from protocol.messages import Intrinsics
    from sim.cameras import place_fixed_cameras
    from sim.changes import ChangingScene, edits_from_spec, random_edits
    from sim.nav import NavMap
    from sim.people import People, plan_walks
    from sim.scene import generate_scene

    scene = generate_scene(family, seed)
    K = Intrinsics.from_fov(cfg.width, cfg.height, 90.0)
    cams = place_fixed_cameras(scene, cfg.cameras, seed, intrinsics=K) if cfg.cameras else []
    edits = []
    if dynamic:
        if cfg.script is not None:
            edits = edits_from_spec(scene, cfg.script, seed)
        elif cfg.edits:
            edits = random_edits(scene, cfg.edits, cfg.duration_s, seed, kinds=cfg.edit_kinds,
                                 window=cfg.edit_window, focus=[c.room for c in cams] or None)
    world = ChangingScene(scene, edits)
    walks = plan_walks(NavMap(scene), cfg.people, cfg.duration_s, seed) if dynamic and cfg.people else []
    people = People(walks, seed=seed) if walks else None
    n_ticks = int(math.floor(cfg.duration_s * cfg.fps + 1e-9)) + 1
    poses, priors = robot_poses(scene, n_ticks, cfg, seed) if cfg.robot else ([], [])
    cores = {g: MapperCore(mapper_config(g, cfg.perception, torch_threads, cfg.mapper or None))
             for g in cfg.geometries}
    scorers = {g: ChangeScorer(world, people, cfg.right_m, cfg.settle_s, cfg.person_near_m) for g in cfg.geometries}
    map_s = dict.fromkeys(cfg.geometries, 0.0)
    every = max(1, int(round(cfg.score_every_s * cfg.fps)))
    t_wall = time.perf_counter()
    if dynamic:
        for e in edits:
            log(f"changes {family}/{seed}: edit at {e.t_s:.1f}s: {e.note}")
    for k in range(n_ticks):
        t = k / cfg.fps
        labels = world.labels_at(t, people)
        frames: list[tuple[str, Any, np.ndarray, np.ndarray | None, bool]] = [
            (c.camera_id, c.intrinsics, np.asarray(c.T_world_cam, float), np.asarray(c.T_world_cam, float), True)
            for c in cams]
        if cfg.robot:
            frames.append(("robot0", K, poses[k], np.asarray(priors[k]), False))
        for source, intr, T_true, prior, fixed in frames:
            out = world.render(intr, T_true, t, people=people)
            oracle = OracleData(depth_m=out.depth_m.astype(np.float32), T_world_cam_true=T_true,
                                instance_id=out.instance_id.astype(np.int32), labels=labels)
            # the robot's priors carry independent per-frame errors (no relative information), as bench.rooms says
            rel = None if fixed else math.inf
            view = View(image=out.rgb, source_id=source, intrinsics=intr, T_world_cam=prior, pose_trusted=fixed,
                        stamp_ns=int(round(t * 1e9)) + 1_000_000_000, seq=k, oracle=oracle,
                        prior_rel_rot_deg=rel, prior_rel_trans_m=rel)
            for g, core in cores.items():
                t0 = time.perf_counter()
                core.ingest(view)
                map_s[g] += time.perf_counter() - t0
                scorers[g].note_view(t, not fixed, intr, T_true, out.depth_m)
        if k % every == 0 or k == n_ticks - 1:
            for g, core in cores.items():
                s = scorers[g].observe(t, core.nodes(), core.store.retired)
                if k % (every * 10) == 0 or k == n_ticks - 1:
                    log(f"changes {family}/{seed} {g}{'' if dynamic else ' (reference)'} t={t:.0f}s: nodes "
                        f"{s['nodes']} F1 {s['f1']:.3f} stale {s['stale']} edits right {s['edits_right']}/"
                        f"{s['edits_done']} person nodes {s['person_nodes']} "
                        f"(wall {time.perf_counter() - t_wall:.0f}s)")
    out_rows = {}
    for g in cfg.geometries:
        res = scorers[g].result()
        res["mapper_s"] = round(map_s[g], 1)
        res["realtime_factor"] = round(map_s[g] / cfg.duration_s, 2)
        res["counters"] = {k: v for k, v in cores[g].counters.items() if v}
        out_rows[g] = (res, scorers[g])
    return {"rows": out_rows, "n_objects": len(scene.objects), "cameras": [c.room for c in cams],
            "people": len(walks), "edits": len(edits)}


def run_changes(cfg: ChangesConfig, torch_threads: int, log: Callable[[str], None]) -> dict[str, Any]:
    """Every seed; per (seed, geometry) the edits, timeline and summary; per geometry the pooled summary."""
    per_run = []
    for seed in cfg.seeds:
        t0 = time.perf_counter()
        ep = run_episode(cfg.family, seed, cfg, torch_threads, log)
        ref = run_episode(cfg.family, seed, cfg, torch_threads, log, dynamic=False) if cfg.reference else None
        for g, (res, scorer) in ep["rows"].items():
            if ref is not None:
                res = scorer.result(reference=ref["rows"][g][0]["timeline"])
                res["mapper_s"], res["realtime_factor"] = ep["rows"][g][0]["mapper_s"], ep["rows"][g][0][
                    "realtime_factor"]
                res["counters"] = ep["rows"][g][0]["counters"]
                res["reference_timeline"] = ref["rows"][g][0]["timeline"]
                # nodes of unchanged objects lost in the static episode too: fusion's churn, not the changes'
                res["summary"]["reference_false_retirements"] = ref["rows"][g][0]["summary"]["false_retirements"]
            res.update(family=cfg.family, seed=seed, geometry=g, n_objects=ep["n_objects"],
                       camera_rooms=ep["cameras"], people=ep["people"], seconds=round(time.perf_counter() - t0, 1))
            per_run.append(res)
            s = res["summary"]
            log(f"changes {cfg.family}/{seed} {g}: right {s['right']}/{s['edits']} edits, time to right p50 "
                f"{_fmt_s(s['all_p50_s'])} p90 {_fmt_s(s['all_p90_s'])}, stale mean {s['stale_mean']:.1f}, false "
                f"retirements {s['false_retirements']} ({s['false_retirements_people']} near people), person nodes "
                f"{s['person_nodes']}, F1 end {s['f1_end']:.3f}")
    summary = []
    for g in cfg.geometries:
        runs = [r for r in per_run if r["geometry"] == g]
        edits = [e for r in runs for e in r["edits"]]
        entry: dict[str, Any] = {"geometry": g, "runs": len(runs), **_edit_stats(edits)}
        for k in ("stale_mean", "f1_end"):
            entry[k] = float(np.mean([r["summary"][k] for r in runs]))
        entry["stale_max"] = max(r["summary"]["stale_max"] for r in runs)
        entry["false_retirements"] = sum(r["summary"]["false_retirements"] for r in runs)
        for k in ("false_retirements_people", "false_retirements_seen_gone", "reference_false_retirements"):
            entry[k] = sum(r["summary"].get(k, 0) for r in runs)
        entry["person_nodes"] = sum(r["summary"]["person_nodes"] for r in runs)
        calm = [r["summary"]["f1_min_calm"] for r in runs if r["summary"]["f1_min_calm"] is not None]
        entry["f1_min_calm"] = min(calm) if calm else None
        ratio = [r["summary"]["f1_ratio_min_calm"] for r in runs if r["summary"]["f1_ratio_min_calm"] is not None]
        entry["f1_ratio_min_calm"] = min(ratio) if ratio else None
        entry["realtime_factor"] = float(np.mean([r["realtime_factor"] for r in runs]))
        summary.append(entry)
    return {"config": cfg.model_dump(mode="json"), "per_run": per_run, "summary": summary}


def _fmt_s(v: float | None) -> str:
    if v is None:
        return "-"
    return "never" if not math.isfinite(v) else f"{v:.1f}s"


def _dash(v: Any) -> Any:
    return "-" if v is None else v


def changes_markdown(res: dict[str, Any]) -> str:
    from bench.report import markdown_table

    cfg = res["config"]
    rows = []
    for s in res["summary"]:
        ratio = s["f1_ratio_min_calm"]
        rows.append({"Geometry": s["geometry"], "Edits right": f"{s['right']}/{s['edits']}",
                     "Time to right p50 / p90": f"{_fmt_s(s['all_p50_s'])} / {_fmt_s(s['all_p90_s'])}",
                     "Fixed-view p90 (n)": f"{_fmt_s(s['fixed_p90_s'])} ({s['fixed_n']})",
                     "Robot-only p90 (n)": f"{_fmt_s(s['robot_p90_s'])} ({s['robot_n']})",
                     "Robot views to right (max)": _dash(s["robot_views_to_right_max"]),
                     "Moves kept id": s["moves_kept_id"],
                     "Stale nodes mean / max": f"{s['stale_mean']:.1f} / {s['stale_max']}",
                     "False retirements (people / seen gone / static episode)":
                         f"{s['false_retirements']} ({s['false_retirements_people']} / "
                         f"{s.get('false_retirements_seen_gone', '-')} / {s.get('reference_false_retirements', '-')})",
                     "Person nodes": s["person_nodes"], "F1 end": f"{s['f1_end']:.3f}",
                     "F1 min calm / static": "-" if ratio is None else f"{ratio:.2f}",
                     "Mapper s per sim s": f"{s['realtime_factor']:.2f}"})
    edit_rows = []
    for r in res["per_run"]:
        for e in r["edits"]:
            edit_rows.append({"Geometry": r["geometry"], "Seed": r["seed"], "t": f"{e['t_s']:.1f}s",
                              "Edit": e["note"], "Seen by": e["where"], "Known before": _dash(e["known_before"]),
                              "Time to right": _fmt_s(e["time_to_right_s"]),
                              "Robot views": e["robot_views_to_right"] if e["robot_views_to_right"] is not None
                              else e["robot_views"],
                              "Kept id": _dash(e["kept_id"])})
    return (f"## Dynamic scenes (argus eval changes)\n\n`{cfg['family']}` seeds {cfg['seeds']}, "
            f"{cfg['duration_s']:.0f} s at {cfg['fps']:g} fps, {cfg['cameras']} fixed camera(s)"
            f"{' + 1 touring robot' if cfg['robot'] else ''}, {cfg['edits']} edits, {cfg['people']} people walking "
            f"through; ORACLE 2D perception (sim semantic camera). Time to right: from the edit until a node is within "
            f"{cfg['right_m']} m of the new place and none is left at the old one (never: not by the episode's end). "
            f"F1 min calm / static: the lowest F1 outside {cfg['settle_s']:g} s after an edit over the same episode's "
            f"F1 without edits and people. Mapper s per sim s: the mapper's compute per simulated second here "
            f"(the figures are in simulated time). False retirements: nodes of unchanged objects lost; people: a "
            f"person came within {cfg['person_near_m']} m; seen gone: the mapper retired it on evidence of absence "
            f"(the rest were merged or pruned by fusion); static episode: as many lost without edits and people.\n\n"
            + markdown_table(rows) + "\n\n### Edits\n\n"
            + markdown_table(edit_rows) + "\n")


def changes_plot(res: dict[str, Any], path: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = res["per_run"]
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for i, r in enumerate(runs):
        t = [s["t_s"] for s in r["timeline"]]
        col = f"C{i}"
        name = f"{r['geometry']} seed {r['seed']}"
        axes[0].plot(t, [s["f1"] for s in r["timeline"]], color=col, label=f"F1 {name}")
        if r.get("reference_timeline"):
            axes[0].plot([s["t_s"] for s in r["reference_timeline"]], [s["f1"] for s in r["reference_timeline"]],
                         ":", color=col, label=f"F1 static {name}")
        axes[1].plot(t, [s["stale"] for s in r["timeline"]], color=col, label=f"stale {name}")
        for e in r["edits"]:
            for ax in axes:
                ax.axvline(e["t_s"], color="0.6", linewidth=0.7, linestyle="--")
            axes[1].annotate(e["kind"][0], (e["t_s"], 0), fontsize=7, color="0.3")
        for fr in r["false_retirements"]:
            axes[0].plot(fr["t_s"], 0.02, "x", color=col)
    axes[0].set_ylabel("node F1")
    axes[0].set_ylim(0, 1)
    axes[1].set_ylabel("stale nodes")
    axes[1].set_xlabel("episode time (s); dashed: edits (m move, r remove, a add); x: false retirements")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
