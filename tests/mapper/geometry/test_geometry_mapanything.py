"""The mapanything adapter against a stand-in `mapanything` module with outputs of the documented shapes."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mapper.geometry.contract import View, anchor_pose, compose, pixel_rays
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from protocol.poses import look_at

INTR = Intrinsics.from_fov(8, 6, 80.0)
SCALE = 2.5


def _truth(n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(3)
    poses = [look_at([0.2 * i, 1.0, 1.2], [0.2 * i + 1.0, 3.0, 0.5]) for i in range(n)]
    depth_ray = [rng.uniform(0.8, 3.0, (6, 8)) for _ in range(n)]
    return poses, depth_ray


def _fake_module(calls: dict, use_quats: bool) -> dict[str, types.ModuleType]:
    class FakeMapAnything:
        @classmethod
        def from_pretrained(cls, name: str, **kw: object) -> FakeMapAnything:
            calls["from_pretrained"] = (name, kw)
            if "missing" in name:
                raise OSError("not in cache")
            return cls()

        def to(self, device: str) -> FakeMapAnything:
            return self

        def eval(self) -> None:
            pass

        def infer(self, views: list[dict], **kw: object) -> list[dict]:
            calls["views"] = views
            poses, depth_ray = _truth(len(views))
            # The real model (checked in test_models_real) predicts poses in its reference view's frame
            # whether or not poses were given: given poses are conditioning, not the output frame.
            ref = np.linalg.inv(poses[0])
            out = []
            for i in range(len(views)):
                T = ref @ poses[i]
                p = {
                    "ray_directions": torch.from_numpy(pixel_rays(INTR))[None],
                    "depth_along_ray": torch.from_numpy(depth_ray[i]).float()[None, ..., None],
                    "metric_scaling_factor": torch.tensor([SCALE]),
                    "conf": torch.full((1, 6, 8), 5.0),
                    "intrinsics": torch.from_numpy(INTR.K()).float()[None],
                    "cam_trans": torch.from_numpy(T[:3, 3]).float()[None],
                    "cam_quats": torch.from_numpy(Rotation.from_matrix(T[:3, :3]).as_quat()).float()[None],
                }
                if not use_quats:
                    p["camera_poses"] = torch.from_numpy(T).float()[None]
                out.append(p)
            return out

    pkg = types.ModuleType("mapanything")
    models = types.ModuleType("mapanything.models")
    models.MapAnything = FakeMapAnything  # type: ignore[attr-defined]
    utils = types.ModuleType("mapanything.utils")
    image = types.ModuleType("mapanything.utils.image")

    def preprocess_inputs(views: list[dict]) -> list[dict]:
        calls["preprocessed"] = True
        return views

    image.preprocess_inputs = preprocess_inputs  # type: ignore[attr-defined]
    return {"mapanything": pkg, "mapanything.models": models, "mapanything.utils": utils,
            "mapanything.utils.image": image}


def _views(n: int, with_poses: bool) -> list[View]:
    poses, _ = _truth(n)
    img = np.zeros((6, 8, 3), np.uint8)
    return [View(img, "c", INTR, poses[i] if with_poses else None, seq=i) for i in range(n)]


@pytest.mark.parametrize("use_quats", [False, True])
@pytest.mark.parametrize("with_poses", [True, False])
def test_maps_outputs_into_contract(monkeypatch: pytest.MonkeyPatch, use_quats: bool, with_poses: bool) -> None:
    calls: dict = {}
    for k, m in _fake_module(calls, use_quats).items():
        monkeypatch.setitem(sys.modules, k, m)
    rec = make_reconstructor("mapanything", checkpoint="some/model")
    views = _views(3, with_poses)
    r = rec.reconstruct(views, targets=[0, 2])
    assert calls["from_pretrained"] == ("some/model", {"local_files_only": True})
    assert calls["preprocessed"]
    assert ("camera_poses" in calls["views"][0]) == with_poses
    assert torch.allclose(calls["views"][1]["intrinsics"], torch.from_numpy(INTR.K()).float())
    assert r.metric_scale == pytest.approx(SCALE)
    poses, depth_ray = _truth(3)
    np.testing.assert_allclose(r.depth_along_ray[1], depth_ray[1] / SCALE, rtol=1e-5)
    assert r.confidence[1].max() == 0.0 and r.confidence[0].min() == pytest.approx(0.8)
    # Anchoring at the true first pose must give the true metric points, whatever the input.
    T_anchor = anchor_pose(r, views) if with_poses else poses[0]
    g = compose(r, T_anchor)
    for i in range(3):
        np.testing.assert_allclose(g.T_world_cam[i], poses[i], atol=1e-5)
        pts_cam = pixel_rays(INTR) * depth_ray[i][..., None]
        expected = pts_cam @ poses[i][:3, :3].T + poses[i][:3, 3]
        np.testing.assert_allclose(g.points_world[i], expected, atol=1e-4)


def test_missing_package_gives_install_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "mapanything", None)
    monkeypatch.setitem(sys.modules, "mapanything.models", None)
    with pytest.raises(RuntimeError, match="pip install"):
        make_reconstructor("mapanything")


def test_missing_checkpoint_is_clear_and_never_downloads(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: dict = {}
    for k, m in _fake_module(calls, False).items():
        monkeypatch.setitem(sys.modules, k, m)
    with pytest.raises(RuntimeError, match="missing/model.*huggingface-cli download missing/model"):
        make_reconstructor("mapanything", checkpoint="missing/model")
    assert calls["from_pretrained"][1] == {"local_files_only": True}


def test_module_not_imported_by_registry() -> None:
    import mapper.geometry.registry  # noqa: F401

    assert "mapanything" not in sys.modules or sys.modules["mapanything"] is None
