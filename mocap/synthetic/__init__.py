"""Synthetic field sessions with exact ground truth: dig cycles of a machine model, field
cameras with their own clocks, visible marker pixels, and (optionally) rendered video."""

from mocap.synthetic.paths import CLASSES
from mocap.synthetic.session import SessionOptions, SyntheticSession, make_session, summary, write_truth

__all__ = ["CLASSES", "SessionOptions", "SyntheticSession", "make_session", "summary", "write_truth"]
