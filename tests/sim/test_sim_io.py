"""glTF + JSON export/load round trip and the ``argus sim`` command line."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim import cli
from sim.cameras import place_fixed_cameras
from sim.io import export_scene, load_cameras, load_scene
from sim.render import Renderer
from sim.scene import generate_scene


def _same_triangles(a, b) -> bool:
    """Same triangles (any order, float32 precision) with the same materials."""
    from scipy.spatial import cKDTree

    ta = np.c_[np.asarray(a.mesh.triangles).reshape(-1, 9), a.face_material * 10.0]
    tb = np.c_[np.asarray(b.mesh.triangles).reshape(-1, 9), b.face_material * 10.0]
    if ta.shape != tb.shape:
        return False
    d, _ = cKDTree(tb).query(ta)
    return bool(d.max() < 1e-5)


def test_export_then_load_round_trips(tmp_path: Path) -> None:
    scene = generate_scene("furnished_room", 4)
    cams = place_fixed_cameras(scene, 2, 0)
    glb, js = export_scene(scene, tmp_path, cameras=cams)
    assert glb.read_bytes()[:4] == b"glTF"
    back = load_scene(js)
    assert [(o.obj_id, o.label, o.room, o.parent_id) for o in back.objects] == \
        [(o.obj_id, o.label, o.room, o.parent_id) for o in scene.objects]
    assert back.relations == scene.relations
    assert [r.name for r in back.rooms] == [r.name for r in scene.rooms]
    for a, b in zip(scene.objects, back.objects, strict=True):
        assert a.box == b.box
        assert _same_triangles(a, b)
    cams2 = load_cameras(js)
    assert [c.camera_id for c in cams2] == [c.camera_id for c in cams]
    assert np.allclose(cams2[0].T_world_cam, cams[0].T_world_cam)
    K = cams[0].intrinsics.scaled(160, 120)
    r1 = Renderer(scene).render(K, cams[0].T_world_cam)
    r2 = Renderer(back).render(K, cams[0].T_world_cam)
    assert (r1.instance_id == r2.instance_id).mean() > 0.999
    assert np.abs(r1.depth_m - r2.depth_m).max() < 1e-4


def test_load_refreshes_boxes_of_moved_objects(tmp_path: Path) -> None:
    import trimesh

    scene = generate_scene("furnished_room", 1)
    glb, js = export_scene(scene, tmp_path)
    # move one object in the glTF, as a user would in Blender (glTF is y-up: world x stays x)
    ts = trimesh.load(str(glb), force="scene", process=False)
    moved = scene.objects[0].obj_id
    for node in list(ts.graph.nodes_geometry):
        if str(node).startswith(f"obj{moved:04d}_"):
            T, g = ts.graph[node]
            T = np.array(T)
            T[0, 3] += 0.5
            ts.graph.update(node, matrix=T)
    glb.write_bytes(ts.export(file_type="glb"))
    back = load_scene(js)
    o, b = scene.object_by_id(moved), back.object_by_id(moved)
    assert abs(b.box.center[0] - o.box.center[0] - 0.5) < 1e-4
    assert back.object_by_id(scene.objects[1].obj_id).box == scene.objects[1].box


def test_load_rejects_other_files(tmp_path: Path) -> None:
    p = tmp_path / "x.json"
    p.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError):
        load_scene(p)
    assert cli.main(["load", str(p)]) == 2


def test_cli_render_writes_pngs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = cli.main(["render", "--family", "furnished_room", "--seed", "2", "--out", str(tmp_path), "--fixed", "1",
                   "--width", "160", "--height", "120"])
    assert rc == 0
    rgb = sorted(tmp_path.glob("*_rgb.png"))
    assert any("cam0" in p.name for p in rgb) and any("robot_" in p.name for p in rgb)
    for kind in ("rgb", "depth", "ids"):
        img = cv2.imread(str(tmp_path / f"furnished_room_002_cam0_{kind}.png"))
        assert img is not None and img.shape == (120, 160, 3)
    info = json.loads(capsys.readouterr().out)
    assert info["render_ms_per_frame"] > 0


def test_cli_export_load_view(tmp_path: Path) -> None:
    assert cli.main(["export", "--family", "furnished_room", "--seed", "3", "--out", str(tmp_path)]) == 0
    js = tmp_path / "furnished_room_003.json"
    assert js.exists() and (tmp_path / "furnished_room_003.glb").exists()
    assert len(json.loads(js.read_text())["cameras"]) == 3
    assert cli.main(["load", str(js), "--check"]) == 0
    rrd = tmp_path / "v.rrd"
    assert cli.main(["view", "--scene", str(js), "--out", str(rrd), "--fixed", "1"]) == 0
    assert rrd.stat().st_size > 10_000


def test_cli_check_small_sweep(tmp_path: Path) -> None:
    out = tmp_path / "check.json"
    assert cli.main(["check", "--seeds", "7", "--families", "furnished_room", "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["errors"] == 0 and rep["issues"] == 0 and len(rep["scenes"]) == 1


@pytest.mark.slow
def test_all_seeds_0_to_49_generate_cleanly(tmp_path: Path) -> None:
    out = tmp_path / "check.json"
    rc = cli.main(["check", "--seeds", "0-49", "--out", str(out)])
    rep = json.loads(out.read_text())
    assert rep["errors"] == 0, [s for s in rep["scenes"] if "error" in s]
    assert rc == 0, [s for s in rep["scenes"] if s.get("issues")]
    assert 90 <= rep["apartment_objects"]["mean"] <= 135
    assert 18 <= rep["furnished_room_objects"]["mean"] <= 32
