"""The cameras of `mocap live`: a video file, a camera device number or a stream URL, each
read by its own thread into a small bounded queue of grey frames.

A file is read as fast as the tracker takes its frames, or with `realtime` as its camera
delivered them: frame f of camera k at f / fps_k + time_offset_k after the start (the
offsets shifted so that none is negative). A device or a stream is read as it comes and
reopened, with a growing pause, when it fails. A frame that finds the queue full (the
tracker is behind) pushes out the oldest one, which is counted as dropped: a late frame
never backs up the queue.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mocap.errors import InputError
from mocap.io.video import Video

log = logging.getLogger(__name__)

FILE, DEVICE, URL = "file", "device", "url"
_RECONNECT_S = (0.5, 5.0)  # first and longest pause before a failed device or stream is reopened


@dataclass(frozen=True)
class SourceSpec:
    """`--source NAME=SOURCE`: the calibration's camera `camera` read from `target`, a file
    path, a device number or a URL (`kind`)."""

    camera: str
    kind: str
    target: str | int

    @property
    def live(self) -> bool:
        return self.kind != FILE


def parse_source(text: str) -> SourceSpec:
    """NAME=SOURCE: SOURCE all digits is a device number, with ``://`` a stream URL, else a
    video file (which must exist)."""
    name, sep, target = text.partition("=")
    if not sep or not name or not target:
        raise InputError(f"--source {text!r}: expected NAME=SOURCE (the calibration's camera name, then a video "
                         "file, a device number or a stream URL), e.g. cam1=videos/cam1.mp4 or cam2=0")
    if target.isdigit():
        return SourceSpec(name, DEVICE, int(target))
    if "://" in target:
        return SourceSpec(name, URL, target)
    if not Path(target).is_file():
        raise InputError(f"--source {name}: video file not found; check the path (a device is a number, a "
                         "stream a URL such as rtsp://host/stream)", path=target)
    return SourceSpec(name, FILE, target)


@dataclass
class Frame:
    """One grey frame (H, W) uint8: the camera's own frame `index`, its `time` on the
    reference clock (s) and when it `arrived` (time.perf_counter())."""

    index: int
    time: float
    arrived: float
    gray: np.ndarray


class SourceReader(threading.Thread):
    """Reads one source into `frames` (a bounded queue) until it ends or `stop` is set.

    `fps` and `offset` the camera's clock (the calibration's); `start` the run's start
    (perf_counter); `pace` the file's delay before frame 0 (its offset shifted by the
    earliest), None to read a file as fast as it is taken; `on_frame(gray)` sees every
    frame read (the session recording). Counters: `read`, `dropped`, `reconnects`;
    `ended` is set when no more frames will come.
    """

    def __init__(self, spec: SourceSpec, fps: float, offset: float, start: float, stop: threading.Event,
                 pace: float | None = None, depth: int = 2, on_frame=None):
        super().__init__(name=f"source {spec.camera}", daemon=True)
        self.spec, self.fps, self.offset, self.clock_start, self.stop, self.pace = spec, fps, offset, start, stop, pace
        self.frames: queue.Queue[Frame] = queue.Queue(maxsize=depth)
        self.on_frame = on_frame
        self.read = self.dropped = self.reconnects = 0
        self.ended = threading.Event()
        self.video: Video | None = Video(spec.target) if spec.kind == FILE else None

    @property
    def size(self) -> tuple[int, int] | None:
        return None if self.video is None else self.video.info.size

    def run(self) -> None:
        try:
            if self.video is not None:
                self._read_file()
            else:
                self._read_stream()
        except Exception:  # a source that fails ends; the others carry on
            log.exception("camera %s: reading %s failed", self.spec.camera, self.spec.target)
        finally:
            self.ended.set()

    def _read_file(self) -> None:
        frames = self.video.frames(gray=True)
        try:
            for index, gray in frames:
                if self.pace is not None:
                    due = self.clock_start + self.pace + index / self.fps
                    while (wait := due - time.perf_counter()) > 0:
                        if self.stop.wait(min(wait, 0.1)):
                            return
                if self.stop.is_set():
                    return
                self._deliver(Frame(index, index / self.fps + self.offset, time.perf_counter(), gray))
        finally:
            frames.close()

    def _read_stream(self) -> None:
        """A device or a stream: frames numbered as they come, timed by their arrival; reopened
        after a failure with a pause that doubles up to `_RECONNECT_S`[1]."""
        index, pause = 0, _RECONNECT_S[0]
        while not self.stop.is_set():
            capture = cv2.VideoCapture(self.spec.target)
            ok = capture.isOpened()
            while ok and not self.stop.is_set():
                ok, image = capture.read()
                if not ok or image is None:
                    break
                pause = _RECONNECT_S[0]
                now = time.perf_counter()
                gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                self._deliver(Frame(index, now - self.clock_start, now, gray))
                index += 1
            capture.release()
            if self.stop.is_set():
                return
            log.warning("camera %s: %s gives no frames; trying again in %.1f s", self.spec.camera,
                        self.spec.target, pause)
            if self.stop.wait(pause):
                return
            pause = min(2 * pause, _RECONNECT_S[1])
            self.reconnects += 1

    def _deliver(self, frame: Frame) -> None:
        """Into the queue; a full queue loses its oldest frame (counted) unless this is a file
        read as fast as it is taken, which waits instead."""
        self.read += 1
        if self.on_frame is not None:
            self.on_frame(frame.gray)
        if self.spec.kind == FILE and self.pace is None:
            while not self.stop.is_set():
                try:
                    self.frames.put(frame, timeout=0.1)
                    return
                except queue.Full:
                    continue
            return
        while True:
            try:
                self.frames.put_nowait(frame)
                return
            except queue.Full:
                try:
                    self.frames.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def take(self, timeout: float = 0.1) -> Frame | None:
        """The next frame, or None when none came within `timeout` s."""
        try:
            return self.frames.get(timeout=timeout)
        except queue.Empty:
            return None

    @property
    def done(self) -> bool:
        """No frame will come any more: the source ended and its queue is empty."""
        return self.ended.is_set() and self.frames.empty()
