"""Unit tests of the ``recorded`` source: a sequence folder of images with a pose per frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edge_camera.pose_accuracy import pose_covariance
from edge_camera.sources import SOURCES, create_source, parse_source_config
from edge_camera.sources.base import FrameSource, SourceConfigError, SourceError
from tests.support.recorded import SIZE, pose_of, write_sequence


def make(folder: Path, **kw) -> FrameSource:
    src = create_source(parse_source_config({"type": "recorded", "path": str(folder), **kw}))
    assert isinstance(src, FrameSource)
    src.open()
    return src


def grey(src: FrameSource) -> int:
    return int(round(src.read().rgb.mean()))


class TestRecordedSource:
    def test_registered(self):
        assert SOURCES["recorded"] == "edge_camera.sources.recorded"

    def test_frames_carry_the_folders_poses_and_intrinsics(self, tmp_path):
        src = make(write_sequence(tmp_path / "seq"))
        for i in range(3):
            g = src.read()
            assert g.rgb.shape == (SIZE[1], SIZE[0], 3) and int(round(g.rgb.mean())) == 10 * (i + 1)
            assert np.allclose(g.T_world_cam, pose_of(i), atol=1e-8)
            assert (g.intrinsics.width, g.intrinsics.height) == SIZE
            assert (g.intrinsics.fx, g.intrinsics.fy, g.intrinsics.cx, g.intrinsics.cy) == (50.0, 52.0, 15.5, 11.5)
            assert g.pose_trusted is False and g.pose_covariance is None and g.stamp_ns > 0
        assert src.rate_hz == 5.0 and src.skipped == 0

    def test_jpg_images_are_taken(self, tmp_path):
        src = make(write_sequence(tmp_path / "seq", n=2, ext="jpg"))
        assert [grey(src) for _ in range(2)] == pytest.approx([10, 20], abs=2)

    def test_declared_accuracy_config_over_meta(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", meta={"pose_sigma_trans_m": 0.2, "pose_sigma_rot_deg": 4.0,
                                                       "licence": "x", "depth_divisor": 5000})
        assert np.array_equal(make(folder).read().pose_covariance, pose_covariance(0.2, 4.0))
        src = make(folder, pose_sigma_trans_m=0.01, pose_sigma_rot_deg=0.5)
        assert np.array_equal(src.read().pose_covariance, pose_covariance(0.01, 0.5))

    def test_rate_config_over_meta_over_default(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", meta={"rate_hz": 30})
        assert make(folder).rate_hz == 30
        assert make(folder, rate_hz=2.5).rate_hz == 2.5

    def test_start_stop_and_loop(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", n=5)
        src = make(folder, start=1, stop=4, loop=True)
        assert [grey(src) for _ in range(5)] == [20, 30, 40, 20, 30]
        src = make(folder, start=3)
        assert [grey(src) for _ in range(2)] == [40, 50]
        with pytest.raises(SourceError, match="end of recording"):
            src.read()

    def test_end_without_loop_is_sticky_and_never_replays(self, tmp_path):
        src = make(write_sequence(tmp_path / "seq", n=2))
        src.read()
        src.close()
        src.open()  # a reopen (after a network fault) resumes at the next frame
        assert grey(src) == 20
        with pytest.raises(SourceError, match="end of recording .*not replayed"):
            src.read()
        src.close()
        src.open()  # what the node does after the end-of-recording fault
        with pytest.raises(SourceError, match="end of recording"):
            src.read()

    def test_bad_pose_or_unreadable_image_is_skipped_and_counted(self, tmp_path, caplog):
        folder = write_sequence(tmp_path / "seq", n=4)
        (folder / "frames" / "frame-000000.pose.txt").unlink()
        (folder / "frames" / "frame-000001.pose.txt").write_text("1 0 0\n0 1 0\n")
        (folder / "frames" / "frame-000002.color.png").write_bytes(b"not an image")
        src = make(folder, loop=True)
        assert [grey(src) for _ in range(3)] == [40, 40, 40]
        assert src.skipped == 3  # each bad frame counted once, not once per loop
        text = caplog.text
        for name in ("frame-000000.pose.txt", "frame-000001.pose.txt", "frame-000002.color.png"):
            assert name in text

    def test_pose_off_a_rotation_is_skipped_naming_the_file(self, tmp_path, caplog):
        folder = write_sequence(tmp_path / "seq", n=2)
        np.savetxt(folder / "frames" / "frame-000000.pose.txt", np.diag([2.0, 1.0, 1.0, 1.0]))
        src = make(folder)
        assert grey(src) == 20 and src.skipped == 1
        assert "frame-000000.pose.txt" in caplog.text and "orthonormal" in caplog.text

    def test_near_rotation_is_projected(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", n=1)
        np.savetxt(folder / "frames" / "frame-000000.pose.txt", pose_of(0), fmt="%.4f")
        T = make(folder).read().T_world_cam
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        assert np.allclose(T, pose_of(0), atol=1e-3)

    def test_world_from_recording_moves_every_pose_config_over_meta(self, tmp_path):
        # A y-up recording (HoloLens, ARKit) with its floor 1.2 m below its origin, into z up / floor at z = 0.
        W = [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 1.2], [0, 0, 0, 1]]
        folder = write_sequence(tmp_path / "seq", n=2, meta={"world_from_recording": W})
        src = make(folder)
        for i in range(2):
            assert np.allclose(src.read().T_world_cam, np.array(W) @ pose_of(i), atol=1e-9)
        shift = [[1, 0, 0, 5.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        T = make(folder, world_from_recording=shift).read().T_world_cam
        assert np.allclose(T, np.array(shift) @ pose_of(0), atol=1e-9)

    def test_k_in_a_file_of_another_name(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", n=1, meta={"intrinsics_file": "camera-intrinsics.color.txt"})
        (folder / "camera-intrinsics.txt").rename(folder / "camera-intrinsics.color.txt")
        assert make(folder).read().intrinsics.fx == 50.0
        (folder / "meta.json").unlink()
        assert make(folder, intrinsics_file="camera-intrinsics.color.txt").read().intrinsics.fy == 52.0
        with pytest.raises(SourceConfigError, match="camera-intrinsics.txt"):
            make(folder)

    def test_a_world_frame_that_does_not_look_z_up_is_warned_about(self, tmp_path, caplog):
        y_up = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]  # the inverse: z-up poses made y-up
        make(write_sequence(tmp_path / "a", n=2, meta={"world_from_recording": y_up}))
        assert "does not look z-up" not in caplog.text  # stated: the user chose it
        make(write_sequence(tmp_path / "b", n=2))
        assert "does not look z-up" not in caplog.text
        folder = write_sequence(tmp_path / "c", n=2)
        for i in range(2):
            np.savetxt(folder / "frames" / f"frame-{i:06d}.pose.txt", np.array(y_up) @ pose_of(i))
        make(folder)
        assert "does not look z-up" in caplog.text and "world_from_recording" in caplog.text

    def test_all_images_unreadable_names_the_folder(self, tmp_path):
        folder = write_sequence(tmp_path / "seq", n=2)
        for p in (folder / "frames").glob("*.color.png"):
            p.write_bytes(b"junk")
        src = make(folder)
        with pytest.raises(SourceConfigError, match=f"no frame of {folder} is readable"):
            src.read()


def _broken(folder: Path, case: str) -> str:
    """Break a fresh sequence folder one way; returns the file name the error must name."""
    write_sequence(folder, n=2)
    frames, intr, meta = folder / "frames", folder / "camera-intrinsics.txt", folder / "meta.json"
    if case == "no frames dir":
        for p in frames.iterdir():
            p.unlink()
        frames.rmdir()
        return str(frames)
    if case == "no frames":
        for p in frames.glob("*.color.png"):
            p.unlink()
        return str(frames)
    if case == "no intrinsics":
        intr.unlink()
        return str(intr)
    if case == "intrinsics not a matrix":
        intr.write_text("500 0 320\n0 five 240\n0 0 1\n")
        return str(intr)
    if case == "intrinsics too short":
        intr.write_text("500 0 320\n0 500 240\n")
        return str(intr)
    if case == "intrinsics zero focal":
        intr.write_text("0 0 320\n0 500 240\n0 0 1\n")
        return str(intr)
    if case == "meta not json":
        meta.write_text("{rate_hz: 3")
        return str(meta)
    if case == "meta not an object":
        meta.write_text("[1, 2]")
        return str(meta)
    if case == "meta bad rate":
        meta.write_text('{"rate_hz": "fast"}')
        return str(meta)
    if case == "meta one sigma":
        meta.write_text('{"pose_sigma_trans_m": 0.1}')
        return str(meta)
    if case == "meta world not rigid":
        meta.write_text('{"world_from_recording": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}')
        return str(meta)
    if case == "no usable pose":
        for p in frames.glob("*.pose.txt"):
            p.write_text("nan")
        return str(folder)
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["no frames dir", "no frames", "no intrinsics", "intrinsics not a matrix",
                                  "intrinsics too short", "intrinsics zero focal", "meta not json",
                                  "meta not an object", "meta bad rate", "meta one sigma", "meta world not rigid",
                                  "no usable pose"])
def test_broken_folder_is_one_clear_configuration_error_naming_the_file(tmp_path, case):
    named = _broken(tmp_path / "seq", case)
    with pytest.raises(SourceConfigError) as err:
        create_source(parse_source_config({"type": "recorded", "path": str(tmp_path / "seq")}))
    msg = str(err.value)
    assert named in msg and "\n" not in msg


def test_start_past_the_end_is_a_configuration_error(tmp_path):
    write_sequence(tmp_path / "seq", n=2)
    with pytest.raises(SourceConfigError, match="start = 2 is past the last of the 2 frames"):
        create_source(parse_source_config({"type": "recorded", "path": str(tmp_path / "seq"), "start": 2}))


@pytest.mark.parametrize(
    ("fields", "match"),
    [({"pose_sigma_trans_m": 0.1}, "both or neither"), ({"pose_sigma_rot_deg": 1.0}, "both or neither"),
     ({"start": 3, "stop": 3}, "greater than start"), ({"pose_sigma_trans_m": 0, "pose_sigma_rot_deg": 1}, "greater"),
     ({"rate_hz": 0}, "greater"), ({"colour": "red"}, "colour")],
)
def test_bad_config_fields_are_refused(tmp_path, fields, match):
    with pytest.raises(ValueError, match=match):
        parse_source_config({"type": "recorded", "path": str(tmp_path), **fields})
