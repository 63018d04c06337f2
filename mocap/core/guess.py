"""A user's initial guess of a calibration, in the paper's parameters: the type the guess
TOML reads and the calibration starts from."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Guess:
    """A user's initial guess: per camera name the paper's parameters; joints (J,) rad / m."""

    cameras: dict = field(default_factory=dict)
    joints: np.ndarray | None = None
