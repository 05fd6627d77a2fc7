"""Recorded sequence folders (bench/sequences.py): reading them, clear errors, and the wire path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from bench import sequences as seqs
from bench.video import stretches
from protocol.poses import PoseAccuracy
from tests.support.recorded import SIZE, K, pose_of, write_sequence

META = {"depth_divisor": 1000, "valid_depth_m": [0.2, 5.0], "licence": "test"}


def _with_depth(folder: Path, n: int = 3, meta: dict | None = None) -> Path:
    write_sequence(folder, n=n, meta=META if meta is None else meta)
    for i in range(n):
        depth = np.full((SIZE[1], SIZE[0]), 1500 + 100 * i, np.uint16)
        depth[0, 0] = 0  # no data
        cv2.imwrite(str(folder / "frames" / f"frame-{i:06d}.depth.png"), depth)
    return folder


def test_a_sequence_folder_reads_with_its_meta(tmp_path: Path) -> None:
    seq = seqs.load(_with_depth(tmp_path / "s"))
    assert seq.name == "s" and len(seq.frames) == 3 and seq.meta.declared() is None
    f = seq.frames[1]
    assert np.allclose(f.K, K) and np.allclose(f.T_world_cam, pose_of(1))
    assert f.depth_m[1, 1] == pytest.approx(1.6) and not f.valid[0, 0] and f.valid[1, 1]
    assert [f.index for f in seqs.load(tmp_path / "s", start=1, stop=3).frames] == [1, 2]


def test_declared_accuracy_is_both_sigmas_or_neither(tmp_path: Path) -> None:
    seq = seqs.load(_with_depth(tmp_path / "s", meta=dict(META, pose_sigma_trans_m=0.01, pose_sigma_rot_deg=0.1)))
    assert seq.meta.declared() == PoseAccuracy(0.01, 0.1)
    _with_depth(tmp_path / "t", meta=dict(META, pose_sigma_rot_deg=0.1))
    with pytest.raises(seqs.SequenceError, match="both or neither"):
        seqs.load(tmp_path / "t")


def test_world_from_recording_moves_the_poses_the_camera_would_send(tmp_path: Path) -> None:
    W = [[0, -1, 0, 1.0], [1, 0, 0, 0], [0, 0, 1, 0.5], [0, 0, 0, 1]]
    seq = seqs.load(_with_depth(tmp_path / "s", meta=dict(META, world_from_recording=W)))
    assert np.allclose(seq.frames[2].T_world_cam, np.array(W) @ pose_of(2), atol=1e-9)
    _with_depth(tmp_path / "t", meta=dict(META, world_from_recording=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]))
    with pytest.raises(seqs.SequenceError, match="world_from_recording"):
        seqs.load(tmp_path / "t")


@pytest.mark.parametrize("breakage, named", [
    ("no_meta", "meta.json: missing"),
    ("bad_meta", "meta.json: depth_divisor"),
    ("no_pose", "frame-000001.pose.txt: missing"),
    ("bad_pose", "frame-000001.pose.txt: not a 4x4 pose"),
    ("bad_depth", "frame-000001.depth.png: missing or not an image"),
    ("rgb_depth", "frame-000001.depth.png: expected 32x24 uint16 depth"),
    ("no_intrinsics", "camera-intrinsics.txt: missing"),
])
def test_a_broken_folder_is_one_line_naming_the_file(tmp_path: Path, breakage: str, named: str) -> None:
    folder = _with_depth(tmp_path / "s")
    frames = folder / "frames"
    if breakage == "no_meta":
        (folder / "meta.json").unlink()
    elif breakage == "bad_meta":
        (folder / "meta.json").write_text('{"depth_divisor": -1, "valid_depth_m": [0, 1]}')
    elif breakage == "no_pose":
        (frames / "frame-000001.pose.txt").unlink()
    elif breakage == "bad_pose":
        (frames / "frame-000001.pose.txt").write_text("1 2 3\n")
    elif breakage == "bad_depth":
        (frames / "frame-000001.depth.png").write_bytes(b"not a png")
    elif breakage == "rgb_depth":
        cv2.imwrite(str(frames / "frame-000001.depth.png"), np.zeros((SIZE[1], SIZE[0], 3), np.uint8))
    else:
        (folder / "camera-intrinsics.txt").unlink()
    with pytest.raises(seqs.SequenceError) as e:
        seqs.load(folder)
    msg = str(e.value)
    assert named in msg and "\n" not in msg


def test_discover_takes_folders_with_a_meta_file_only(tmp_path: Path) -> None:
    _with_depth(tmp_path / "b")
    write_sequence(tmp_path / "a", n=1)  # no meta.json, no sidecar
    assert seqs.discover(tmp_path) == [tmp_path / "b"]


def test_frames_reach_the_reconstructor_the_way_the_wire_brings_them(tmp_path: Path) -> None:
    seq = seqs.load(_with_depth(tmp_path / "s"))
    feed = seqs.WireFeed("replay")
    declared = feed.view(seq.frames[0], PoseAccuracy(0.002, 0.05))
    bare = feed.view(seq.frames[1], None)
    assert declared is not None and bare is not None
    assert declared.prior_rel_rot_deg == pytest.approx(0.05) and bare.prior_rel_rot_deg is None
    assert (declared.seq, bare.seq) == (0, 1) and declared.source_id == "replay"
    assert np.allclose(declared.T_world_cam, pose_of(0)) and not declared.pose_trusted
    assert declared.oracle is None and declared.intrinsics is not None and declared.intrinsics.fx == K[0, 0]
    # The image went through JPEG: close to the recorded one, not bit-identical in general.
    assert np.abs(declared.image.astype(int) - seq.frames[0].rgb.astype(int)).max() <= 3


def test_stretches_cover_the_frames_without_overlap() -> None:
    assert stretches(10, 4) == [(0, 4), (4, 8)]
    assert stretches(3, 4) == [(0, 3)]
    assert stretches(5, 0) == []
