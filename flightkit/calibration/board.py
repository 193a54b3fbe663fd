"""A ChArUco board seen by the camera: its pose per image, for hand-eye without VO.

:class:`CharucoBoardDetector` wraps OpenCV's ``cv2.aruco`` (``CharucoDetector`` and
``solvePnP``): for one image it returns ``T_camera_board`` (board frame: origin at the board's
outer corner that is top-left in :meth:`CharucoBoardDetector.image`, x to the right and y down
that image, z into the board) with the RMS reprojection error of
the corners, or None when too few corners are seen. A board fixed in the room while the tracked
body moves gives camera motions ``B = T_camera_board(i) @ T_camera_board(j)^-1`` for
:func:`flightkit.calibration.hand_eye.solve_hand_eye`.

When the OpenCV build has no ``aruco`` module, constructing the detector raises
:class:`~flightkit.errors.CalibrationError` saying so.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from flightkit.errors import CalibrationError
from flightkit.frames import Transform

__all__ = ["BoardPose", "BoardSpec", "CharucoBoardDetector", "aruco_available", "board_camera_poses", "parse_board"]


def aruco_available() -> bool:
    """Whether this OpenCV has the ChArUco detector (OpenCV >= 4.7 with ``aruco``)."""
    return hasattr(cv2, "aruco") and hasattr(cv2.aruco, "CharucoDetector")


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """A ChArUco board as printed.

    Attributes:
        squares_x, squares_y: chessboard squares along x and y.
        square_m: side of a chessboard square, metres (measure the print).
        marker_m: side of an ArUco marker, metres.
        dictionary: the ArUco dictionary name in OpenCV, e.g. ``"DICT_5X5_100"``.
    """

    squares_x: int = 5
    squares_y: int = 7
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = "DICT_5X5_100"


@dataclass(frozen=True, slots=True)
class BoardPose:
    """The board in one image.

    Attributes:
        T_camera_board: the board's pose in the camera (OpenCV) frame.
        corners: ChArUco corners used.
        reprojection_px: RMS reprojection error of those corners, pixels.
    """

    T_camera_board: Transform
    corners: int
    reprojection_px: float


class CharucoBoardDetector:
    """Detect a ChArUco board and solve its pose.

    Args:
        spec: the board.
        camera_matrix: 3x3 intrinsics (pixels).
        dist_coeffs: OpenCV distortion coefficients (None: none).
        min_corners: fewer corners than this give no pose.

    Raises:
        CalibrationError: this OpenCV has no aruco module, or the dictionary name is unknown.
    """

    def __init__(
        self,
        spec: BoardSpec,
        camera_matrix: npt.ArrayLike,
        dist_coeffs: npt.ArrayLike | None = None,
        min_corners: int = 6,
    ) -> None:
        if not aruco_available():
            raise CalibrationError(
                f"OpenCV {cv2.__version__} has no ChArUco detector (cv2.aruco); install opencv-contrib-python "
                "or calibrate hand-eye from VO instead",
                "board",
            )
        dict_id = getattr(cv2.aruco, spec.dictionary, None)
        if dict_id is None:
            raise CalibrationError(f"unknown ArUco dictionary {spec.dictionary!r}; use e.g. DICT_5X5_100", "board")
        self.spec = spec
        self.board: Any = cv2.aruco.CharucoBoard(
            (spec.squares_x, spec.squares_y), spec.square_m, spec.marker_m, cv2.aruco.getPredefinedDictionary(dict_id)
        )
        self.detector: Any = cv2.aruco.CharucoDetector(self.board)
        self.K = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
        self.dist = np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64).reshape(-1)
        self.min_corners = min_corners

    def image(self, px_per_square: int = 100, margin_px: int = 0) -> npt.NDArray[np.uint8]:
        """The board as an 8-bit image, e.g. to print or to render in a test."""
        size = (
            self.spec.squares_x * px_per_square + 2 * margin_px,
            self.spec.squares_y * px_per_square + 2 * margin_px,
        )
        return np.asarray(self.board.generateImage(size, marginSize=margin_px), dtype=np.uint8)

    def detect(self, gray: npt.NDArray[np.uint8]) -> BoardPose | None:
        """The board's pose in ``gray`` (8-bit), or None when fewer than ``min_corners`` corners are seen."""
        corners, ids, _, _ = self.detector.detectBoard(gray)
        if ids is None or len(ids) < self.min_corners:
            return None
        obj, img = self.board.matchImagePoints(corners, ids)
        ok, rvec, tvec = cv2.solvePnP(obj, img, self.K, self.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return None
        proj, _ = cv2.projectPoints(obj, rvec, tvec, self.K, self.dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
        R, _ = cv2.Rodrigues(rvec)  # noqa: N806
        T = np.eye(4)  # noqa: N806
        T[:3, :3] = R
        T[:3, 3] = tvec.reshape(3)
        return BoardPose(Transform.from_matrix(T), int(len(ids)), err)


def parse_board(text: str) -> BoardSpec:
    """``"5x7:0.04:0.03"`` or ``"5x7:0.04:0.03:DICT_4X4_50"`` (squares, square m, marker m[, dictionary]).

    Raises:
        CalibrationError: malformed text.
    """
    parts = text.split(":")
    try:
        sx, sy = (int(v) for v in parts[0].lower().split("x"))
        spec = BoardSpec(sx, sy, float(parts[1]), float(parts[2]), parts[3] if len(parts) > 3 else "DICT_5X5_100")
    except (ValueError, IndexError) as exc:
        raise CalibrationError(
            f"board {text!r} is not SQUARESxSQUARES:SQUARE_M:MARKER_M[:DICT], e.g. 5x7:0.04:0.03", "board"
        ) from exc
    if not (spec.squares_x >= 3 and spec.squares_y >= 3 and 0 < spec.marker_m < spec.square_m):
        raise CalibrationError(f"board {text!r}: needs >= 3x3 squares and 0 < marker < square", "board")
    return spec


def board_camera_poses(
    detector: CharucoBoardDetector,
    images: Iterable[tuple[int, npt.NDArray[np.uint8]]],
    max_reprojection_px: float = 2.0,
) -> tuple[list[int], list[Transform], list[float]]:
    """The camera's pose in the board frame (``T_board_camera``) for every image that shows the board.

    Args:
        detector: the board detector.
        images: (stamp_ns, 8-bit grey image) pairs.
        max_reprojection_px: detections worse than this are left out.

    Returns:
        (stamps, poses, reprojection errors) of the images kept. Blocks while detecting (~5-20 ms per image).
    """
    stamps: list[int] = []
    poses: list[Transform] = []
    errors: list[float] = []
    for stamp, gray in images:
        pose = detector.detect(gray)
        if pose is None or pose.reprojection_px > max_reprojection_px:
            continue
        stamps.append(int(stamp))
        poses.append(pose.T_camera_board.inverse())
        errors.append(pose.reprojection_px)
    return stamps, poses, errors
