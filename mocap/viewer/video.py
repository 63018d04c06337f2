"""A session video as a Rerun video asset: the file's own H.264 stream, not re-encoded.

Rerun plays H.264 in an MP4 container; any other codec is reported and left out of the
replay (`load_video` returns None with the reason in a log warning).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import av
import cv2
import numpy as np
import rerun as rr

from mocap.errors import InputError

log = logging.getLogger(__name__)

PLAYABLE_CODECS = ("h264",)


@dataclass(frozen=True)
class Video:
    """A video asset and its frames' presentation times, ns from the video's start (N,)."""

    path: Path
    asset: rr.AssetVideo
    timestamps_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_ns)


def video_codec(path: Path) -> str | None:
    """The codec name of the file's first video stream, or None if it has none or is unreadable."""
    try:
        with av.open(str(path)) as container:
            streams = container.streams.video
            return streams[0].codec_context.name if streams else None
    except (av.FFmpegError, OSError):
        return None


def load_video(path: str | Path, camera: str) -> Video | None:
    """The camera's video as an asset, or None (with a warning) if it cannot be replayed."""
    path = Path(path)
    if not path.is_file():
        log.warning("camera %s: no video at %s; replaying without it", camera, path)
        return None
    codec = video_codec(path)
    if codec not in PLAYABLE_CODECS:
        found = "no readable video stream" if codec is None else f"codec {codec}"
        log.warning(
            "camera %s: %s has %s, the replay needs H.264 in MP4 (re-encode it, e.g. ffmpeg "
            "-i IN -c:v libx264 OUT.mp4); replaying without it",
            camera,
            path,
            found,
        )
        return None
    try:
        asset = rr.AssetVideo(path=path, media_type="video/mp4")
        timestamps = asset.read_frame_timestamps_nanos()
    except RuntimeError as exc:  # the MP4 reader's own word on a cut or corrupt file ("MP4 error: ...")
        raise InputError(f"camera {camera}: the MP4 cannot be read to its end ({_one_line(exc)}): a truncated or "
                         "corrupt file; copy it again, or leave out its --video", path=path) from None
    return Video(path, asset, timestamps)


def first_frame_jpeg(path: str | Path, quality: int = 80) -> bytes | None:
    """The video's first frame as JPEG bytes (None if it cannot be decoded): shown at once
    while a viewer still loads and decodes the video itself."""
    try:
        with av.open(str(path)) as container:
            frame = next(container.decode(video=0), None)
            if frame is None:
                return None
            rgb = frame.to_ndarray(format="rgb24")
    except (av.FFmpegError, OSError):
        return None
    ok, data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    return data.tobytes() if ok else None


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())
