"""mvs on real label-fusion frames (recorded poses as noisy priors); skips when ../shared/data is absent."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapper.geometry.contract import CONFIDENT, anchor_pose, compose
from mapper.geometry.registry import make_reconstructor
from tests.support.procs import REPO

DATA = REPO / ".." / "shared" / "data" / "labelfusion"


@pytest.mark.skipif(not (DATA / "frames").is_dir(), reason="real frames not present (../shared/data/labelfusion)")
def test_real_frames_depth_against_recorded_depth() -> None:
    from bench.video import load_sequence

    frames, _ = load_sequence("labelfusion", DATA.parent)  # through the wire, no accuracy declared
    data = [(f.view, f.depth_m) for f in frames[6:11]]
    views = [v for v, _ in data]
    r = make_reconstructor("mvs").reconstruct(views, targets=[2])
    g = compose(r, anchor_pose(r, views))
    h, w = g.depth_m.shape[1:]
    gt = cv2.resize(data[2][1], (w, h), interpolation=cv2.INTER_NEAREST)
    valid = (gt > 0.3) & (gt < 0.82)  # the recorded encoding wraps above 0.82 m
    sel = valid & (g.confidence[2] >= CONFIDENT)
    assert sel.sum() > 0.3 * valid.sum(), f"confident fraction {sel.sum() / valid.sum():.2f}"
    assert np.median(np.abs(g.depth_m[2][sel] - gt[sel]) / gt[sel]) < 0.10
    # The bundle adjustment moved the priors, but not far: they are roughly right.
    for i, v in enumerate(views):
        assert np.linalg.norm(g.T_world_cam[i][:3, 3] - v.T_world_cam[:3, 3]) < 0.05
