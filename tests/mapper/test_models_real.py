"""The optional learned backends against the REAL packages (random weights, built offline).

Slow tier. Each test skips with the reason when its extra is absent (pip install -e '.[sam]', '.[clip]',
'.[da3]', '.[mapanything]'). Images are real frames from ../shared/data (skipped when absent).
MapAnything's image encoder is DINOv2 loaded through torch.hub: it needs the hub code cached once
(TORCH_HOME with hub/facebookresearch_dinov2_main; see docs/backends.md).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapper.geometry.contract import View, anchor_pose, compose
from mapper.geometry.modelutil import ModelUnavailable
from mapper.geometry.registry import make_reconstructor
from protocol.messages import Intrinsics
from tests.support.procs import REPO

DATA = REPO.parent / "shared" / "data"
TUM = DATA / "tum-fr1-xyz"
pytestmark = pytest.mark.slow


def _have(mod: str) -> bool:
    return importlib.util.find_spec(mod) is not None


def _torchvision() -> None:
    """Import torchvision (CPU shim where PyPI's CUDA wheel sits beside a CPU torch; see torchvision_cpu)."""
    pytest.importorskip("torch")
    from tests.support.torchvision_cpu import ensure_torchvision

    try:
        ensure_torchvision()
    except ImportError:
        pytest.skip("torchvision not installed (needed by the model packages)")


def _need(module: str, extra: str) -> None:
    """Skip unless the extra's package is installed; then make torchvision importable (see _torchvision)."""
    if not _have(module):
        pytest.skip(f"extra `{extra}` not installed (pip install -e '.[{extra}]'; package {module})")
    _torchvision()


def _tum_views(idx: tuple[int, ...] = (0, 4, 8), crop: tuple[int, int] | None = None) -> list[View]:
    if not (TUM / "frames").is_dir():
        pytest.skip("real frames ../shared/data/tum-fr1-xyz absent")
    views = []
    for i in idx:
        img = cv2.imread(str(TUM / "frames" / f"frame-{i:06d}.color.png"))[:, :, ::-1]
        K = Intrinsics(width=640, height=480, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
        if crop is not None:  # odd size, not a multiple of any patch size
            h, w = crop
            img = img[:h, :w]
            K = Intrinsics(width=w, height=h, fx=525.0, fy=525.0, cx=319.5, cy=239.5)
        T = np.loadtxt(TUM / "frames" / f"frame-{i:06d}.pose.txt")
        views.append(View(image=np.ascontiguousarray(img), source_id="tum", intrinsics=K, T_world_cam=T, seq=i))
    return views


# ---------------------------------------------------------------- SAM
def test_sam_real_package_on_real_frames() -> None:
    _need("segment_anything", "sam")
    from mapper.perception.registry import make_segmenter

    seg = make_segmenter("sam", random_init=True, points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0,
                         min_mask_region_area=0)
    view = _tum_views((0,), crop=(331, 517))[0]  # odd size: SAM resizes to its 1024 long side itself
    masks = seg.segment(view)
    for m in masks:
        assert m.mask.shape == (331, 517) and m.mask.dtype == bool
    # random weights give arbitrary masks (possibly none); the plumbing must hold either way
    assert all(0.0 <= m.score or m.score != m.score for m in masks)


def test_sam_missing_checkpoint_is_one_clear_message(tmp_path: Path) -> None:
    _need("segment_anything", "sam")
    from mapper.perception.registry import make_segmenter
    from mapper.perception.sam import BackendUnavailable

    with pytest.raises(BackendUnavailable, match="does not exist"):
        make_segmenter("sam", checkpoint=str(tmp_path / "sam_vit_b.pth"))
    with pytest.raises(BackendUnavailable, match="needs a local checkpoint"):
        make_segmenter("sam")
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(BackendUnavailable, match="no CUDA GPU"):
            make_segmenter("sam", random_init=True, device="cuda")


# ---------------------------------------------------------------- CLIP
def test_clip_real_package_on_real_frames(tmp_path: Path) -> None:
    _need("open_clip", "clip")
    from mapper.perception.base import Mask2D
    from mapper.perception.registry import make_embedder

    vocab = tmp_path / "v.txt"
    vocab.write_text("chair\nmonitor\nkeyboard\n")
    emb = make_embedder("clip", random_init=True, vocabulary=vocab)
    view = _tum_views((0,))[0]
    m1 = np.zeros((480, 640), bool)
    m1[60:330, 280:610] = True
    m2 = np.zeros((120, 160), bool)  # a mask at a lower resolution than the image
    m2[100:118, 80:150] = True
    dets = emb.embed(view, [Mask2D(mask=m1, instance_key=1), Mask2D(mask=m2, instance_key=2),
                            Mask2D(mask=np.zeros((480, 640), bool), instance_key=3)])
    assert [d.instance_key for d in dets] == [1, 2]  # the empty mask is dropped
    for d in dets:
        assert d.descriptor.dtype == np.float32 and d.descriptor.shape == (512,)
        assert abs(float(np.linalg.norm(d.descriptor)) - 1.0) < 1e-4
        assert d.label in {"chair", "monitor", "keyboard"} and 0.0 <= d.confidence <= 1.0
        assert {a for a, _ in d.alternatives} | {d.label} == {"chair", "monitor", "keyboard"}


# ---------------------------------------------------------------- Depth Anything 3
@pytest.fixture(scope="module")
def da3_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A DA3-small with random weights saved in the save_pretrained layout, loaded back by the adapter."""
    _need("depth_anything_3", "da3")
    import torch

    from mapper.geometry.modelutil import import_or_explain

    torch.manual_seed(0)
    api = import_or_explain("depth_anything_3.api", "da3", "")
    d = tmp_path_factory.mktemp("da3small")
    api.DepthAnything3(model_name="da3-small").save_pretrained(str(d))
    return d


def test_da3_posed_round_trip_shapes_and_metric(da3_checkpoint: Path) -> None:
    views = _tum_views((0, 4, 8))
    rec = make_reconstructor("da3", checkpoint=str(da3_checkpoint))
    out = rec.reconstruct(views)
    n, h, w = out.depth_along_ray.shape
    assert n == 3 and max(h, w) == 504 and h % 14 == 0 and w % 14 == 0  # DA3's patch-multiple resolution
    assert out.ray_dirs.dtype == np.float32 and out.depth_along_ray.dtype == np.float32
    assert out.confidence.min() >= 0.0 and out.confidence.max() <= 1.0
    assert out.info["metric"] and out.info["posed_input"] and out.metric_scale == 1.0
    assert out.intrinsics[0].width == w and out.intrinsics[0].fx == pytest.approx(525.0 * w / 640, rel=1e-3)
    geo = compose(out, anchor_pose(out, views))
    for i, v in enumerate(views):  # the known poses come back unchanged
        np.testing.assert_allclose(geo.T_world_cam[i], v.T_world_cam, atol=1e-4)


def test_da3_two_posed_views_and_unposed(da3_checkpoint: Path) -> None:
    rec = make_reconstructor("da3", checkpoint=str(da3_checkpoint))
    views = _tum_views((0, 8))
    out = rec.reconstruct(views)  # < 3 posed views: unposed run, poses kept, depth scaled by the baseline
    geo = compose(out, anchor_pose(out, views))
    for i, v in enumerate(views):
        np.testing.assert_allclose(geo.T_world_cam[i], v.T_world_cam, atol=1e-4)
    bare = [View(image=v.image, source_id="x", seq=v.seq) for v in _tum_views((0, 4, 8))]
    out = rec.reconstruct(bare, targets=[1])
    assert not out.info["metric"] and "T_world_first" not in out.info
    np.testing.assert_allclose(out.T_first_cam[0], np.eye(4), atol=1e-6)
    assert out.confidence[0].max() == 0.0 and out.confidence[2].max() == 0.0  # non-targets


def test_da3_odd_image_size_is_resized(da3_checkpoint: Path) -> None:
    rec = make_reconstructor("da3", checkpoint=str(da3_checkpoint))
    out = rec.reconstruct(_tum_views((0, 4, 8), crop=(331, 517)))
    _, h, w = out.depth_along_ray.shape
    assert h % 14 == 0 and w % 14 == 0 and w == 504


def test_da3_missing_checkpoint_and_gpu_are_clear(tmp_path: Path) -> None:
    _need("depth_anything_3", "da3")
    with pytest.raises(ModelUnavailable, match="huggingface-cli download depth-anything/DA3-BASE"):
        make_reconstructor("da3", checkpoint="depth-anything/DA3-BASE")
    with pytest.raises(ModelUnavailable, match="huggingface-cli download"):
        make_reconstructor("da3", checkpoint=str(tmp_path))  # an empty directory
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ModelUnavailable, match="no CUDA GPU"):
            make_reconstructor("da3", device="cuda")


# ---------------------------------------------------------------- MapAnything
def _dinov2_hub_cached() -> bool:
    home = Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))
    return (home / "hub" / "facebookresearch_dinov2_main" / "hubconf.py").is_file()


@pytest.fixture(scope="module")
def mapanything_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small MapAnything (DINOv2-S encoder, 4 alternating-attention layers, the real heads) with random
    weights, saved in the save_pretrained layout the adapter loads."""
    _need("mapanything", "mapanything")
    if not _dinov2_hub_cached():
        pytest.skip("MapAnything's DINOv2 encoder comes from torch.hub: cache facebookresearch/dinov2 under TORCH_HOME")
    import torch

    from tests.support.mapanything_small import save_small_mapanything

    torch.manual_seed(0)
    d = tmp_path_factory.mktemp("mapanything_small")
    save_small_mapanything(str(d))
    return d


def test_mapanything_posed_round_trip_and_scale(mapanything_checkpoint: Path) -> None:
    views = _tum_views((0, 4, 8))
    rec = make_reconstructor("mapanything", checkpoint=str(mapanything_checkpoint))
    out = rec.reconstruct(views)
    n, h, w = out.depth_along_ray.shape
    assert n == 3 and h % 14 == 0 and w % 14 == 0 and out.ray_dirs.shape == (3, h, w, 3)
    np.testing.assert_allclose(np.linalg.norm(out.ray_dirs, axis=-1), 1.0, atol=1e-5)
    assert out.confidence.min() >= 0.0 and out.confidence.max() <= 1.0
    assert out.metric_scale > 0
    geo = compose(out, anchor_pose(out, views))
    for i, v in enumerate(views):
        np.testing.assert_allclose(geo.T_world_cam[i], v.T_world_cam, atol=1e-4)


def test_mapanything_odd_size_unposed_and_errors(
    mapanything_checkpoint: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec = make_reconstructor("mapanything", checkpoint=str(mapanything_checkpoint))
    out = rec.reconstruct(_tum_views((0, 4), crop=(331, 517)))
    assert out.depth_along_ray.shape[1] % 14 == 0 and out.depth_along_ray.shape[2] % 14 == 0
    # no priors at all: the model's own poses (view 0 at the origin) and intrinsics; nothing to anchor on
    bare = [View(image=v.image, source_id="x", seq=v.seq) for v in _tum_views((0, 4))]
    out = rec.reconstruct(bare)
    assert "T_world_first" not in out.info and len(out.info["intrinsics_ok"]) == 2
    np.testing.assert_allclose(out.T_first_cam[0], np.eye(4), atol=1e-5)
    for ok, c in zip(out.info["intrinsics_ok"], out.confidence, strict=True):
        assert ok or c.max() == 0.0  # random weights may predict no valid pinhole: that view is not used
    with pytest.raises(ModelUnavailable, match="huggingface-cli download"):
        make_reconstructor("mapanything", checkpoint=str(tmp_path))
    with pytest.raises(ModelUnavailable, match="no CUDA GPU"):
        import torch

        if torch.cuda.is_available():
            pytest.skip("a GPU is present")
        make_reconstructor("mapanything", checkpoint=str(mapanything_checkpoint), device="cuda")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))  # an empty hub cache: one message, no GitHub access
    with pytest.raises(ModelUnavailable, match="torch hub cache"):
        make_reconstructor("mapanything", checkpoint=str(mapanything_checkpoint))


def test_mapanything_quaternion_order_is_xyzw(mapanything_checkpoint: Path) -> None:
    """The real package's cam_quats are (x, y, z, w): our conversion reproduces its camera_poses rotation."""
    from mapper.geometry.mapanything_adapter import quat_xyzw_to_matrix

    rec = make_reconstructor("mapanything", checkpoint=str(mapanything_checkpoint))
    inputs = rec._preprocess(rec._inputs(_tum_views((0, 4))))  # type: ignore[attr-defined]
    preds = rec.model.infer(inputs, use_amp=False)  # type: ignore[attr-defined]
    for p in preds:
        q = p["cam_quats"].detach().double().numpy().reshape(4)
        R = p["camera_poses"].detach().double().numpy().reshape(4, 4)[:3, :3]
        np.testing.assert_allclose(quat_xyzw_to_matrix(q), R, atol=1e-4)
        wxyz = np.roll(q, 1)  # the other order must not fit (fails unless the rotation is trivial)
        assert np.abs(quat_xyzw_to_matrix(wxyz) - R).max() > 1e-2


def test_batch_timing_plumbing_da3_cpu() -> None:
    """`argus bench geometry --batch-views` on the real package (CPU, tiny model): numbers come back; a CUDA
    request on a machine without a GPU is reported as not measured."""
    _need("depth_anything_3", "da3")
    from bench.modeltiming import batch_timing

    rep = batch_timing("da3", {"process_res": 224}, [3], random_weights="da3-small", repeats=1)
    assert rep["measured"] and rep["batches"][0]["views"] == 3 and rep["batches"][0]["seconds_per_batch"] > 0
    import torch

    if not torch.cuda.is_available():
        rep = batch_timing("da3", {"device": "cuda"}, [8, 32], random_weights="da3-base")
        assert not rep["measured"] and "no GPU" in rep["reason"] and "batches" not in rep


def test_perception_timing_sam_clip_cpu() -> None:
    """`argus bench perception` with the real SAM + OpenCLIP (random weights, CPU): per-frame seconds come back."""
    _need("segment_anything", "sam")
    _need("open_clip", "clip")
    from bench.modeltiming import perception_timing

    rep = perception_timing("sam", "clip", {"random_init": True, "points_per_side": 4}, {"random_init": True},
                            frames=1)
    assert rep["measured"] and rep["segment_s"] > 0 and rep["embed_s"] >= 0
