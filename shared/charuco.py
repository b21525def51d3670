"""The ChArUco calibration board: its geometry, OpenCV's board object and its printed image.

One definition serves the simulated board body (the world textures a plate with ``image``) and
``xm calibrate`` (which detects it). Board frame, as OpenCV defines it: origin at the board's
top-left outer corner as printed, x along the rows of squares (to the right on the print), y
down the print, z into the board (away from the viewer); chessboard corner ``i`` lies at
``board().getChessboardCorners()[i]``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np


class BoardError(ValueError):
    """A board description that OpenCV cannot build."""


@dataclass(frozen=True)
class BoardSpec:
    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.05  # side of one chessboard square
    marker_m: float = 0.037  # side of the ArUco marker inside a white square
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise BoardError(f"a ChArUco board needs at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_m < self.square_m:
            raise BoardError(f"marker side {self.marker_m} m must be positive and smaller than the square "
                             f"{self.square_m} m")
        if not hasattr(cv2.aruco, self.dictionary):
            raise BoardError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_50, DICT_5X5_100)")
        markers = (self.squares_x * self.squares_y) // 2
        size = int(self.dictionary.split("_")[-1]) if self.dictionary.split("_")[-1].isdigit() else 1 << 30
        if markers > size:
            raise BoardError(f"{self.dictionary} has {size} markers; a {self.squares_x}x{self.squares_y} board "
                             f"needs {markers}")

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    def board(self) -> cv2.aruco.CharucoBoard:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, d)

    def corners(self) -> np.ndarray:
        """(N,3) chessboard corners in the board frame, metres."""
        return np.asarray(self.board().getChessboardCorners(), float).reshape(-1, 3)

    def image(self, px_per_square: int = 64) -> np.ndarray:
        """The printed board, (H,W) uint8, no margin: pixel edge (u, v) is board point (u, v) / px_per_m."""
        return self.board().generateImage((self.squares_x * px_per_square, self.squares_y * px_per_square),
                                          marginSize=0, borderBits=1)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict, where: str = "board") -> BoardSpec:
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise BoardError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        try:
            return cls(**{k: type(getattr(cls(), k))(v) for k, v in data.items()})
        except (TypeError, ValueError) as exc:
            if isinstance(exc, BoardError):
                raise BoardError(f"{where}: {exc}") from exc
            raise BoardError(f"{where}: {exc}") from exc
