"""Model-based camera calibration against an articulated machine, and the classic DLT."""

from mocap.calibration.problem import Observations
from mocap.calibration.solve import CalibrationOptions, CalibrationResult, calibrate, template_camera
from mocap.core.guess import Guess

__all__ = [
    "CalibrationOptions",
    "CalibrationResult",
    "Guess",
    "Observations",
    "calibrate",
    "template_camera",
]
