"""Calibration boards (chessboard, ChArUco): their geometry in metres and OpenCV objects."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from skyfix import validate
from skyfix.errors import InputError

__all__ = ["BoardSpec"]


@dataclass(frozen=True)
class BoardSpec:
    """A printed calibration board.

    ``kind``: ``"chessboard"`` or ``"charuco"``. ``squares``: (columns, rows) of squares;
    a chessboard then has (columns - 1) x (rows - 1) inner corners, OpenCV's pattern size.
    ``square_m``: side of a square in metres; ``marker_m``: ArUco marker side (ChArUco);
    ``dictionary``: OpenCV predefined ArUco dictionary name.
    """

    kind: str = "chessboard"
    squares: tuple[int, int] = (10, 7)
    square_m: float = 0.05
    marker_m: float = 0.037
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise InputError(f"BoardSpec.kind must be 'chessboard' or 'charuco', got {self.kind!r}")
        cols, rows = self.squares
        if min(cols, rows) < 3:
            raise InputError(f"BoardSpec.squares must be at least (3, 3), got {self.squares}")
        validate.positive_scalar("square_m", self.square_m)
        if self.kind == "charuco" and not 0 < self.marker_m < self.square_m:
            raise InputError(f"marker_m must be in (0, square_m={self.square_m}), got {self.marker_m}")

    @property
    def pattern_size(self) -> tuple[int, int]:
        """Inner corners (columns, rows) as OpenCV's chessboard functions want them."""
        return self.squares[0] - 1, self.squares[1] - 1

    def opencv_charuco_board(self):
        """The ``cv2.aruco.CharucoBoard`` of this spec."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_m, dictionary)

    def inner_corners_m(self) -> np.ndarray:
        """Inner corners ``(N, 3)`` in board metres (x right, y down from the top-left square corner, z=0),
        row-major, the order OpenCV reports ChArUco corner ids in."""
        cols, rows = self.pattern_size
        xx, yy = np.meshgrid(np.arange(1, cols + 1), np.arange(1, rows + 1))
        return np.stack((xx.ravel(), yy.ravel(), np.zeros(xx.size)), axis=1) * self.square_m
