"""Reading videos frame by frame: grey from the decoder's luma plane (PyAV), colour
through OpenCV's VideoCapture; the video's size, rate and frame count from OpenCV.

A video that cannot be opened (not a video, a still image renamed, a truncated file without
its index) is an InputError. A video that breaks part-way (a corrupt or truncated file)
stops the iteration and sets `broken_at`, the frame where it broke; the frames before it
have been delivered, so a caller keeps its results up to there or refuses them.
"""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np

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
        probe_video(self.path)
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
        if gray:
            yield from self._read_luma(start, stop)
            return
        capture = cv2.VideoCapture(str(self.path))
        self.broken_at = None
        try:
            if start > 0:
                capture.set(cv2.CAP_PROP_POS_FRAMES, start)
            index = start
            while stop is None or index < stop:
                ok, image = capture.read()
                if not ok or image is None:
                    self._check_end(index, stop)
                    return
                yield index, image
                index += 1
        finally:
            capture.release()

    def _read_luma(self, start: int, stop: int | None):
        """Grey frames straight from the decoder's luma plane (PyAV, one decoding thread): no
        conversion to colour and back. Limited-range luma (16-235) is stretched to 0-255,
        as OpenCV's grey conversion of the decoded colours gives."""
        self.broken_at = None
        index = 0
        try:
            with av.open(str(self.path)) as container:
                stream = container.streams.video[0]
                # one decoding thread: with the tracker on the other core, more only compete
                stream.codec_context.thread_count = 1
                for frame in container.decode(stream):
                    if stop is not None and index >= stop:
                        return
                    if index >= start:
                        yield index, _luma(frame)
                    index += 1
        except av.error.FFmpegError:
            pass
        self._check_end(index, stop)

    def _check_end(self, index: int, stop: int | None) -> None:
        """Reading stopped at frame `index`: a warning and `broken_at` if that is before the end."""
        expected = self.info.frame_count if stop is None else min(stop, self.info.frame_count)
        if index < expected:
            self.broken_at = index
            log.info(  # the caller reports it, once
                "%s: the video broke at frame %d of %d (corrupt or truncated); frames before it are kept",
                self.path,
                index,
                self.info.frame_count,
            )


def probe_video(path: Path) -> None:
    """Refuse a file the video library cannot open or that holds no video: a still image
    renamed .mp4, a truncated file without its index, a text file."""
    try:
        with av.open(str(path)) as container:
            form = container.format.name
            streams = container.streams.video
            codec = streams[0].codec_context.name if streams else None
    except (av.error.FFmpegError, IndexError, ValueError, OSError) as exc:
        reason = getattr(exc, "strerror", None) or "unknown format"
        raise InputError(f"cannot open the video ({reason}): not a video, or a truncated or corrupt file",
                         path=path) from None
    if codec is None:
        raise InputError(f"holds no readable video stream (a {form} file, truncated or corrupt?); give the camera's whole video", path=path)
    if form.endswith("_pipe") or form in ("image2", "png", "gif", "apng", "webp"):
        raise InputError(f"is a still image ({codec}), not a video; give the camera's video", path=path)


_STRETCH = 255 / 219  # limited-range luma (16-235) to full (0-255): round((v - 16) * 255 / 219), saturated


def full_range(luma: np.ndarray) -> np.ndarray:
    """Limited-range luma (H, W) uint8 stretched to full range, a new contiguous image. One
    multiply-add a pixel (`cv2.addWeighted`, the second image weighted 0; float32 lands at
    least 1/438 from a rounding tie, so every level maps as the exact formula does) costs
    about half of a table lookup (`cv2.LUT`) on a 1080p frame."""
    return cv2.addWeighted(luma, _STRETCH, luma, 0.0, -16 * _STRETCH, dtype=cv2.CV_8U)


def _luma(frame) -> np.ndarray:
    """A decoded frame's grey image (H, W) uint8: its luma plane for YUV formats (stretched
    from limited range), else the frame converted to grey."""
    name = frame.format.name
    if not (name.startswith("yuv") or name in ("nv12", "nv21", "gray")):
        return frame.to_ndarray(format="gray")
    plane = frame.planes[0]
    luma = np.frombuffer(plane, np.uint8).reshape(plane.height, plane.line_size)[:, : plane.width]
    full = name.startswith("yuvj") or name == "gray" or getattr(frame, "color_range", 1) == 2
    return np.ascontiguousarray(luma) if full else full_range(luma)
