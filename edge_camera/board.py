"""Intrinsics and pose of a fixed camera from a printed ChArUco board (OpenCV's aruco module; pure: images in,
matrices out).

Print the board (``argus edge-camera calibrate --print-board board.png``), measure its square size, put it
where the camera sees it and survey the board's pose in the world once (``T_world_board``: its origin is the
board's first chessboard corner, x along the squares' rows, y along the columns, z out of the printed face).
With several images of the board held at different angles the camera's intrinsics are calibrated too; with
one image (or known intrinsics) only the pose is solved. The camera's pose is
``T_world_cam = T_world_board @ inv(T_cam_board)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from protocol.messages import Intrinsics

F64 = NDArray[np.float64]


class BoardError(ValueError):
    """The board was not found, or too poorly, to calibrate from."""


class BoardSpec(BaseModel):
    """A ChArUco board as printed."""

    model_config = ConfigDict(extra="forbid")
    squares_x: int = Field(default=7, ge=3, description="chessboard squares along x")
    squares_y: int = Field(default=5, ge=3, description="chessboard squares along y")
    square_m: float = Field(default=0.04, gt=0.0, description="printed square side, metres (measure it)")
    marker_m: float = Field(default=0.03, gt=0.0, description="printed marker side, metres")
    dictionary: str = Field(default="DICT_5X5_100", description="ArUco dictionary name (cv2.aruco.DICT_*)")

    def board(self) -> cv2.aruco.CharucoBoard:
        if self.marker_m >= self.square_m:
            raise BoardError("marker_m must be smaller than square_m")
        d = getattr(cv2.aruco, self.dictionary, None)
        if not isinstance(d, int):
            raise BoardError(f"unknown ArUco dictionary {self.dictionary!r}")
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m,
                                      cv2.aruco.getPredefinedDictionary(d))

    def image(self, px_per_square: int = 120) -> NDArray[np.uint8]:
        """The board to print, with a white margin of half a square: board point (x, y) metres is at pixel
        ``margin + (x, y) / square_m * px_per_square``, ``margin = px_per_square // 2``."""
        m = px_per_square // 2
        size = (self.squares_x * px_per_square + 2 * m, self.squares_y * px_per_square + 2 * m)
        return np.asarray(self.board().generateImage(size, marginSize=m), np.uint8)


@dataclass(frozen=True)
class BoardView:
    """Board corners found in one image: ``object_points`` (N, 3) on the board (metres, z = 0) and their
    ``image_points`` (N, 2) pixels."""

    object_points: F64
    image_points: F64


def detect(image: NDArray[np.uint8], spec: BoardSpec, min_corners: int = 6) -> BoardView:
    """The board's chessboard corners in an image (RGB or grey); :class:`BoardError` when fewer than
    ``min_corners`` are found."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    board = spec.board()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(grey)
    n = 0 if ids is None else len(ids)
    if n < min_corners:
        raise BoardError(f"board not found: {n} of {(spec.squares_x - 1) * (spec.squares_y - 1)} corners seen "
                         f"(need {min_corners}; is the board {spec.squares_x}x{spec.squares_y} {spec.dictionary}, "
                         "in focus and fully lit?)")
    obj, img = board.matchImagePoints(corners, ids)  # type: ignore[call-overload]  # stubs want a list of UMat
    return BoardView(np.asarray(obj, np.float64).reshape(-1, 3), np.asarray(img, np.float64).reshape(-1, 2))


def calibrate_intrinsics(views: Sequence[BoardView], width: int, height: int) -> tuple[Intrinsics, F64, float]:
    """Intrinsics, distortion (k1 k2 p1 p2 k3) and RMS reprojection error (px) from >= 3 board views at
    different angles (10 or more for the tangential and third radial terms)."""
    if len(views) < 3:
        raise BoardError(f"calibrating intrinsics needs >= 3 images of the board at different angles, got {len(views)}")
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32) for v in views]
    # Few views cannot pin down five distortion terms: below 10, only the two radial ones are estimated.
    flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST if len(views) < 10 else 0
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (width, height), None, None, flags=flags)
    intr = Intrinsics(width=width, height=height, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                      cy=float(K[1, 2]))
    return intr, np.asarray(dist, np.float64).reshape(-1), float(rms)


def board_pose(view: BoardView, K: F64, dist: F64 | None = None, max_rms_px: float = 2.0) -> tuple[F64, float]:
    """``T_cam_board`` (4x4) and its RMS reprojection error (px); :class:`BoardError` above ``max_rms_px``."""
    ok, rvec, tvec = cv2.solvePnP(view.object_points, view.image_points, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise BoardError("the board's pose could not be solved")
    proj, _ = cv2.projectPoints(view.object_points, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - view.image_points) ** 2, axis=1))))
    if rms > max_rms_px:
        raise BoardError(f"board pose reprojects {rms:.1f} px RMS (> {max_rms_px}): wrong intrinsics or board size?")
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T, rms


def camera_pose(T_world_board: F64, T_cam_board: F64) -> F64:
    """``T_world_cam`` of the camera that sees the board at ``T_cam_board``."""
    return np.asarray(T_world_board, np.float64) @ np.linalg.inv(T_cam_board)
