"""Scene files: a binary glTF (``.glb``) with the geometry plus a JSON with objects, relations, rooms, doors,
materials and (optionally) fixed cameras.

Every glTF node is named ``obj<id>_m<material>`` or ``structure_m<material>`` (one node per object and
material), so a scene edited in Blender (move, rescale, re-mesh objects; keep the node names) loads back
with its labels. glTF is y-up: the world (z-up) is rotated on export and back on load, so Blender shows
the floor flat. Boxes and centroids are recomputed on load for objects whose geometry moved.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, cast

import numpy as np
import trimesh

from protocol.messages import OrientedBox, vec3
from protocol.poses import rot_z
from sim.world import Scene, SceneObject

# world (z up) -> glTF (y up): x -> x, z -> y, y -> -z
T_GLTF_WORLD = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
T_WORLD_GLTF = T_GLTF_WORLD.T.copy()
_NODE_RE = re.compile(r"^(?:obj(\d+)|structure)_m(\d+)")


def _pieces(mesh: trimesh.Trimesh, face_material: np.ndarray) -> list[tuple[int, trimesh.Trimesh]]:
    out = []
    for m in np.unique(face_material):
        faces = np.nonzero(face_material == m)[0]
        sub = cast(trimesh.Trimesh, mesh.submesh([faces], append=True, repair=False))  # append: one mesh
        out.append((int(m), sub))
    return out


def export_scene(scene: Scene, out_dir: str | Path, stem: str | None = None,
                 cameras: list[Any] | None = None) -> tuple[Path, Path]:
    """Write ``<stem>.glb`` and ``<stem>.json`` into ``out_dir``; returns both paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = stem or f"{scene.family}_{scene.seed:03d}"
    glb_path, json_path = out / f"{stem}.glb", out / f"{stem}.json"
    materials = {}
    for i, m in enumerate(scene.materials):
        materials[i] = trimesh.visual.material.PBRMaterial(
            name=f"{m.name}_{i}", baseColorFactor=[*[int(round(c * 255)) for c in m.color1], 255],
            metallicFactor=0.0, roughnessFactor=0.9)
    tscene = trimesh.Scene()

    def add(prefix: str, mesh: trimesh.Trimesh, fm: np.ndarray) -> None:
        for mi, sub in _pieces(mesh, fm):
            g = sub.copy()
            g.apply_transform(T_GLTF_WORLD)
            g.visual = trimesh.visual.TextureVisuals(material=materials.get(mi))
            name = f"{prefix}_m{mi}"
            tscene.add_geometry(g, geom_name=name, node_name=name)

    add("structure", scene.structure, scene.structure_face_material)
    for o in scene.objects:
        fm = o.face_material if o.face_material is not None else np.zeros(len(o.mesh.faces), np.int32)
        add(f"obj{o.obj_id:04d}", o.mesh, fm)
    glb_path.write_bytes(tscene.export(file_type="glb"))
    data = scene.to_json(include_meshes=False)
    data["gltf"] = glb_path.name
    if cameras:
        data["cameras"] = [{"camera_id": c.camera_id, "intrinsics": c.intrinsics.model_dump(mode="json"),
                            "T_world_cam": np.asarray(c.T_world_cam).tolist(), "pose_known": c.pose_known,
                            "room": c.room} for c in cameras]
    json_path.write_text(json.dumps(data, indent=1))
    return glb_path, json_path


def _box_from_mesh(mesh: trimesh.Trimesh, yaw: float) -> OrientedBox:
    R = rot_z(-yaw)
    local = mesh.vertices @ R.T
    lo, hi = local.min(0), local.max(0)
    c = rot_z(yaw) @ ((lo + hi) / 2)
    return OrientedBox(center=vec3(c), extent=vec3(hi - lo), yaw_rad=yaw)


def load_scene(json_path: str | Path) -> Scene:
    """Read a scene written by :func:`export_scene` (the glTF named in the JSON sits beside it)."""
    jp = Path(json_path)
    data = json.loads(jp.read_text())
    if "gltf" not in data:
        return Scene.from_json(data)  # self-contained JSON (Scene.to_json with meshes)
    glb = jp.parent / data["gltf"]
    tscene = cast(trimesh.Scene, trimesh.load(str(glb), force="scene", process=False))
    parts: dict[int | None, list[tuple[trimesh.Trimesh, int]]] = {}
    for node in tscene.graph.nodes_geometry:
        T, gname = tscene.graph[node]
        m = _NODE_RE.match(str(node)) or _NODE_RE.match(str(gname))
        if m is None:
            continue  # a node we did not write (a light, a helper): ignored
        geom = tscene.geometry[gname]
        if not isinstance(geom, trimesh.Trimesh):
            continue
        g = trimesh.Trimesh(vertices=np.asarray(geom.vertices, np.float64), faces=np.asarray(geom.faces),
                            process=False)
        g.apply_transform(T_WORLD_GLTF @ np.asarray(T, np.float64))
        oid = int(m.group(1)) if m.group(1) is not None else None
        parts.setdefault(oid, []).append((g, int(m.group(2))))

    def merged(items: list[tuple[trimesh.Trimesh, int]]) -> tuple[trimesh.Trimesh, np.ndarray]:
        items = sorted(items, key=lambda x: x[1])
        mesh = cast(trimesh.Trimesh, trimesh.util.concatenate([g for g, _ in items])) if len(items) > 1 else items[0][0]
        fm = np.concatenate([np.full(len(g.faces), k, np.int32) for g, k in items])
        return mesh, fm

    if None not in parts:
        raise ValueError(f"{glb}: no structure nodes (structure_m<k>) found")
    meshes = {oid: merged(v) for oid, v in parts.items() if oid is not None}
    known = {int(o["obj_id"]) for o in data["objects"]}
    data = dict(data)
    data["objects"] = [o for o in data["objects"] if int(o["obj_id"]) in meshes]
    scene = Scene.from_json(data, meshes=meshes, structure=merged(parts[None]))
    missing = known - set(meshes)
    if missing:
        scene.relations = [r for r in scene.relations if r[0] not in missing and r[2] not in missing]
    # objects edited in a 3D tool: refresh their ground-truth box and centroid from the geometry
    fixed = []
    for o in scene.objects:
        box = _box_from_mesh(o.mesh, o.box.yaw_rad)
        if math.dist(box.center, o.box.center) > 0.005 or np.max(np.abs(np.subtract(box.extent, o.box.extent))) > 0.005:
            o = SceneObject(obj_id=o.obj_id, label=o.label, category=o.category, room=o.room, mesh=o.mesh, box=box,
                            parent_id=o.parent_id, centroid=np.asarray(box.center), T_world_obj=o.T_world_obj,
                            face_material=o.face_material, surfaces=())
        fixed.append(o)
    scene.objects = fixed
    scene.__post_init__()
    return scene


def load_cameras(json_path: str | Path) -> list[Any]:
    """Fixed cameras stored in a scene JSON (empty when none)."""
    from protocol.messages import Intrinsics
    from sim.cameras import FixedCamera

    data = json.loads(Path(json_path).read_text())
    return [FixedCamera(camera_id=c["camera_id"], intrinsics=Intrinsics.model_validate(c["intrinsics"]),
                        T_world_cam=np.asarray(c["T_world_cam"], float), pose_known=bool(c["pose_known"]),
                        room=str(c["room"])) for c in data.get("cameras", [])]
