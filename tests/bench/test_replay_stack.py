"""``argus bench replay`` end to end (slow): a generated three-frame folder through a real router, mapper (with its
local worker process) and edge camera on loopback.

The mapper's keyframe poses are observed on the wire: each keyframe job's result (``work/result``, the pose the
worker's reconstruction gave the keyframe, which the mapper fuses with). The folder's images are flat grey, so no
image feature can move a pose: every keyframe must come back exactly at the folder's pose.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import replay
from tests.bench.test_replay import with_depth


@pytest.mark.slow
@pytest.mark.integration
def test_a_recorded_folder_plays_through_the_stack_with_its_poses(tmp_path: Path) -> None:
    # 160x120: the worker returns depth at 320x240 at least, which the mapper refuses for smaller images
    folder = with_depth(tmp_path / "seq", n=3, scale=5)
    out = tmp_path / "out"
    setup = replay.ReplaySetup(sequence=folder, rate_hz=0.5, settle_s=2.0, timeout_s=120.0, out=out)
    res = replay.run(setup)
    f = res["figures"]
    assert f["settled"] and f["frames_sent"] == 3 == f["mapper_frames_in"]
    assert f["keyframe_results_rejected"] == 0 and f["keyframes_done_locally"] == 0
    poses = res["replay"]["keyframe_poses"]
    assert len(poses) >= 2, f"keyframes mapped by the worker: {poses}; mapper: {f['mapper_status']}"
    for kf in poses:
        assert kf["trans_cm"] < 1e-4 and kf["rot_deg"] < 1e-4, kf
    assert res["reference"]["points"] > 100
    assert json.loads((out / "replay.json").read_text())["sequence"] == "seq"
    for name in ("replay.md", "replay.png", "replay.rrd"):
        assert (out / name).stat().st_size > 0
