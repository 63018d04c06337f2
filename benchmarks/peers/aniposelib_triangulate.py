"""The aniposelib side of bench_reconstruct.py, run in aniposelib's own environment.

    python aniposelib_triangulate.py IN.npz OUT.npz

IN holds `matrix` (C, 3, 3), `distortion` (C, 5), `rotation` (C, 3) Rodrigues world ->
camera, `translation` (C, 3), `size` (C, 2) and `pixels` (C, N, 2) NaN where not seen;
`method` is "triangulate" or "triangulate_ransac". OUT gets `xyz` (N, 3) and `seconds`
(the CPU time of the triangulation call alone, after one warm-up call that compiles
aniposelib's numba functions).
"""

import sys
import time

import numpy as np
from aniposelib.cameras import Camera, CameraGroup


def main(source: str, target: str) -> None:
    data = np.load(source)
    cameras = [
        Camera(
            name=f"cam{k}",
            size=data["size"][k].tolist(),
            matrix=data["matrix"][k],
            dist=data["distortion"][k],
            rvec=data["rotation"][k],
            tvec=data["translation"][k],
        )
        for k in range(len(data["matrix"]))
    ]
    group = CameraGroup(cameras)
    method = str(data["method"])
    pixels = data["pixels"]
    call = group.triangulate if method == "triangulate" else group.triangulate_ransac
    call(pixels[:, :20])  # warm-up: numba compilation
    start = time.process_time()
    out = call(pixels)
    seconds = time.process_time() - start
    xyz = out if method == "triangulate" else out[0]
    np.savez(target, xyz=xyz, seconds=seconds)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
