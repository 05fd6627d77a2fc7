"""A worker's warm-up job: a real (synthetic) keyframe through compute_keyframe, and never a crash."""

from __future__ import annotations

import math

import numpy as np

from mapper.config import MapperCoreConfig
from mapper.geometry.registry import make_reconstructor
from mapper.perception.registry import make_embedder, make_segmenter
from mapper.work.compute import compute_keyframe, warm_up, warm_up_views


def _parts() -> tuple[object, object, object]:
    return make_reconstructor("mvs"), make_segmenter("classical", {}), make_embedder("classical", {})


def test_warm_up_views_are_a_consistent_scene() -> None:
    """The plane 2 m away comes out at 2 m: the warm-up takes the paths of a real keyframe, not an error path."""
    rec, seg, emb = _parts()
    out = compute_keyframe(rec, seg, emb, MapperCoreConfig(), warm_up_views(), 0, perception=True)  # type: ignore[arg-type]
    assert out is not None
    conf = out.geometry.confidence > 0.5
    assert conf.mean() > 0.5
    assert abs(float(np.median(out.geometry.depth_m[conf])) - 2.0) < 0.1
    assert out.detections is not None


def test_warm_up_returns_its_seconds_and_never_raises() -> None:
    rec, seg, emb = _parts()
    assert warm_up(rec, seg, emb, MapperCoreConfig(), perception=False) > 0  # type: ignore[arg-type]

    class Broken:
        def reconstruct(self, *a: object, **k: object) -> None:
            raise RuntimeError("no model")

    assert math.isnan(warm_up(Broken(), seg, emb, MapperCoreConfig()))  # type: ignore[arg-type]


def test_a_worker_warms_up_the_backends_a_default_mapper_sends() -> None:
    """The warm-up builds the default settings' backends under their digest: the first job of a mapper with the
    default settings finds them built (the same objects), so its keyframe pays no first-call costs."""
    from mapper.work.config import WorkerConfig
    from mapper.work.jobs import core_settings
    from mapper.work.worker import WorkerNode

    node = WorkerNode(WorkerConfig(id="w"))
    assert node.backends.warm_up() > 0
    parts = node.backends.parts
    settings, digest = core_settings(MapperCoreConfig())
    assert node.backends.of(digest, settings)[1] is parts
