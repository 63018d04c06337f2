"""A video a person can check the tracking on: every labelled marker drawn on the frames
of the camera's own video where it was tracked, a ring around it, a dot on its centre and
its name beside it, each marker in its own colour.

Shapes: K labels in a frame.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mocap.core.tracks import Tracks
from mocap.io.video import Video
from mocap.synthetic.encode import video_writer

_SHIFT = 4  # OpenCV drawing with sub-pixel centres: coordinates in 1/16 px


def marker_colours(names) -> dict[str, tuple[int, int, int]]:
    """A saturated BGR colour for each marker name, hues spread around the circle (the
    same names always get the same colours)."""
    names = sorted(set(names))
    hues = (np.arange(len(names)) * 0.618034) % 1.0  # golden-ratio steps: neighbours differ
    hsv = np.stack([np.round(hues * 179), np.full(len(names), 255), np.full(len(names), 255)], -1)
    bgr = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2BGR)[0]
    return {name: tuple(int(c) for c in colour) for name, colour in zip(names, bgr)}


def draw_labels(image: np.ndarray, xy: np.ndarray, names, colours: dict, ring_px: float = 9.0) -> np.ndarray:
    """Draw labels (K, 2) px with their marker `names` (K,) on a BGR image (in place; returned):
    a ring of `ring_px`, a dot of 2 px radius on the centre and the name, in the marker's colour."""
    scale = 1 << _SHIFT
    for (x, y), name in zip(np.asarray(xy, dtype=float), names):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        colour = colours[name]
        centre = (int(round(x * scale)), int(round(y * scale)))
        cv2.circle(image, centre, int(ring_px * scale), colour, 1, cv2.LINE_AA, _SHIFT)
        cv2.circle(image, centre, 2 * scale, colour, -1, cv2.LINE_AA, _SHIFT)
        cv2.putText(image, str(name), (int(x + ring_px + 2), int(y - ring_px)), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colour, 1, cv2.LINE_AA)
    return image


def write_preview(video: Video, tracks: Tracks, out: str | Path, start: int = 0, stop: int | None = None,
                  codec: str = "h264") -> int:
    """Write the video's frames `start`..`stop` with the tracks' labels drawn on them to
    `out` (H.264 by default); returns the number of frames written."""
    colours = marker_colours(tracks.marker)
    order = np.argsort(tracks.frame, kind="stable")
    frames, first = np.unique(tracks.frame[order], return_index=True)
    bounds = dict(zip(frames.tolist(), zip(first, np.r_[first[1:], len(order)])))
    count = 0
    with video_writer(out, video.info.size, video.info.fps or 30.0, codec) as write:
        for index, image in video.frames(gray=False, start=start, stop=stop):
            rows = order[slice(*bounds[index])] if index in bounds else order[:0]
            draw_labels(image, tracks.xy[rows], tracks.marker[rows], colours)
            cv2.putText(image, f"frame {index}  {len(rows)} labels", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                        (255, 255, 255), 1, cv2.LINE_AA)
            write(image)
            count += 1
    return count
