"""The calibration settings of a deployment: board geometry, registration placement, capture size.

A deployment may carry a ``[calibration]`` table (the board as printed and where the registration
board lies on the table)::

    [calibration]
    board = { squares_x = 7, squares_y = 5, square_m = 0.05, marker_m = 0.037, dictionary = "DICT_4X4_50" }
    registration = { xy = [0.0, 0.0], yaw_deg = 0.0, thickness_m = 0.003 }
    width = 640                  # capture size of a simulated calibration run
    height = 480
    frames = 120                 # frame sets of the simulated sequence
    model = "full"               # camera model: "full" (OpenCV's) or "centred" (see calibration/bundle.py)

Missing keys take the defaults shown (those of the simulated board body).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from calibration.bundle import MODELS
from services.world.calibration_sequence import Registration
from shared.charuco import BoardError, BoardSpec


@dataclass(frozen=True)
class Settings:
    board: BoardSpec = field(default_factory=BoardSpec)
    registration: Registration = field(default_factory=Registration)
    width: int = 640
    height: int = 480
    frames: int = 120
    model: str = "full"


KEYS = {"board", "registration", "width", "height", "frames", "model"}


def settings_from_table(table: dict, where: str = "[calibration]") -> Settings:
    unknown = sorted(set(table) - KEYS)
    if unknown:
        raise BoardError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(KEYS))})")
    try:
        reg = Registration.from_dict(table.get("registration", {}))
        width, height = int(table.get("width", 640)), int(table.get("height", 480))
        frames = int(table.get("frames", 120))
    except (TypeError, ValueError, IndexError) as exc:
        raise BoardError(f"{where}: {exc}") from exc
    model = str(table.get("model", "full"))
    if model not in MODELS:
        raise BoardError(f"{where}.model: one of {', '.join(MODELS)}, got {model!r}")
    if width < 16 or height < 16 or frames < 2:
        raise BoardError(f"{where}: width/height at least 16 px and frames at least 2, got {width}x{height}, {frames}")
    return Settings(BoardSpec.from_dict(table.get("board", {}), f"{where}.board"), reg, width, height, frames, model)


def load_settings(deployment: str | Path) -> Settings:
    """The ``[calibration]`` table of a deployment file (defaults where it has none)."""
    path = Path(deployment)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise BoardError(f"{path}: deployment file not found") from exc
    except tomllib.TOMLDecodeError as exc:
        raise BoardError(f"{path}: not valid TOML: {exc}") from exc
    return settings_from_table(data.get("calibration", {}), f"{path}: [calibration]")
