"""Unit tests of the edge camera's pieces: source backends, calibration files, config, sizing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from edge_camera.calibration import CalibrationError, load_calibration
from edge_camera.config import EdgeCameraConfig, PublishConfig
from edge_camera.pose_accuracy import pose_covariance
from edge_camera.publish import FramePublisher, output_size
from edge_camera.sources import SOURCES, create_source, parse_source_config
from edge_camera.sources.base import FrameSource, SourceConfigError, SourceError
from protocol.tomlconfig import ConfigError, load_config
from tests.support.procs import REPO


def _png(path: Path, value: int, size: tuple[int, int] = (32, 24)) -> None:
    img = np.full((size[1], size[0], 3), value, np.uint8)
    cv2.imwrite(str(path), img)


class TestFolderSource:
    def make(self, folder: Path, **kw) -> FrameSource:
        src = create_source(parse_source_config({"type": "folder", "path": str(folder), **kw}))
        assert isinstance(src, FrameSource)
        return src

    def test_sorted_order_and_loop(self, tmp_path):
        for name, v in (("b.png", 20), ("a.png", 10), ("c.jpg", 30), ("notes.txt", 0)):
            (_png(tmp_path / name, v) if name.endswith(("png", "jpg")) else (tmp_path / name).write_text("x"))
        src = self.make(tmp_path)
        src.open()
        values = [int(round(src.read().rgb.mean())) for _ in range(4)]
        assert values[:3] == pytest.approx([10, 20, 30], abs=2)
        assert values[3] == pytest.approx(10, abs=2)  # looped
        assert src.rate_hz == 2.0

    def test_emptied_folder_and_vanished_file_are_faults(self, tmp_path):
        _png(tmp_path / "a.png", 10)
        _png(tmp_path / "b.png", 20)
        src = self.make(tmp_path)
        src.open()
        src.read()
        (tmp_path / "b.png").unlink()
        with pytest.raises(SourceError, match="vanished"):
            src.read()
        (tmp_path / "a.png").unlink()
        with pytest.raises(SourceError, match="no images"):
            src.open()

    def test_missing_folder_is_transient_not_config(self, tmp_path):
        src = self.make(tmp_path / "later")
        with pytest.raises(SourceError, match="does not exist"):
            src.open()
        (tmp_path / "later").mkdir()
        _png(tmp_path / "later" / "x.png", 50)
        src.open()
        assert src.read().rgb.shape == (24, 32, 3)

    def test_corrupt_image_is_skipped(self, tmp_path):
        _png(tmp_path / "a.png", 10)
        (tmp_path / "b.png").write_bytes(b"not an image")
        _png(tmp_path / "c.png", 30)
        src = self.make(tmp_path)
        src.open()
        assert [int(round(src.read().rgb.mean())) for _ in range(2)] == pytest.approx([10, 30], abs=2)
        assert src.skipped == 1

    def test_no_loop_waits_for_new_images_and_resumes_after_reopen(self, tmp_path):
        _png(tmp_path / "a.png", 10)
        src = self.make(tmp_path, loop=False)
        src.open()
        src.read()
        with pytest.raises(SourceError, match="no new images"):
            src.read()
        _png(tmp_path / "b.png", 90)
        src.open()  # what the node does after a fault: b, not a again
        assert src.read().rgb.mean() == pytest.approx(90, abs=2)


def _write_video(path: Path, n: int, size: tuple[int, int] = (64, 48)) -> None:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, size)
    assert vw.isOpened()
    for i in range(n):
        vw.write(np.full((size[1], size[0], 3), (20 * i + 10) % 256, np.uint8))
    vw.release()


class TestVideoSource:
    def test_plays_at_file_rate_and_loops(self, tmp_path):
        _write_video(tmp_path / "v.avi", 3)
        src = create_source(parse_source_config({"type": "video", "path": str(tmp_path / "v.avi")}))
        src.open()
        assert src.rate_hz == pytest.approx(10.0)
        means = [src.read().rgb.mean() for _ in range(4)]
        assert means[:3] == pytest.approx([10, 30, 50], abs=4)
        assert means[3] == pytest.approx(10, abs=4)

    def test_end_without_loop_is_a_fault_and_never_replays(self, tmp_path):
        _write_video(tmp_path / "v.avi", 2)
        src = create_source(parse_source_config({"type": "video", "path": str(tmp_path / "v.avi"), "loop": False}))
        src.open()
        src.read(), src.read()
        with pytest.raises(SourceError, match="end of video"):
            src.read()
        src.close()
        src.open()
        with pytest.raises(SourceError, match="end of video"):
            src.read()

    def test_missing_or_removed_file(self, tmp_path):
        src = create_source(parse_source_config({"type": "video", "path": str(tmp_path / "none.mp4")}))
        with pytest.raises(SourceError, match="does not exist"):
            src.open()


def test_opencv_device_that_does_not_exist_is_a_transient_fault():
    src = create_source(parse_source_config({"type": "opencv", "device": 63, "read_timeout_s": 0.5}))
    with pytest.raises(SourceError):
        src.open()
    src.close()


def test_stream_url_validation_and_redaction():
    with pytest.raises(ValueError, match="scheme"):
        parse_source_config({"type": "stream", "url": "no-scheme"})
    src = create_source(parse_source_config({"type": "stream", "url": "rtsp://u:secret@10.0.0.1/s"}))
    assert "secret" not in src._redacted()


def test_pattern_frames_change_and_have_the_configured_size():
    src = create_source(parse_source_config({"type": "pattern", "width": 80, "height": 60}))
    src.open()
    a, b = src.read().rgb, src.read().rgb
    assert a.shape == (60, 80, 3) and a.dtype == np.uint8 and not np.array_equal(a, b)


def test_unknown_source_type_and_extra_fields_are_refused():
    with pytest.raises(SourceConfigError, match="unknown source type"):
        parse_source_config({"type": "nope"})
    with pytest.raises(ValueError):
        parse_source_config({"type": "folder", "path": "/x", "colour": "red"})
    assert set(SOURCES) >= {"opencv", "stream", "video", "folder", "recorded", "pattern", "sim"}


class TestCalibration:
    def test_json_and_yaml(self, tmp_path):
        T = np.eye(4)
        T[:3, 3] = [1, 2, 3]
        (tmp_path / "c.json").write_text(json.dumps({
            "camera_matrix": [[500, 0, 319.5], [0, 510, 239.5], [0, 0, 1]], "image_width": 640,
            "image_height": 480, "T_world_cam": T.tolist()}))
        c = load_calibration(tmp_path / "c.json")
        assert (c.intrinsics.fx, c.intrinsics.fy, c.intrinsics.width) == (500, 510, 640)
        assert np.allclose(c.T_world_cam, T)
        fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 640)
        fs.write("image_height", 480)
        fs.write("camera_matrix", np.array([[500.0, 0, 319.5], [0, 510, 239.5], [0, 0, 1]]))
        fs.release()
        y = load_calibration(tmp_path / "c.yaml")
        assert y.intrinsics == c.intrinsics and y.T_world_cam is None

    def test_shipped_examples_load(self):
        for name in ("calibration.json", "calibration.yaml"):
            c = load_calibration(REPO / "edge_camera" / "examples" / name)
            assert c.intrinsics is not None and c.T_world_cam is not None
        assert np.array_equal(load_calibration(REPO / "edge_camera" / "examples" / "calibration.json").pose_covariance,
                              pose_covariance(0.02, 1.0))

    def test_pose_accuracy_json_and_yaml(self, tmp_path):
        T = np.eye(4)
        (tmp_path / "c.json").write_text(json.dumps({"T_world_cam": T.tolist(), "pose_sigma_trans_m": 0.05,
                                                     "pose_sigma_rot_deg": 2}))
        assert np.array_equal(load_calibration(tmp_path / "c.json").pose_covariance, pose_covariance(0.05, 2.0))
        fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_WRITE)
        fs.write("T_world_cam", T)
        fs.write("pose_sigma_trans_m", 0.05)
        fs.write("pose_sigma_rot_deg", 2.0)
        fs.release()
        assert np.array_equal(load_calibration(tmp_path / "c.yaml").pose_covariance, pose_covariance(0.05, 2.0))
        (tmp_path / "n.json").write_text(json.dumps({"T_world_cam": T.tolist()}))
        assert load_calibration(tmp_path / "n.json").pose_covariance is None

    @pytest.mark.parametrize(
        ("content", "suffix", "match"),
        [
            ("{bad", ".json", "not valid JSON"),
            ('{"T_world_cam": [[1, 0], [0, 1]]}', ".json", "T_world_cam"),
            ('{"T_world_cam": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', ".json", "orthonormal"),
            ("{}", ".json", "neither"),
            ('{"intrinsics": {"width": 0}}', ".json", "calibration"),
            ('{"colour": 1}', ".json", "unknown fields"),
            ("garbage: [", ".yaml", "calibration"),
            ('{"T_world_cam": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "pose_sigma_trans_m": 0.1}', ".json",
             "both or neither"),
            ('{"T_world_cam": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "pose_sigma_trans_m": 0.1, '
             '"pose_sigma_rot_deg": -1}', ".json", "sigma_rot_deg must be finite and > 0"),
            ('{"T_world_cam": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "pose_sigma_trans_m": "1cm", '
             '"pose_sigma_rot_deg": 1}', ".json", "sigma_trans_m must be finite and > 0"),
            ('{"intrinsics": {"width": 640, "height": 480, "fx": 1, "fy": 1, "cx": 1, "cy": 1}, '
             '"pose_sigma_trans_m": 0.1, "pose_sigma_rot_deg": 1}', ".json", "no T_world_cam"),
            ("%YAML:1.0\n---\npose_sigma_rot_deg: 1.0\nT_world_cam: !!opencv-matrix\n   rows: 4\n   cols: 4\n"
             "   dt: d\n   data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n", ".yaml", "both or neither"),
        ],
    )
    def test_bad_files(self, tmp_path, content, suffix, match):
        p = tmp_path / f"c{suffix}"
        p.write_text(content)
        with pytest.raises(CalibrationError, match=match):
            load_calibration(p)

    def test_missing_file(self, tmp_path):
        with pytest.raises(CalibrationError, match="does not exist"):
            load_calibration(tmp_path / "nope.yaml")


def test_header_scales_calibration_to_the_published_size(tmp_path):
    from edge_camera.sources.base import Grab

    calib_path = tmp_path / "c.json"
    calib_path.write_text(json.dumps({"intrinsics": {"width": 640, "height": 480, "fx": 400, "fy": 400,
                                                     "cx": 319.5, "cy": 239.5}}))
    cfg = EdgeCameraConfig(source={"type": "pattern"}, publish=PublishConfig(width=320))
    pub = FramePublisher(cfg, None, None, load_calibration(calib_path))  # type: ignore[arg-type]
    h = pub.header_for(Grab(rgb=np.zeros((480, 640, 3), np.uint8), stamp_ns=5), (320, 240))
    assert (h.width, h.height, h.intrinsics.fx, h.intrinsics.cx) == (320, 240, 200.0, 159.5)
    assert h.T_world_cam is None and h.pose_trusted is False


class TestHeaderPoseCovariance:
    """The header's covariance comes with its pose, from whichever supplied the pose."""

    T_GRAB = np.diag([1.0, -1.0, -1.0, 1.0])
    COV_GRAB = pose_covariance(0.3, 5.0)

    def header(self, tmp_path, calibration: dict | None, **grab):
        from edge_camera.sources.base import Grab

        calib = None
        if calibration is not None:
            (tmp_path / "c.json").write_text(json.dumps(calibration))
            calib = load_calibration(tmp_path / "c.json")
        pub = FramePublisher(EdgeCameraConfig(source={"type": "pattern"}), None, None, calib)  # type: ignore[arg-type]
        return pub.header_for(Grab(rgb=np.zeros((24, 32, 3), np.uint8), stamp_ns=5, **grab), (32, 24))

    def test_from_the_grab_without_calibration(self, tmp_path):
        h = self.header(tmp_path, None, T_world_cam=self.T_GRAB, pose_covariance=self.COV_GRAB)
        assert np.array_equal(np.asarray(h.pose_covariance), self.COV_GRAB) and h.pose_trusted is False
        assert self.header(tmp_path, None, T_world_cam=self.T_GRAB).pose_covariance is None

    def test_no_pose_no_covariance(self, tmp_path):
        h = self.header(tmp_path, None, pose_covariance=self.COV_GRAB)
        assert h.T_world_cam is None and h.pose_covariance is None
        intr_only = {"intrinsics": {"width": 32, "height": 24, "fx": 30, "fy": 30, "cx": 15.5, "cy": 11.5}}
        h = self.header(tmp_path, intr_only, pose_covariance=self.COV_GRAB)
        assert h.T_world_cam is None and h.pose_covariance is None

    def test_calibration_pose_brings_its_own_covariance(self, tmp_path):
        calib = {"T_world_cam": np.eye(4).tolist(), "pose_sigma_trans_m": 0.01, "pose_sigma_rot_deg": 0.5}
        h = self.header(tmp_path, calib, T_world_cam=self.T_GRAB, pose_covariance=self.COV_GRAB)
        assert np.array_equal(np.asarray(h.T_world_cam), np.eye(4)) and h.pose_trusted is True
        assert np.array_equal(np.asarray(h.pose_covariance), pose_covariance(0.01, 0.5))
        # A calibrated pose without a stated accuracy does not borrow the grab's.
        h = self.header(tmp_path, {"T_world_cam": np.eye(4).tolist()}, T_world_cam=self.T_GRAB,
                        pose_covariance=self.COV_GRAB)
        assert h.pose_trusted is True and h.pose_covariance is None

    def test_calibration_intrinsics_only_keep_the_grabs_pose_and_covariance(self, tmp_path):
        intr_only = {"intrinsics": {"width": 32, "height": 24, "fx": 30, "fy": 30, "cx": 15.5, "cy": 11.5}}
        h = self.header(tmp_path, intr_only, T_world_cam=self.T_GRAB, pose_covariance=self.COV_GRAB)
        assert np.array_equal(np.asarray(h.T_world_cam), self.T_GRAB)
        assert np.array_equal(np.asarray(h.pose_covariance), self.COV_GRAB) and h.pose_trusted is False


@pytest.mark.parametrize(
    ("w", "h", "pw", "ph", "out"),
    [(640, 480, None, None, (640, 480)), (640, 480, 160, None, (160, 120)), (640, 480, None, 240, (320, 240)),
     (640, 480, 100, 100, (100, 100))],
)
def test_output_size(w, h, pw, ph, out):
    assert output_size(w, h, PublishConfig(width=pw, height=ph)) == out


def test_config_file_and_overrides(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('id = "a"\n[source]\ntype = "folder"\npath = "/x"\n')
    cfg = load_config(EdgeCameraConfig, p, {"publish.width": 320, "id": None}, ["source.rate_hz=0.5"])
    assert cfg.id == "a" and cfg.publish.width == 320 and cfg.source.rate_hz == 0.5
    with pytest.raises(ConfigError, match="publsh"):
        load_config(EdgeCameraConfig, p, overrides=["publsh.width=3"])
    with pytest.raises(ConfigError, match="id"):
        load_config(EdgeCameraConfig, p, {"id": "bad/id"})
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(EdgeCameraConfig, tmp_path / "none.toml")


def test_shipped_example_configs_validate():
    from robot_agent.config import RobotAgentConfig

    for path in sorted((REPO / "edge_camera" / "examples").glob("*.toml")):
        load_config(EdgeCameraConfig, path)
    for path in sorted((REPO / "robot_agent" / "examples").glob("*.toml")):
        load_config(RobotAgentConfig, path)


@pytest.mark.integration
def test_help_shows_an_example_command():
    for cmd in ("edge-camera", "robot-agent"):
        out = subprocess.run([sys.executable, "-m", "deploy.cli", cmd, "--help"], cwd=REPO, capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0 and f"argus {cmd} --config" in out.stdout


@pytest.mark.integration
def test_light_imports_pull_in_neither_torch_nor_open3d_nor_sim():
    code = (
        "import sys\n"
        "import protocol.codec, protocol.transport, protocol.session, protocol.tomlconfig\n"
        "import edge_camera.cli, edge_camera.node, edge_camera.config\n"
        "from edge_camera.sources import create_source, parse_source_config\n"
        "for t in ('opencv', 'stream', 'video', 'folder', 'recorded', 'pattern', 'sim'):\n"
        "    __import__('edge_camera.sources.' + {'opencv': 'opencv_device'}.get(t, t))\n"
        "s = create_source(parse_source_config({'type': 'pattern', 'width': 8, 'height': 8})); s.open(); s.read()\n"
        "import robot_agent.cli, robot_agent.node, robot_agent.config\n"
        "from robot_agent.bodies import create_body, parse_body_config\n"
        "b = create_body(parse_body_config({'type': 'kinematic'})); b.capture()\n"
        "parse_body_config({'type': 'sim'}); parse_source_config({'type': 'sim'})\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'open3d', 'sim', 'trimesh', "
        "'mapper', 'planner', 'bench'))\n"
        "print('HEAVY', bad)\n"
        "sys.exit(1 if bad else 0)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "HEAVY []" in out.stdout


def test_live_capture_keeps_only_the_newest_frame_and_reports_the_end(tmp_path):
    # A file:// URL through the stream backend exercises the live reader thread without a network.
    _write_video(tmp_path / "s.avi", 30)
    src = create_source(parse_source_config({"type": "stream", "url": f"file://{tmp_path / 's.avi'}",
                                             "read_timeout_s": 2.0}))
    src.open()
    try:
        assert src.read().rgb.shape == (48, 64, 3)
        got = 0
        with pytest.raises(SourceError, match="ended"):
            for _ in range(100):
                src.read()
                got += 1
        # The reader raced through the file: most frames were superseded, never queued.
        assert got < 30 and src.superseded + got + 1 >= 29
    finally:
        src.close()
