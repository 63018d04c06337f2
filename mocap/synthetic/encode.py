"""Writing rendered frames to video files OpenCV can read: H.264 through PyAV, or mp4v
through OpenCV's VideoWriter. A video is written beside its target and renamed when whole."""

from __future__ import annotations

import contextlib
import os
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

CODECS = ("h264", "mp4v")


def frame_rate(fps: float) -> Fraction:
    """NTSC rates as exact fractions (29.97 -> 30000/1001), others as given."""
    for base in (24, 30, 60):
        if abs(fps - base * 1000 / 1001) < 1e-3:
            return Fraction(base * 1000, 1001)
    return Fraction(fps).limit_denominator(1001)


@contextlib.contextmanager
def video_writer(path: str | Path, size: tuple[int, int], fps: float, codec: str = "h264", threads: int = 0,
                 crf: int = 23):
    """Yield ``write(image)`` for BGR uint8 images (H, W, 3); the file appears when done.

    `threads` is the H.264 encoder's thread count (0: automatic), `crf` its quality (0
    lossless, 23 default, 35 and up heavy compression). The video is written to
    a hidden ``.NAME.partial.mp4`` beside `path` (the extension tells OpenCV the container)
    and renamed onto `path` when whole; removed on an error.
    """
    if codec not in CODECS:
        raise ValueError(f"codec must be one of {CODECS}, got {codec!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.partial.mp4")
    try:
        if codec == "mp4v":
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size)
            try:
                yield writer.write
            finally:
                writer.release()
        else:
            container = av.open(str(tmp), "w", format="mp4")
            try:
                stream = container.add_stream("libx264", rate=frame_rate(fps))
                stream.width, stream.height = size
                stream.pix_fmt = "yuv420p"
                stream.thread_count = threads
                stream.options = {"preset": "ultrafast", "crf": str(int(crf))}

                def write(image: np.ndarray) -> None:
                    for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                        container.mux(packet)

                yield write
                for packet in stream.encode():
                    container.mux(packet)
            finally:
                container.close()
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
