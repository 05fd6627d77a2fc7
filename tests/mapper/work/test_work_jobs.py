"""Keyframe jobs and results on the wire (mapper/work/jobs.py): round trips and every rejection reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mapper.config import MapperCoreConfig
from mapper.geometry.contract import View
from mapper.geometry.singleview import depth_to_world
from mapper.perception.base import Detection, ViewGeometry
from mapper.work.compute import KeyframeProducts
from mapper.work.jobs import (
    ResultRejected,
    core_settings,
    decode_result,
    encode_products,
    make_job,
    products_problem,
    view_of,
)
from protocol.codec import decode, encode
from protocol.jpeg import encode_jpeg
from protocol.messages import Intrinsics, WorkJob, WorkResult

W, H = 64, 48
INTR = Intrinsics.from_fov(W, H, 90.0)


def pose(x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def views() -> list[View]:
    rng = np.random.default_rng(0)
    return [View(image=rng.integers(0, 255, (H, W, 3), dtype=np.uint8), source_id=s, intrinsics=INTR,
                 T_world_cam=pose(x), seq=q, stamp_ns=10 + q) for s, q, x in (("cam", 7, 0.0), ("rob", 3, 0.4))]


def job() -> WorkJob:
    vs = views()
    return make_job(vs, 0, encode_jpeg(vs[0].image), 1, True, MapperCoreConfig())


def products(dets: bool = True) -> KeyframeProducts:
    h, w = H // 2, W // 2
    K = INTR.scaled(w, h).K()
    depth = np.linspace(0.5, 4.0, h * w, dtype=np.float32).reshape(h, w)
    depth[0, 0] = 0.0
    conf = np.linspace(0.0, 1.0, h * w, dtype=np.float32).reshape(h, w)
    T = pose(0.25)
    mask = np.zeros((H, W), bool)
    mask[10:20, 5:30] = True
    d = [Detection(mask=mask, label="chair", confidence=0.8, descriptor=np.ones(8, np.float32) / np.sqrt(8),
                   alternatives=(("sofa", 0.1),), instance_key=4)]
    return KeyframeProducts(ViewGeometry(depth_to_world(depth, K, T), depth, conf), T, K, d if dets else None,
                            {"geometry": 1.5})


def roundtrip(p: KeyframeProducts | None, j: WorkJob | None = None) -> KeyframeProducts | None:
    j = j or job()
    msg = decode(encode(encode_products(p, j, "w1")), WorkResult)
    return decode_result(msg, j)


def test_job_round_trip_and_views() -> None:
    j = decode(encode(job()), WorkJob)
    assert j.job_id == "cam#7" and j.target_index == 0 and [f.source_id for f in j.window] == ["cam", "rob"]
    v = view_of(j.window[1], np.zeros((H, W, 3), np.uint8))
    assert v.key == ("rob", 3) and np.allclose(v.T_world_cam, pose(0.4)) and v.stamp_ns == 13
    with pytest.raises(ValueError, match="the job says"):
        view_of(j.window[0], np.zeros((H + 1, W, 3), np.uint8))
    settings, digest = core_settings(MapperCoreConfig())
    assert j.core_config == settings and j.config_digest == digest
    assert MapperCoreConfig.model_validate(settings) == MapperCoreConfig()
    assert core_settings(MapperCoreConfig(torch_threads=3))[1] != digest


def test_result_round_trip_is_close() -> None:
    p = products()
    q = roundtrip(p)
    assert q is not None and q.detections is not None and p.detections is not None
    assert np.abs(q.geometry.depth_m - p.geometry.depth_m).max() <= 0.0005 + 1e-6  # 1 mm units
    assert np.abs(q.geometry.confidence - p.geometry.confidence).max() <= 1.0 / 65535 + 1e-7
    assert np.abs(q.geometry.points_world - p.geometry.points_world).max() < 0.002
    assert q.geometry.depth_m[0, 0] == 0.0
    assert np.array_equal(q.T_world_cam, p.T_world_cam) and np.allclose(q.K, p.K)
    a, b = q.detections[0], p.detections[0]
    assert np.array_equal(a.mask, b.mask) and a.label == "chair" and a.alternatives == (("sofa", 0.1),)
    assert np.array_equal(a.descriptor, b.descriptor) and a.instance_key == 4
    assert roundtrip(products(dets=False)).detections is None  # type: ignore[union-attr]


def test_not_anchored_is_a_valid_answer() -> None:
    assert roundtrip(None) is None


def test_deep_depth_gets_coarser_units() -> None:
    p = products(dets=False)
    deep = p.geometry.depth_m * 40.0  # up to 160 m
    K, T = p.K, p.T_world_cam
    geo = ViewGeometry(depth_to_world(deep, K, T), deep, p.geometry.confidence)
    q = roundtrip(dataclasses.replace(p, geometry=geo))
    assert q is not None and np.abs(q.geometry.depth_m - deep).max() < 160.0 / 65535


def bad(p: KeyframeProducts, **geo: np.ndarray) -> KeyframeProducts:
    g = p.geometry
    return dataclasses.replace(p, geometry=ViewGeometry(geo.get("points", g.points_world), geo.get("depth", g.depth_m),
                                                        geo.get("conf", g.confidence)))


@pytest.mark.parametrize(("change", "reason"), [
    ("nan_depth", "result_not_finite"),
    ("conf_shape", "result_bad_shape"),
    ("too_big", "result_bad_shape"),
    ("negative", "result_bad_depth"),
    ("conf_range", "result_bad_depth"),
    ("shear", "result_bad_pose"),
    ("mask_shape", "result_bad_shape"),
    ("nan_descriptor", "result_bad_detection"),
    ("mixed_dims", "result_bad_detection"),
])
def test_products_problems(change: str, reason: str) -> None:
    p = products()
    g = p.geometry
    assert products_problem(p, (H, W)) is None
    d = g.depth_m.copy()
    det = p.detections[0]  # type: ignore[index]
    if change == "nan_depth":
        d[3, 3] = np.nan
        p = bad(p, depth=d)
    elif change == "conf_shape":
        p = bad(p, conf=g.confidence[:-1])
    elif change == "too_big":
        big = np.ones((4 * H + 1, 4 * W), np.float32)  # 16x the image's pixels is the most accepted
        p = bad(p, depth=big, conf=big, points=np.zeros((*big.shape, 3), np.float32))
    elif change == "negative":
        d[1, 1] = -1.0
        p = bad(p, depth=d)
    elif change == "conf_range":
        p = bad(p, conf=g.confidence * 2.0)
    elif change == "shear":
        T = p.T_world_cam.copy()
        T[0, 1] = 0.5
        p = dataclasses.replace(p, T_world_cam=T)
    elif change == "mask_shape":
        p = dataclasses.replace(p, detections=[dataclasses.replace(det, mask=det.mask[:-1])])
    elif change == "nan_descriptor":
        p = dataclasses.replace(p, detections=[dataclasses.replace(det, descriptor=np.full(8, np.nan, np.float32))])
    elif change == "mixed_dims":
        p = dataclasses.replace(p, detections=[det, dataclasses.replace(det, descriptor=np.ones(4, np.float32))])
    problem = products_problem(p, (H, W))
    assert problem is not None and problem[0] == reason


def test_garbage_on_the_wire_is_rejected_with_a_reason() -> None:
    j = job()
    good = encode_products(products(), j, "w1")
    cases = {
        "result_bad_image": good.model_copy(update={"depth_png": b"\x89PNG\r\n\x1a\nrubbish"}),
        "result_incomplete": good.model_copy(update={"confidence_png": None}),
        "result_bad_shape": good.model_copy(update={"intrinsics": INTR}),  # 64x48 intrinsics for a 32x24 depth
        "result_bad_pose": good.model_copy(update={"T_world_cam": [[1, 0.4, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                    [0, 0, 0, 1]]}),
        "result_bad_detection": good.model_copy(update={"detections": [
            good.detections[0].model_copy(update={"mask_png": b"not a png"})]}),  # type: ignore[index]
    }
    for reason, msg in cases.items():
        with pytest.raises(ResultRejected) as e:
            decode_result(decode(encode(msg), WorkResult), j)
        assert e.value.reason == reason, (reason, e.value)


def test_a_nearly_rigid_pose_is_cleaned_not_rejected() -> None:
    j = job()
    msg = encode_products(products(dets=False), j, "w1")
    T = np.asarray(msg.T_world_cam)
    T[:3, :3] *= 1.0 + 1e-7
    q = decode_result(msg.model_copy(update={"T_world_cam": T.tolist()}), j)
    assert q is not None and np.allclose(q.T_world_cam[:3, :3] @ q.T_world_cam[:3, :3].T, np.eye(3), atol=1e-12)


# --- frames worked reduced (issue 37) ---------------------------------------------------------------------
def test_a_worker_decodes_each_jpeg_at_the_reduction_its_job_names() -> None:
    """The mapper worked a 4000x4000 frame at 1/4: the job says so, and the worker's image is the mapper's."""
    from bench.bigframes import textured_jpeg
    from mapper.work.config import WorkerConfig
    from mapper.work.worker import JobFailed, WorkerNode
    from protocol.jpeg import decode_jpeg

    big = textured_jpeg(4000, 4000, seed=7)
    small = decode_jpeg(big, max_pixels=4000 * 4000, reduction=4)  # what the mapper's intake made of it
    intr = Intrinsics.from_fov(4000, 4000, 70.0).reduced(4)
    vs = [dataclasses.replace(views()[0], image=small, intrinsics=intr), views()[1]]
    j = decode(encode(make_job(vs, 0, big, 1, True, MapperCoreConfig(), reductions=[4, 1])), WorkJob)
    assert [(f.width, f.height, f.reduction) for f in j.window] == [(1000, 1000, 4), (W, H, 1)]
    assert j.window[0].intrinsics == intr
    worker = WorkerNode(WorkerConfig(id="w"))
    img = worker._decode(j.window[0], j.jpeg)
    assert np.array_equal(img, small)
    assert view_of(j.window[0], img).image.shape == (1000, 1000, 3)
    with pytest.raises(JobFailed, match="at 1/2 is not the job's 1000x1000"):
        worker._decode(j.window[0].model_copy(update={"reduction": 2}), j.jpeg)
    with pytest.raises(JobFailed, match="max_image_pixels"):
        WorkerNode(WorkerConfig(id="w", max_image_pixels=999_999))._decode(j.window[0], j.jpeg)
    assert make_job(vs[1:], 0, big, 1, True, MapperCoreConfig()).window[0].reduction == 1  # the default


def test_the_offloader_puts_the_remembered_reduction_in_each_jobs_frames() -> None:
    from mapper.work.config import OffloadConfig
    from mapper.work.offload import Offloader
    from protocol.keys import Keys
    from protocol.transport import Counters

    o = Offloader(OffloadConfig(), MapperCoreConfig(), Keys("t"), Counters(), perception=True)
    o.dispatcher.worker_up("a")
    vs = views()
    o.remember(vs[0].key, b"jpeg0", reduction=4)
    o.remember(vs[1].key, b"jpeg1")
    assert o.offload(vs[0], vs, 0)
    job = next(iter(o._pending.values())).job
    assert [f.reduction for f in job.window] == [4, 1]
    o._pending.clear()
    o.prune([])  # forgotten with their JPEGs
    assert o._reduction == {} and not o._jpegs
