"""Reading videos frame by frame (OpenCV's VideoCapture), grey or colour.

A video that cannot be opened is an InputError. A video that breaks part-way (a corrupt or
truncated file) stops the iteration with a warning naming the frame where it broke; the
frames before it have been delivered, so a caller keeps its results up to there.
"""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2

from mocap.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VideoInfo:
    """`size` (width, height) px, `fps` frames per second, `frame_count` as the container
    states it (0 if unknown)."""

    path: Path
    size: tuple[int, int]
    fps: float
    frame_count: int


class Video:
    """A video file: `info`, and iteration over ``(frame_index, image)`` pairs.

    ``Video(path).frames(gray=True)`` yields (H, W) uint8 images; with ``gray=False`` (H, W, 3)
    BGR. After iterating, `broken_at` is the frame index where reading failed before the
    stated end, or None.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError("video file not found; check the path", path=self.path)
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise InputError("cannot open the video (unknown format or corrupt file)", path=self.path)
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        count = max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)
        capture.release()
        if width <= 0 or height <= 0:
            raise InputError("the video has no readable frames", path=self.path)
        self.info = VideoInfo(self.path, (width, height), fps, count)
        self.broken_at: int | None = None

    def frames(self, gray: bool = True, start: int = 0, stop: int | None = None, prefetch: int = 0):
        """Yield (index, image) from frame `start` up to `stop` (exclusive; None: the end).

        With `prefetch` > 0, a background thread decodes up to that many frames ahead, so
        that decoding overlaps the caller's work on the previous frames.
        """
        if prefetch <= 0:
            yield from self._read(gray, start, stop)
            return
        buffer: queue.Queue = queue.Queue(maxsize=prefetch)
        done = object()
        stopping = threading.Event()

        def produce() -> None:
            try:
                for item in self._read(gray, start, stop):
                    while not stopping.is_set():
                        try:
                            buffer.put(item, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                    if stopping.is_set():
                        return
            finally:
                buffer.put(done)

        thread = threading.Thread(target=produce, name=f"decode {self.path.name}", daemon=True)
        thread.start()
        try:
            while (item := buffer.get()) is not done:
                yield item
        finally:
            stopping.set()
            while thread.is_alive():
                try:
                    buffer.get(timeout=0.1)
                except queue.Empty:
                    pass
            thread.join()

    def _read(self, gray: bool, start: int, stop: int | None):
        capture = cv2.VideoCapture(str(self.path))
        self.broken_at = None
        try:
            if start > 0:
                capture.set(cv2.CAP_PROP_POS_FRAMES, start)
            index = start
            while stop is None or index < stop:
                ok, image = capture.read()
                if not ok or image is None:
                    expected = self.info.frame_count if stop is None else min(stop, self.info.frame_count)
                    if index < expected:
                        self.broken_at = index
                        log.warning(
                            "%s: the video broke at frame %d of %d (corrupt or truncated); "
                            "frames before it are kept",
                            self.path,
                            index,
                            self.info.frame_count,
                        )
                    return
                if gray:
                    image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
                yield index, image
                index += 1
        finally:
            capture.release()

