"""A starting base pose per frame for a base that moves every frame (a hand-held board, a
bouncing or walking machine): each frame's base markers as its best camera sees them,
solved by OpenCV's PnP. Shapes: C cameras, K frames, M markers."""

from __future__ import annotations

import cv2
import numpy as np

from mocap.core.camera import Camera
from mocap.core.geometry import matrix_to_rotvec, rotvec_to_matrix
from mocap.core.machine import Machine


def board_poses(machine: Machine, cameras: list[Camera], pixels: np.ndarray) -> np.ndarray:
    """(K, 6) ``world_from_base`` (rotation vector, translation m) for pixels (C, K, M, 2):
    from the camera that sees most of the base's markers in that frame (at least 4), the
    identity where none does."""
    fixed = ~machine.moves[:, machine.marker_links].any(0) if machine.n_joints else np.ones(len(machine.marker_names), bool)
    local = machine.markers(np.zeros((1, machine.n_joints)))[0, fixed]  # (B, 3) in the base frame
    seen = np.isfinite(pixels[:, :, fixed, 0])  # (C, K, B)
    counts = seen.sum(-1)
    out = np.zeros((pixels.shape[1], 6))
    for k in np.nonzero(counts.max(0) >= 4)[0]:
        c = int(np.argmax(counts[:, k]))
        camera, mask = cameras[c], seen[c, k]
        ok, rvec, tvec = cv2.solvePnP(local[mask], pixels[c, k][fixed][mask], camera.matrix, camera.distortion)
        if not ok:
            continue
        cam_from_base = rotvec_to_matrix(rvec.ravel()), tvec.ravel()
        world_from_cam = camera.cam_from_world.rotation.T, -camera.cam_from_world.rotation.T @ camera.cam_from_world.translation
        rotation = world_from_cam[0] @ cam_from_base[0]
        out[k] = np.r_[matrix_to_rotvec(rotation), world_from_cam[0] @ cam_from_base[1] + world_from_cam[1]]
    return out
