"""``argus edge-camera calibrate``: a fixed camera's calibration file from images of a ChArUco board
(``DETAILS`` and ``EXAMPLES`` below are its help)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from edge_camera.board import BoardError, BoardSpec, board_pose, calibrate_intrinsics, camera_pose, detect
from edge_camera.calibration import CalibrationError, load_calibration
from protocol.poses import PoseError, as_pose

DETAILS = """All images come from the camera to calibrate, at its publish resolution. Without --intrinsics at least
three images show the board at different angles (held by hand) and the intrinsics are calibrated from all
of them; the LAST image shows the board at its surveyed pose (--board-pose) with the camera mounted, and
gives the camera's pose. The output is the JSON calibration file `argus edge-camera --calibration` reads."""

EXAMPLES = """examples:
  argus edge-camera calibrate --print-board board.png          # print it, measure the square side
  argus edge-camera calibrate held1.jpg held2.jpg held3.jpg mounted.jpg \\
      --board-pose 2.0,0.5,1.1,90,0,180 --out cam1.json        # intrinsics and pose
  argus edge-camera calibrate mounted.jpg --intrinsics cam1.json --board-pose ... --out cam1.json"""

EPILOG = """The board pose is the surveyed pose of the board in the world (z up, floor z = 0): its origin is the
board's corner at the first chessboard square, x along the printed rows, y down the printed columns, z out
of the back of the print (OpenCV's ChArUco frame). Give it as x,y,z,roll,pitch,yaw (metres, degrees;
R = Rz(yaw) Ry(pitch) Rx(roll)) or as 16 numbers (a 4x4 matrix, row-major).
Exit status: 0 written, 2 on an input or board error (the message says which image and why)."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="argus edge-camera calibrate",
        description="A fixed camera's calibration file (intrinsics and pose) from images of a ChArUco board.\n\n"
        + DETAILS, epilog=EXAMPLES + "\n\n" + EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("images", nargs="*", type=Path, help="images of the board; the last at the surveyed pose")
    p.add_argument("--board", default="7x5", help="chessboard squares, XxY (default 7x5)")
    p.add_argument("--square-m", type=float, default=0.04, help="printed square side, metres")
    p.add_argument("--marker-m", type=float, default=0.03, help="printed marker side, metres")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (cv2.aruco.DICT_*)")
    p.add_argument("--board-pose", default=None, help="T_world_board: x,y,z,roll,pitch,yaw or 16 numbers")
    p.add_argument("--intrinsics", type=Path, default=None, help="take intrinsics from this calibration file")
    p.add_argument("--out", type=Path, default=None, help="calibration file to write (JSON)")
    p.add_argument("--print-board", type=Path, default=None, help="write the board image (PNG) and exit")
    return p


def parse_board_pose(text: str) -> np.ndarray:
    """``x,y,z,roll,pitch,yaw`` (metres, degrees) or 16 numbers (4x4 row-major) to a 4x4 pose."""
    try:
        v = [float(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        raise ValueError(f"--board-pose {text!r}: not a list of numbers") from None
    if len(v) == 16:
        return as_pose(np.asarray(v).reshape(4, 4), source="--board-pose")
    if len(v) != 6:
        raise ValueError(f"--board-pose needs 6 or 16 numbers, got {len(v)}")
    x, y, z, roll, pitch, yaw = v
    cr, sr, cp, sp = math.cos(math.radians(roll)), math.sin(math.radians(roll)), math.cos(math.radians(pitch)), \
        math.sin(math.radians(pitch))
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    Rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rz @ Ry @ Rx, (x, y, z)
    return T


def _spec(a: argparse.Namespace) -> BoardSpec:
    try:
        sx, sy = (int(n) for n in a.board.lower().split("x"))
    except ValueError:
        raise ValueError(f"--board {a.board!r}: expected XxY, e.g. 7x5") from None
    return BoardSpec(squares_x=sx, squares_y=sy, square_m=a.square_m, marker_m=a.marker_m, dictionary=a.dictionary)


def calibrate(a: argparse.Namespace) -> dict[str, object]:
    """The calibration file's content; ValueError (BoardError, CalibrationError, PoseError) on bad input."""
    spec = _spec(a)
    if not a.images:
        raise ValueError("no images given")
    if a.board_pose is None:
        raise ValueError("--board-pose is needed: where the board is in the world in the last image")
    T_world_board = parse_board_pose(a.board_pose)
    views, size = [], None
    for path in a.images:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"{path}: not a readable image")
        if size is not None and img.shape != size:
            raise ValueError(f"{path}: {img.shape[1]}x{img.shape[0]}, the other images are {size[1]}x{size[0]}")
        size = img.shape
        try:
            views.append(detect(np.asarray(img, np.uint8), spec))
        except BoardError as e:
            raise BoardError(f"{path}: {e}") from None
    assert size is not None
    h, w = size
    if a.intrinsics is not None:
        calib = load_calibration(a.intrinsics)
        if calib.intrinsics is None:
            raise CalibrationError(f"{a.intrinsics} holds no intrinsics")
        intr = calib.intrinsics if (calib.intrinsics.width, calib.intrinsics.height) == (w, h) else \
            calib.intrinsics.scaled(w, h)
        dist = calib.distortion if calib.distortion is not None else np.zeros(5)
        rms_intr = None
    else:
        intr, dist, rms_intr = calibrate_intrinsics(views, w, h)
    T_cam_board, rms_pose = board_pose(views[-1], intr.K(), dist)
    T_world_cam = as_pose(camera_pose(T_world_board, T_cam_board), source="the calibrated pose")
    return {
        "intrinsics": intr.model_dump(),
        "distortion_coefficients": [float(x) for x in np.asarray(dist).reshape(-1)],
        "T_world_cam": np.round(T_world_cam, 6).tolist(),
        "_report": {"images": len(views), "rms_intrinsics_px": rms_intr, "rms_pose_px": rms_pose,
                    "corners_last_image": len(views[-1].object_points)},
    }


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    if a.print_board is not None:
        try:
            img = _spec(a).image()
        except ValueError as e:
            print(f"argus edge-camera calibrate: {e}", file=sys.stderr)
            return 2
        cv2.imwrite(str(a.print_board), img)
        print(f"board written to {a.print_board}: print it flat, then measure one square and pass --square-m")
        return 0
    if a.out is None:
        print("argus edge-camera calibrate: --out is needed", file=sys.stderr)
        return 2
    try:
        result = calibrate(a)
    except (ValueError, PoseError) as e:
        print(f"argus edge-camera calibrate: {e}", file=sys.stderr)
        return 2
    report = result.pop("_report")
    a.out.write_text(json.dumps(result, indent=2) + "\n")
    t = np.asarray(result["T_world_cam"])[:3, 3]
    print(f"wrote {a.out}: camera at ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m; {report}")
    return 0
