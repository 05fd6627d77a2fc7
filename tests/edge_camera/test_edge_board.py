"""Fixed-camera calibration from a ChArUco board (edge_camera.board and ``argus edge-camera calibrate``)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from edge_camera.board import BoardError, BoardSpec, board_pose, calibrate_intrinsics, camera_pose, detect
from edge_camera.calibration import load_calibration
from protocol.messages import Intrinsics
from protocol.poses import rotation_angle_deg

SPEC = BoardSpec(squares_x=7, squares_y=5, square_m=0.04, marker_m=0.03)
INTR = Intrinsics(width=640, height=480, fx=520.0, fy=520.0, cx=322.0, cy=236.0)
P = 120  # printed pixels per square


def T_cam_board(rx_deg: float, ry_deg: float, centre: tuple[float, float, float]) -> np.ndarray:
    """The board turned by (rx, ry) degrees, its centre at ``centre`` in the camera frame."""
    R = cv2.Rodrigues(np.radians([rx_deg, ry_deg, 0.0]))[0]
    mid = np.array([SPEC.squares_x * SPEC.square_m / 2, SPEC.squares_y * SPEC.square_m / 2, 0.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(centre) - R @ mid
    return T


def photograph(T: np.ndarray, intr: Intrinsics = INTR) -> np.ndarray:
    """What the camera sees of the printed board at ``T`` (T_cam_board): a homography of the print."""
    printed = SPEC.image(P)
    m = P // 2
    k = SPEC.square_m / P
    to_metres = np.array([[k, 0, -m * k], [0, k, -m * k], [0, 0, 1.0]])
    H = intr.K() @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ to_metres
    grey = cv2.warpPerspective(printed, H, (intr.width, intr.height), flags=cv2.INTER_AREA, borderValue=150)
    return np.repeat(grey[:, :, None], 3, axis=2)


def test_pose_from_one_image_with_known_intrinsics() -> None:
    T = T_cam_board(20.0, -25.0, (0.05, 0.02, 0.7))
    view = detect(photograph(T), SPEC)
    assert len(view.object_points) >= 20
    est, rms = board_pose(view, INTR.K())
    assert rms < 1.0
    assert rotation_angle_deg(est, T) < 0.5
    assert np.linalg.norm(est[:3, 3] - T[:3, 3]) < 0.01
    T_world_board = np.eye(4)
    T_world_board[:3, 3] = [2.0, 1.0, 1.2]
    T_world_cam = camera_pose(T_world_board, T)
    corner = np.array([0.1, 0.1, 0.0, 1.0])  # a board point: the same world point either way
    assert np.allclose(T_world_cam @ T @ corner, T_world_board @ corner)


def test_intrinsics_from_several_views() -> None:
    poses = [T_cam_board(rx, ry, (x, y, z)) for rx, ry, x, y, z in
             [(25, 0, 0.0, 0.0, 0.6), (-20, 15, 0.1, -0.05, 0.7), (10, -30, -0.1, 0.05, 0.65), (0, 30, 0.05, 0.08, 0.8),
              (-25, -15, -0.08, -0.06, 0.55)]]
    views = [detect(photograph(T), SPEC) for T in poses]
    intr, dist, rms = calibrate_intrinsics(views, INTR.width, INTR.height)
    assert rms < 1.0
    assert intr.fx == pytest.approx(INTR.fx, rel=0.02) and intr.cx == pytest.approx(INTR.cx, abs=10)


def test_board_not_found_says_so() -> None:
    blank = np.full((480, 640, 3), 128, np.uint8)
    with pytest.raises(BoardError, match="board not found: 0 of 24 corners"):
        detect(blank, SPEC)
    with pytest.raises(BoardError, match=">= 3 images"):
        calibrate_intrinsics([], 640, 480)


def test_calibrate_command_writes_a_file_the_camera_reads(tmp_path: Path) -> None:
    from edge_camera.cli import main

    T_world_board = np.eye(4)
    T_world_board[:3, :3] = cv2.Rodrigues(np.radians([90.0, 0.0, 0.0]))[0]  # upright on a wall
    T_world_board[:3, 3] = [2.0, 3.0, 1.0]
    poses = [T_cam_board(rx, ry, (x, y, z)) for rx, ry, x, y, z in
             [(25, 0, 0.0, 0.0, 0.6), (-20, 15, 0.1, -0.05, 0.7), (10, -30, -0.1, 0.05, 0.65), (0, 20, 0.0, 0.0, 0.9)]]
    paths = []
    for i, T in enumerate(poses):
        paths.append(tmp_path / f"img{i}.png")
        cv2.imwrite(str(paths[-1]), photograph(T))
    out = tmp_path / "cam.json"
    pose_arg = ",".join(f"{v:.9f}" for v in T_world_board.reshape(-1))
    assert main(["calibrate", *map(str, paths), "--board-pose", pose_arg, "--out", str(out)]) == 0
    calib = load_calibration(out)
    truth = camera_pose(T_world_board, poses[-1])
    assert calib.intrinsics is not None and calib.intrinsics.fx == pytest.approx(INTR.fx, rel=0.03)
    assert calib.T_world_cam is not None
    assert np.linalg.norm(calib.T_world_cam[:3, 3] - truth[:3, 3]) < 0.03
    assert rotation_angle_deg(calib.T_world_cam, truth) < 1.0
    # with the intrinsics known, one image of the mounted camera is enough
    again = tmp_path / "again.json"
    assert main(["calibrate", str(paths[-1]), "--intrinsics", str(out), "--board-pose", pose_arg,
                 "--out", str(again)]) == 0
    assert json.loads(again.read_text())["intrinsics"] == json.loads(out.read_text())["intrinsics"]


def test_calibrate_command_refuses_clearly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from edge_camera.cli import main

    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    assert main(["calibrate", str(blank), "--board-pose", "0,0,1,0,0,0", "--out", str(tmp_path / "x.json")]) == 2
    assert "blank.png: board not found" in capsys.readouterr().err
    assert main(["calibrate", str(blank), "--board-pose", "1,2", "--out", str(tmp_path / "x.json")]) == 2
    assert "6 or 16 numbers" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
    assert main(["calibrate", "--print-board", str(tmp_path / "board.png")]) == 0
    assert detect(cv2.imread(str(tmp_path / "board.png")), SPEC) is not None
