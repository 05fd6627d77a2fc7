"""2D perception backends: sim (ORACLE), classical, optional sam/clip wiring; Rerun file output."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from mapper.geometry.contract import View
from mapper.perception.base import ViewGeometry, label_descriptor
from mapper.perception.registry import make_embedder, make_segmenter
from mapper.perception.sam import BackendUnavailable
from mapper.perception.sim import OracleMissing
from tests.support.boxes import EYES, INTR, LABELS, oracle_core, view, world_points


def test_sim_segmenter_and_embedder_are_oracle() -> None:
    seg, emb = make_segmenter("sim"), make_embedder("sim")
    assert "ORACLE" in seg.description and "ORACLE" in emb.description
    v = view(EYES[0], 0)
    masks = seg.segment(v)
    assert {m.hint_label for m in masks} == set(LABELS.values())
    dets = emb.embed(v, masks)
    assert all(d.confidence == 1.0 for d in dets)
    assert np.allclose(dets[0].descriptor, label_descriptor(dets[0].label))
    bare = View(image=v.image, source_id="x", intrinsics=INTR)
    with pytest.raises(OracleMissing):
        seg.segment(bare)


def test_label_descriptor_similarity() -> None:
    a, b, c = label_descriptor("chair"), label_descriptor("office chair"), label_descriptor("refrigerator")
    assert float(a @ a) == pytest.approx(1.0)
    assert float(a @ b) > float(a @ c)


def test_classical_finds_objects_and_removes_floor() -> None:
    v = view(EYES[0], 0)
    assert v.oracle is not None
    depth = v.oracle.depth_m.copy()
    T = v.oracle.T_world_cam_true
    pts = world_points(T, depth)
    # Add a floor plane (z = 0) wherever the ray cast hit nothing and looks down.
    vv, uu = np.mgrid[0 : INTR.height, 0 : INTR.width].astype(np.float64)
    d_cam = np.stack([(uu - INTR.cx) / INTR.fx, (vv - INTR.cy) / INTR.fy, np.ones_like(uu)], -1)
    d_w = d_cam @ T[:3, :3].T
    t = -T[2, 3] / d_w[..., 2]
    floor = (depth == 0) & (t > 0)
    depth[floor] = t[floor]
    pts = world_points(T, depth)
    geo = ViewGeometry(points_world=pts, depth_m=depth, confidence=np.ones_like(depth))
    masks = make_segmenter("classical").segment(v, geo)
    assert masks, "no regions found"
    ids = v.oracle.instance_id
    # No mask is mostly floor, and the large objects are each covered by some mask.
    for m in masks:
        assert (ids[m.mask] > 0).mean() > 0.5
    covered = {int(np.bincount(ids[m.mask][ids[m.mask] > 0]).argmax()) for m in masks if (ids[m.mask] > 0).any()}
    assert {1, 3} <= covered
    dets = make_embedder("classical").embed(v, masks)
    assert len(dets) == len(masks) and all(d.label == "object" for d in dets)
    assert all(abs(float(np.linalg.norm(d.descriptor)) - 1.0) < 1e-5 for d in dets)


def test_unknown_backend_and_missing_optional_packages_are_clear() -> None:
    with pytest.raises(ValueError, match="unknown segmenter"):
        make_segmenter("nope")
    if importlib.util.find_spec("segment_anything") is None:
        with pytest.raises(BackendUnavailable, match="pip install"):
            make_segmenter("sam", checkpoint="/nonexistent.pth")
    if importlib.util.find_spec("open_clip") is None:
        with pytest.raises(BackendUnavailable, match="pip install"):
            make_embedder("clip", pretrained="/nonexistent.pt")


@pytest.mark.slow
def test_sam_wiring_random_init() -> None:
    pytest.importorskip("segment_anything")
    seg = make_segmenter("sam", random_init=True, points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0)
    masks = seg.segment(view(EYES[0], 0))
    assert all(m.mask.shape == (INTR.height, INTR.width) for m in masks)


@pytest.mark.slow
def test_clip_wiring_random_init(tmp_path: Path) -> None:
    pytest.importorskip("open_clip")
    vocab = tmp_path / "v.txt"
    vocab.write_text("chair\ntable\n# comment\nbasket\n")
    emb = make_embedder("clip", random_init=True, vocabulary=vocab)
    v = view(EYES[0], 0)
    dets = emb.embed(v, make_segmenter("sim").segment(v))
    assert dets and all(d.label in {"chair", "table", "basket"} for d in dets)
    assert all(0.0 <= d.confidence <= 1.0 for d in dets)


def test_rerun_file_output(tmp_path: Path) -> None:
    from mapper.config import RerunConfig
    from mapper.rerun_log import RerunLogger

    core = oracle_core()
    out = tmp_path / "map.rrd"
    logger = RerunLogger(RerunConfig(file=out, point_parts=2))
    parts = []
    for i, eye in enumerate(EYES[:2]):
        core.ingest(view(eye, i))
        logger.log(core)
        parts.append(logger._points.parts)
        assert len(logger._points.logged) == len(core.voxels)  # every voxel is in the recording once
    logger.log(core)  # nothing new: no part logged
    parts.append(logger._points.parts)
    core.ingest(view(EYES[2], 2))
    logger.log(core)  # two parts already: the whole map afresh as part 0
    parts.append(logger._points.parts)
    logger.close()
    assert parts == [1, 2, 2, 1]
    assert len(logger._points.logged) == len(core.voxels)
    assert out.stat().st_size > 1000


@pytest.mark.integration
def test_rerun_server_is_loopback_only_and_stopped_with_its_port(tmp_path: Path) -> None:
    import socket

    from mapper.config import RerunConfig
    from mapper.rerun_log import RerunLogger, server_command
    from tests.support.procs import free_port

    cfg = RerunConfig(serve=True, port=free_port())
    cmd = server_command(cfg)
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1" and "--serve-grpc" in cmd
    web = server_command(cfg.model_copy(update={"web_port": 9999}))
    assert "--serve-web" in web and web[web.index("--web-viewer-port") + 1] == "9999"
    logger = RerunLogger(cfg)
    server = logger._server
    assert server is not None and server.poll() is None
    logger.close()
    assert server.poll() is not None  # the viewer binary itself, stopped
    with socket.socket() as s:
        s.bind(("127.0.0.1", cfg.port))  # and its port is free again


def test_byte_histogram_counts_as_histogramdd() -> None:
    """The embedder's table look-up histogram of HSV bytes gives np.histogramdd's counts, bin edges and bytes past
    the hue range (OpenCV's hue stops at 179) included."""
    from mapper.perception.classical import byte_histogram

    rng = np.random.default_rng(8)
    px = rng.integers(0, 256, (5000, 3)).astype(np.uint8)
    px[:256] = np.arange(256, dtype=np.uint8)[:, None]  # every byte on every axis
    for bins in ((12, 3, 3), (7, 5, 2), (64, 16, 16)):
        ranges = ((0, 180), (0, 256), (0, 256))
        want, _ = np.histogramdd(px.astype(np.float32), bins=bins, range=ranges)
        got = byte_histogram(px, bins, ranges)
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)
