"""The aniposelib side of bench_calibration.py, run in aniposelib's own environment.

    python aniposelib_load.py CAMERAS.toml POINTS.npy OUT.json

Loads the calibration file with `aniposelib.cameras.CameraGroup.load` (as a user of
aniposelib would) and writes, per camera in the group's order, its name, size, matrix,
distortion, rotation and translation as aniposelib read them, and the pixels of the world
points (N, 3) projected by aniposelib's own `Camera.project`.
"""

import json
import sys

import numpy as np
from aniposelib.cameras import CameraGroup


def main(calibration: str, points: str, target: str) -> None:
    xyz = np.load(points)
    group = CameraGroup.load(calibration)
    cameras = []
    for camera in group.cameras:
        pixels = np.asarray(camera.project(xyz)).reshape(-1, 2)
        cameras.append(
            {
                "name": camera.get_name(),
                "size": [int(v) for v in camera.get_size()],
                "matrix": np.asarray(camera.get_camera_matrix()).tolist(),
                "distortion": np.asarray(camera.get_distortions()).reshape(-1).tolist(),
                "rotation": np.asarray(camera.get_rotation()).reshape(-1).tolist(),
                "translation": np.asarray(camera.get_translation()).reshape(-1).tolist(),
                "pixels": pixels.tolist(),
            }
        )
    with open(target, "w", encoding="utf-8") as out:
        json.dump({"cameras": cameras}, out)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3])
