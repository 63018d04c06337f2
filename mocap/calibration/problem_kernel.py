"""The calibration problem's residuals and Jacobian for all observations at once, compiled
(numba): `problem.Problem`'s evaluation, one pass over the observations with the lens model
of `core.camera_kernel.project_point`."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mocap.core.camera_kernel import project_point

BEHIND_PX = 1e4  # the residual of a marker behind its camera (finite, so that the solver can start)


@njit(cache=True, nogil=True)
def evaluate(camera, marker, group, xy, poses, marker_links, positions, joint_links, axes, revolute, moves,
             rotations, d_rotations, translations, matrices, distortions, camera_start, joint_start,
             terms, fit_principal_point, offset_start, residuals, jac):  # pragma: no cover - compiled
    """Residuals (N, 2) and Jacobian rows (2N, P) of N observations, written into `residuals`
    and `jac` (zeros on entry; the rows of a marker behind its camera stay zero).

    Per observation: camera (N,), marker (N,), group (N,) (its joint values' row in `poses`),
    pixel xy (N, 2). The machine: poses (G, L, 4, 4) world-from-link per group, marker_links
    (M,), positions (M, 3) in their links (the offsets added), joint_links (J,), axes (J, 3) in
    the joints' links, revolute (J,), moves (J, M) whether joint j moves marker m. Per
    camera: rotation (C, 3, 3) and its derivative d_rotations (C, 3, 9) (d R.flat / d rvec, as
    cv2.Rodrigues), translations (C, 3), matrices (C, 3, 3), distortions (C, 5), its block's
    first column camera_start (C,); joint_start (G,) the first column of each group's joints;
    terms (T,) the distortion coefficients fitted; offset_start the first offset column, or
    -1 without offsets.
    """
    n_joints = len(joint_links)
    p_world = np.empty(3)
    p_cam = np.empty(3)
    uv = np.empty(2)
    d_cam = np.empty((2, 3))  # d uv / d camera-frame point
    d_world = np.empty((2, 3))  # d uv / d world point
    for i in range(len(camera)):
        c, m, g = camera[i], marker[i], group[i]
        link = poses[g, marker_links[m]]
        for a in range(3):
            p_world[a] = (link[a, 0] * positions[m, 0] + link[a, 1] * positions[m, 1]
                          + link[a, 2] * positions[m, 2]) + link[a, 3]
        rotation = rotations[c]
        for a in range(3):
            p_cam[a] = (rotation[a, 0] * p_world[0] + rotation[a, 1] * p_world[1]
                        + rotation[a, 2] * p_world[2]) + translations[c, a]
        seen = project_point(p_cam, matrices[c], distortions[c], uv, d_cam)
        if not seen or not math.isfinite(uv[0]):
            residuals[i, 0] = residuals[i, 1] = BEHIND_PX
            continue
        residuals[i, 0] = uv[0] - xy[i, 0]
        residuals[i, 1] = uv[1] - xy[i, 1]
        start = camera_start[c]
        for r in range(2):
            row = 2 * i + r
            # rotation: d p_cam_a / d rvec_k = sum_j dR_aj / d rvec_k p_world_j
            for k in range(3):
                total = 0.0
                for a in range(3):
                    d_p = (d_rotations[c, k, 3 * a] * p_world[0] + d_rotations[c, k, 3 * a + 1] * p_world[1]
                           + d_rotations[c, k, 3 * a + 2] * p_world[2])
                    total += d_cam[r, a] * d_p
                jac[row, start + k] = total
            for a in range(3):
                jac[row, start + 3 + a] = d_cam[r, a]
            focal = matrices[c, 0, 0]
            jac[row, start + 6] = (uv[r] - matrices[c, r, 2]) / focal
            for a in range(3):
                d_world[r, a] = d_cam[r, 0] * rotation[0, a] + d_cam[r, 1] * rotation[1, a] + d_cam[r, 2] * rotation[2, a]
        k = start + 7
        if fit_principal_point:
            jac[2 * i, k] = 1.0
            jac[2 * i + 1, k + 1] = 1.0
            k += 2
        if len(terms):
            x = p_cam[0] / p_cam[2]
            y = p_cam[1] / p_cam[2]
            r2 = x * x + y * y
            focal = matrices[c, 0, 0]
            for term in terms:
                if term == 0:
                    dx, dy = x * r2, y * r2
                elif term == 1:
                    dx, dy = x * r2 * r2, y * r2 * r2
                elif term == 2:
                    dx, dy = 2 * x * y, r2 + 2 * y * y
                elif term == 3:
                    dx, dy = r2 + 2 * x * x, 2 * x * y
                else:
                    dx, dy = x * r2**3, y * r2**3
                jac[2 * i, k] = focal * dx
                jac[2 * i + 1, k] = focal * dy
                k += 1
        # the joints: revolute j moves the marker by a_j x (p - o_j), prismatic by a_j
        for j in range(n_joints):
            if not moves[j, m]:
                continue
            o = poses[g, joint_links[j]]
            ax = o[0, 0] * axes[j, 0] + o[0, 1] * axes[j, 1] + o[0, 2] * axes[j, 2]
            ay = o[1, 0] * axes[j, 0] + o[1, 1] * axes[j, 1] + o[1, 2] * axes[j, 2]
            az = o[2, 0] * axes[j, 0] + o[2, 1] * axes[j, 1] + o[2, 2] * axes[j, 2]
            if revolute[j]:
                lx, ly, lz = p_world[0] - o[0, 3], p_world[1] - o[1, 3], p_world[2] - o[2, 3]
                dx, dy, dz = ay * lz - az * ly, az * lx - ax * lz, ax * ly - ay * lx
            else:
                dx, dy, dz = ax, ay, az
            column = joint_start[g] + j
            for r in range(2):
                jac[2 * i + r, column] = d_world[r, 0] * dx + d_world[r, 1] * dy + d_world[r, 2] * dz
        if offset_start >= 0:  # d world / d offset: the marker's link's rotation
            column = offset_start + 3 * m
            for r in range(2):
                for a in range(3):
                    jac[2 * i + r, column + a] = (d_world[r, 0] * link[0, a] + d_world[r, 1] * link[1, a]
                                                  + d_world[r, 2] * link[2, a])
