"""A calibration board seen by the camera: its pose per image, for hand-eye without VO.

Two kinds of board (:class:`BoardSpec` ``kind``):

* ``charuco``: a chessboard with ArUco markers in its white squares (``cv2.aruco.CharucoBoard``,
  ``CharucoDetector``); its points are the inner chessboard corners.
* ``apriltag``: a grid of AprilTags (``cv2.aruco.GridBoard`` with an AprilTag dictionary,
  ``DICT_APRILTAG_36h11`` by default, detected by ``ArucoDetector`` with AprilTag corner
  refinement), as Kalibr's "aprilgrid"; its points are the four corners of every tag seen.

:class:`BoardDetector` solves the board's pose with ``solvePnP`` from the points it sees: for one
image it returns ``T_camera_board`` (board frame: OpenCV's, x to the right and y down
:meth:`BoardDetector.image`, z into the board) with the RMS reprojection error of the points, or
None when too few are seen. A board fixed in the room while the tracked body moves gives camera
motions ``B = T_camera_board(i) @ T_camera_board(j)^-1`` for
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

__all__ = ["BOARD_KINDS", "BoardDetector", "BoardPose", "BoardSpec", "aruco_available", "board_camera_poses",
           "parse_board"]

BOARD_KINDS = ("charuco", "apriltag")
_DEFAULT_DICTIONARY = {"charuco": "DICT_5X5_100", "apriltag": "DICT_APRILTAG_36h11"}


def aruco_available() -> bool:
    """Whether this OpenCV has the ChArUco detector (OpenCV >= 4.7 with ``aruco``)."""
    return hasattr(cv2, "aruco") and hasattr(cv2.aruco, "CharucoDetector")


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """A board as printed (measure the print).

    Attributes:
        squares_x, squares_y: ChArUco: chessboard squares along x and y; AprilTag grid: tags per
            row and per column.
        square_m: ChArUco: side of a chessboard square; AprilTag grid: tag pitch (tag side plus
            the gap between tags), metres.
        marker_m: side of a marker (tag), metres; smaller than ``square_m``.
        dictionary: the OpenCV dictionary name (default ``DICT_5X5_100`` for ChArUco,
            ``DICT_APRILTAG_36h11`` for an AprilTag grid).
        kind: ``charuco`` or ``apriltag``.
    """

    squares_x: int = 5
    squares_y: int = 7
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = ""
    kind: str = "charuco"

    @property
    def dictionary_name(self) -> str:
        return self.dictionary or _DEFAULT_DICTIONARY.get(self.kind, "")


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


class BoardDetector:
    """Detect a ChArUco board or an AprilTag grid and solve its pose.

    Args:
        spec: the board.
        camera_matrix: 3x3 intrinsics (pixels).
        dist_coeffs: OpenCV distortion coefficients (None: none).
        min_corners: fewer board points than this give no pose (an AprilTag gives 4).

    Raises:
        CalibrationError: this OpenCV has no aruco module, an unknown kind, or an unknown dictionary.
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
        if spec.kind not in BOARD_KINDS:
            raise CalibrationError(f"unknown board kind {spec.kind!r}; use {' or '.join(BOARD_KINDS)}", "board")
        dict_id = getattr(cv2.aruco, spec.dictionary_name, None)
        if dict_id is None:
            raise CalibrationError(
                f"unknown dictionary {spec.dictionary_name!r}; use e.g. {_DEFAULT_DICTIONARY[spec.kind]}", "board"
            )
        self.spec = spec
        dictionary = cv2.aruco.getPredefinedDictionary(dict_id)
        self.board: Any
        self.detector: Any
        if spec.kind == "charuco":
            self.board = cv2.aruco.CharucoBoard(
                (spec.squares_x, spec.squares_y), spec.square_m, spec.marker_m, dictionary
            )
            self.detector = cv2.aruco.CharucoDetector(self.board)
        else:
            self.board = cv2.aruco.GridBoard(
                (spec.squares_x, spec.squares_y), spec.marker_m, spec.square_m - spec.marker_m, dictionary
            )
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG  # 0.12 px rendered (SUBPIX: 0.73)
            self.detector = cv2.aruco.ArucoDetector(dictionary, params)
        self.K = np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
        self.dist = np.zeros(5) if dist_coeffs is None else np.asarray(dist_coeffs, dtype=np.float64).reshape(-1)
        self.min_corners = min_corners

    def image(self, px_per_square: int = 100, margin_px: int = 0) -> npt.NDArray[np.uint8]:
        """The board as an 8-bit image, ``px_per_square`` pixels per square (tag pitch), e.g. to
        print or to render in a test; a pixel is ``square_m / px_per_square`` metres of the board.
        An AprilTag grid's image is one gap narrower than its pitch times the tag count."""
        gap_px = 0 if self.spec.kind == "charuco" else round(
            px_per_square * (self.spec.square_m - self.spec.marker_m) / self.spec.square_m
        )
        size = (
            self.spec.squares_x * px_per_square - gap_px + 2 * margin_px,
            self.spec.squares_y * px_per_square - gap_px + 2 * margin_px,
        )
        return np.asarray(self.board.generateImage(size, marginSize=margin_px), dtype=np.uint8)

    def detect(self, gray: npt.NDArray[np.uint8]) -> BoardPose | None:
        """The board's pose in ``gray`` (8-bit), or None when fewer than ``min_corners`` points are seen."""
        if self.spec.kind == "charuco":
            corners, ids, _, _ = self.detector.detectBoard(gray)
        else:
            corners, ids, _ = self.detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            return None
        obj, img = self.board.matchImagePoints(corners, ids)
        if obj is None or len(obj) < self.min_corners:
            return None
        ok, rvec, tvec = cv2.solvePnP(obj, img, self.K, self.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return None
        proj, _ = cv2.projectPoints(obj, rvec, tvec, self.K, self.dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
        R, _ = cv2.Rodrigues(rvec)  # noqa: N806
        T = np.eye(4)  # noqa: N806
        T[:3, :3] = R
        T[:3, 3] = tvec.reshape(3)
        return BoardPose(Transform.from_matrix(T), int(len(obj)), err)


def parse_board(text: str) -> BoardSpec:
    """``[KIND:]NXxNY:SQUARE_M:MARKER_M[:DICT]``: ``5x7:0.04:0.03`` (a ChArUco board, the default
    kind), ``charuco:5x7:0.04:0.03:DICT_4X4_50``, ``apriltag:6x6:0.05:0.04`` (6 x 6 AprilTags
    36h11, 5 cm pitch, 4 cm tags).

    Raises:
        CalibrationError: malformed text.
    """
    parts = text.split(":")
    kind = parts.pop(0).lower() if parts and parts[0].lower() in BOARD_KINDS else "charuco"
    try:
        sx, sy = (int(v) for v in parts[0].lower().split("x"))
        spec = BoardSpec(sx, sy, float(parts[1]), float(parts[2]), parts[3] if len(parts) > 3 else "", kind)
    except (ValueError, IndexError) as exc:
        raise CalibrationError(
            f"board {text!r} is not [KIND:]SQUARESxSQUARES:SQUARE_M:MARKER_M[:DICT], e.g. 5x7:0.04:0.03 or "
            "apriltag:6x6:0.05:0.04",
            "board",
        ) from exc
    least = 3 if kind == "charuco" else 2
    if not (spec.squares_x >= least and spec.squares_y >= least and 0 < spec.marker_m < spec.square_m):
        raise CalibrationError(
            f"board {text!r}: needs >= {least}x{least} {'squares' if kind == 'charuco' else 'tags'} and "
            "0 < marker < square (pitch)", "board")
    return spec


def board_camera_poses(
    detector: BoardDetector,
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
