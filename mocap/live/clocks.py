"""Following a camera whose clock drifts (its frames a little faster or slower than its
stated fps): every `every_s` seconds, each other camera's time offset against the reference
camera is estimated again from the motion of the last `window_s` seconds, as `mocap sync`
does (`mocap.clocks.align`: single-camera fits of each camera's frames, the curves laid on
the reference's), in a thread of its own; the rows then place that camera's frames with the
newest offset.

A camera's frame n is placed at n / fps + offset (DESIGN.md) with its stated fps: with a
drifting clock the offset that does so changes over the run; the estimate over a window is
the offset at about its middle frame.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from mocap.clocks.align import joint_curves, synchronise
from mocap.core.camera import Camera
from mocap.core.machine import Machine

log = logging.getLogger(__name__)

# the largest RMS difference of the joint curves (over their spread in the window) taken as a
# match: a window of 2 s spans little of a joint's range, so the fits' noise weighs more than
# in `mocap sync`'s whole recordings (0.15 there)
MAX_RESIDUAL = 0.3


@dataclass(frozen=True)
class OffsetEstimate:
    """Camera `camera`'s offset (s) estimated over a window of its frames around `frame`."""

    camera: int
    frame: float
    offset: float


class ClockFollower(threading.Thread):
    """`add(k, frame, pixels)` as frames are labelled; `offset(k)` the newest estimate (the
    calibration's until there is one). `search_s` bounds the change from the last offset."""

    def __init__(self, machine: Machine, cameras: list[Camera], fps: np.ndarray, offsets: np.ndarray,
                 stop: threading.Event, window_s: float = 2.0, every_s: float = 0.5, search_s: float = 0.3):
        super().__init__(name="clocks", daemon=True)
        self.machine, self.cameras, self.fps = machine, list(cameras), np.asarray(fps, dtype=float)
        self.offsets = np.array(offsets, dtype=float)
        self.calibrated = self.offsets.copy()
        self.stop, self.every_s, self.search_s = stop, every_s, search_s
        self.frames = [deque(maxlen=max(int(window_s * f), 8)) for f in self.fps]
        self.lock = threading.Lock()
        self.estimates: list[OffsetEstimate] = []
        self.at = np.full(len(self.fps), np.nan)  # the frame each camera's newest offset was estimated around
        self.cpu_s, self.updates = 0.0, 0  # this thread's CPU over its updates

    def add(self, k: int, frame: int, pixels: np.ndarray) -> None:
        with self.lock:
            self.frames[k].append((frame, pixels))

    def offset(self, k: int) -> float:
        return float(self.offsets[k])

    def run(self) -> None:
        while not self.stop.wait(self.every_s):
            self._timed_update()

    def finish(self) -> None:
        """After the run: the thread ended, one last estimate over the streams' last window, so
        that the newest offsets are the end's however fast the frames came (a file read as
        fast as it is tracked may end before the first wake-up)."""
        self.join(timeout=5.0)
        if not self.is_alive():
            self._timed_update()

    def _timed_update(self) -> None:
        try:
            began = time.thread_time()
            self.update()
            self.cpu_s += time.thread_time() - began
            self.updates += 1
        except Exception:
            log.exception("clock following failed; the offsets stay as they are")

    def update(self) -> None:
        """One estimate per other camera from the frames in the window."""
        with self.lock:
            windows = [list(d) for d in self.frames]
        if len(windows[0]) < 8:
            return
        reference = self._curves(0, windows[0])
        for k in range(1, len(self.cameras)):
            if len(windows[k]) < 8:
                continue
            curves = self._curves(k, windows[k])
            last = self.offsets[k] - self.offsets[0]  # synchronise's offsets are against the reference's frames
            result = synchronise([reference, curves], self.fps[[0, k]], max_offset=self.search_s + abs(last),
                                 min_overlap=0.5, max_residual=MAX_RESIDUAL)
            found = float(result.offsets[1]) + self.offsets[0]
            if not np.isfinite(found) or abs(found - self.offsets[k]) > self.search_s:
                log.info("camera %s: no offset found (%s)", self.cameras[k].name, result.reasons[1])
                continue
            self.offsets[k], self.at[k] = found, float(np.mean(curves.frames))
            self.estimates.append(OffsetEstimate(k, self.at[k], found))

    def _curves(self, k: int, window: list):
        frames = np.array([f for f, _ in window])
        pixels = np.stack([p for _, p in window])
        return joint_curves(self.machine, self.cameras[k], frames, pixels)
