"""Labelled 2-D tracking of the machine's markers in one camera's video, guided by the
calibrated camera and the machine model."""

from mocap.tracking.model import CameraModel
from mocap.tracking.run import TrackSummary, track_frames
from mocap.tracking.tracker import FrameResult, Tracker, TrackOptions

__all__ = ["CameraModel", "FrameResult", "TrackOptions", "TrackSummary", "Tracker", "track_frames"]
