"""OpenCV's predefined tag dictionaries (ArUco, AprilTag), by name: what a machine model's
`[tags] dictionary` names, checked on load and used by the detector."""

from __future__ import annotations

import cv2


def tag_dictionary(name: str):
    """An OpenCV predefined dictionary by name, e.g. 'DICT_4X4_50' or 'DICT_APRILTAG_36h11'."""
    key = name if name.startswith("DICT_") else f"DICT_{name}"
    if not hasattr(cv2.aruco, key.upper()) and not hasattr(cv2.aruco, key):
        known = sorted(k[5:] for k in dir(cv2.aruco) if k.startswith("DICT_"))
        raise ValueError(f"unknown tag dictionary {name!r}; known: {', '.join(known)}")
    value = getattr(cv2.aruco, key, None)
    value = getattr(cv2.aruco, key.upper()) if value is None else value
    return cv2.aruco.getPredefinedDictionary(value)
