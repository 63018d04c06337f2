"""The calibration problem's residuals and Jacobian for all observations at once, compiled
(numba): `problem.Problem`'s evaluation, one pass over the observations with the lens model
of `core.camera_kernel.project_point`."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mocap.core.camera_kernel import project_point
from mocap.reconstruct.kinkernel import world_frame

BEHIND_PX = 1e4  # the residual of a marker behind its camera (finite, so that the solver can start)


@njit(cache=True, nogil=True)
def rodrigues(r, rotation, jac):
    """cv2.Rodrigues of a rotation vector r (3,): the rotation matrix into `rotation` (3, 3)
    and d R.flat / d r into `jac` (3, 9), by OpenCV's formula."""
    theta = math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
    if theta < 2.220446049250313e-16:  # DBL_EPSILON: the identity, d R / d r_k = [e_k]x
        rotation[:] = 0.0
        jac[:] = 0.0
        for a in range(3):
            rotation[a, a] = 1.0
        jac[0, 5], jac[0, 7] = -1.0, 1.0
        jac[1, 2], jac[1, 6] = 1.0, -1.0
        jac[2, 1], jac[2, 3] = -1.0, 1.0
        return
    c, s = math.cos(theta), math.sin(theta)
    c1 = 1.0 - c
    itheta = 1.0 / theta
    u = (r[0] * itheta, r[1] * itheta, r[2] * itheta)
    rrt = np.empty(9)
    r_x = np.array([0.0, -u[2], u[1], u[2], 0.0, -u[0], -u[1], u[0], 0.0])
    for a in range(3):
        for b in range(3):
            rrt[3 * a + b] = u[a] * u[b]
            rotation[a, b] = (c * (1.0 if a == b else 0.0) + c1 * rrt[3 * a + b]) + s * r_x[3 * a + b]
    drrt = np.empty((3, 9))
    d_r_x = np.zeros((3, 9))
    d_r_x[0, 5], d_r_x[0, 7] = -1.0, 1.0
    d_r_x[1, 2], d_r_x[1, 6] = 1.0, -1.0
    d_r_x[2, 1], d_r_x[2, 3] = -1.0, 1.0
    for i in range(3):  # d (u u^T) / d u_i, the flat (3, 3) e_i u^T + u e_i^T
        for a in range(3):
            for b in range(3):
                drrt[i, 3 * a + b] = (u[b] if a == i else 0.0) + (u[a] if b == i else 0.0)
    for i in range(3):
        a0, a1, a2 = -s * u[i], (s - 2 * c1 * itheta) * u[i], c1 * itheta
        a3, a4 = (c - s * itheta) * u[i], s * itheta
        for k in range(9):
            identity = 1.0 if k % 4 == 0 else 0.0
            jac[i, k] = a0 * identity + a1 * rrt[k] + a2 * drrt[i, k] + a3 * r_x[k] + a4 * d_r_x[i, k]


@njit(cache=True, nogil=True)
def evaluate(x, camera, marker, group, xy, parents, joint_links, at_zero, first, second, revolute, axes,
             n_links, marker_links, positions, moves, camera_start, joint_start, fitted, base_matrices,
             base_distortions, terms, fit_principal_point, offset_start, prior, residuals, jac):
    """Residuals (2N + 3M,) and Jacobian (2N + 3M, P) at the parameter vector x (P,), written
    into `residuals` and `jac` (zeros on entry; the rows of a marker behind its camera stay zero).

    Per observation: camera (N,), marker (N,), group (N,) (the camera with per-camera joints,
    else 0), pixel xy (N, 2). The machine: its joints' parent links, links, poses at zero
    (J, 4, 4), motion terms A and B (J, 4, 4) (`Machine._motion_terms`), revolute (J,) and axes (J, 3) in
    their links; n_links; the markers' links (M,) and positions (M, 3) in them, moves (J, M)
    whether joint j moves marker m. The layout: each camera's first column (C,), each group's
    first joint column (G,), fitted (C,) whether its intrinsics are (else `base_matrices` (C, 3,
    3) and `base_distortions` (C, 5) hold), the distortion terms fitted (T,), the principal
    point's; offset_start the first offset column (-1 without offsets), prior (3M,) the prior
    rows' weights.
    """
    n = len(camera)
    n_cameras, n_groups, n_joints = len(camera_start), len(joint_start), len(joint_links)
    # the cameras: rotation (cv2.Rodrigues), translation, intrinsics
    rotations = np.empty((n_cameras, 3, 3))
    d_rotations = np.empty((n_cameras, 3, 9))
    matrices = base_matrices.copy()
    distortions = base_distortions.copy()
    for c in range(n_cameras):
        start = camera_start[c]
        rodrigues(x[start : start + 3], rotations[c], d_rotations[c])
        if fitted[c]:
            matrices[c, 0, 0] = matrices[c, 1, 1] = x[start + 6]
            matrices[c, 0, 1] = 0.0
            k = start + 7
            if fit_principal_point:
                matrices[c, 0, 2], matrices[c, 1, 2] = x[start + 7], x[start + 8]
                k += 2
            for t in range(len(terms)):
                distortions[c, terms[t]] = x[k + t]
    # the markers (moved by their offsets) in the world and their derivatives by the joints, per group
    moved = positions.copy()
    if offset_start >= 0:
        for m in range(len(positions)):
            for a in range(3):
                moved[m, a] = positions[m, a] + x[offset_start + 3 * m + a]
    poses = np.empty((n_groups, n_links, 4, 4))
    world = np.empty((n_groups, len(positions), 3))
    d_world_d_q = np.empty((n_groups, len(positions), 3, n_joints))
    motion, local, ax = np.empty((4, 4)), np.empty((4, 4)), np.empty(3)
    fixed_rotation, fixed_translation = np.empty((0, 3)), np.empty(0)
    for g in range(n_groups):
        world_frame(x[joint_start[g] : joint_start[g] + n_joints], fixed_rotation, fixed_translation, first, second,
                    revolute, parents, at_zero, joint_links, axes, marker_links, moved, moves, world[g],
                    d_world_d_q[g], poses[g], motion, local, ax)
    p_world = np.empty(3)
    p_cam = np.empty(3)
    uv = np.empty(2)
    d_cam = np.empty((2, 3))  # d uv / d camera-frame point
    d_world = np.empty((2, 3))  # d uv / d world point
    for i in range(n):
        c, m, g = camera[i], marker[i], group[i]
        link = poses[g, marker_links[m]]
        for a in range(3):
            p_world[a] = world[g, m, a]
        rotation = rotations[c]
        start = camera_start[c]
        for a in range(3):
            p_cam[a] = (rotation[a, 0] * p_world[0] + rotation[a, 1] * p_world[1]
                        + rotation[a, 2] * p_world[2]) + x[start + 3 + a]
        seen = project_point(p_cam, matrices[c], distortions[c], uv, d_cam)
        if not seen or not math.isfinite(uv[0]):
            residuals[2 * i] = residuals[2 * i + 1] = BEHIND_PX
            continue
        residuals[2 * i] = uv[0] - xy[i, 0]
        residuals[2 * i + 1] = uv[1] - xy[i, 1]
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
            jac[row, start + 6] = (uv[r] - matrices[c, r, 2]) / matrices[c, 0, 0]
            for a in range(3):
                d_world[r, a] = (d_cam[r, 0] * rotation[0, a] + d_cam[r, 1] * rotation[1, a]
                                 + d_cam[r, 2] * rotation[2, a])
        k = start + 7
        if fit_principal_point:
            jac[2 * i, k] = 1.0
            jac[2 * i + 1, k + 1] = 1.0
            k += 2
        if len(terms):
            u = p_cam[0] / p_cam[2]
            v = p_cam[1] / p_cam[2]
            r2 = u * u + v * v
            focal = matrices[c, 0, 0]
            for term in terms:
                if term == 0:
                    du, dv = u * r2, v * r2
                elif term == 1:
                    du, dv = u * r2 * r2, v * r2 * r2
                elif term == 2:
                    du, dv = 2 * u * v, r2 + 2 * v * v
                elif term == 3:
                    du, dv = r2 + 2 * u * u, 2 * u * v
                else:
                    du, dv = u * r2**3, v * r2**3
                jac[2 * i, k] = focal * du
                jac[2 * i + 1, k] = focal * dv
                k += 1
        # the joints (`world_frame`: revolute j moves the marker by a_j x (p - o_j), prismatic by a_j)
        for j in range(n_joints):
            if not moves[j, m]:
                continue
            column = joint_start[g] + j
            d_q = d_world_d_q[g, m, :, j]
            for r in range(2):
                jac[2 * i + r, column] = d_world[r, 0] * d_q[0] + d_world[r, 1] * d_q[1] + d_world[r, 2] * d_q[2]
        if offset_start >= 0:  # d world / d offset: the marker's link's rotation
            column = offset_start + 3 * m
            for r in range(2):
                for a in range(3):
                    jac[2 * i + r, column + a] = (d_world[r, 0] * link[0, a] + d_world[r, 1] * link[1, a]
                                                  + d_world[r, 2] * link[2, a])
    for k in range(len(prior)):  # the offsets' prior rows
        residuals[2 * n + k] = prior[k] * x[offset_start + k]
        jac[2 * n + k, offset_start + k] = prior[k]
