"""The kinematic fit's inner loop, compiled (numba): for every frame at once, the marker
pixels' robust residuals and the frame's normal equations, without the Jacobian of all
observations in memory.

Per observation (camera c, marker m) of frame f: the marker's camera-frame position, its
pixel through the OpenCV lens (mocap.camera.project_cam) and the pixel's derivative by the
frame's parameters (d pixel / d camera point · R_c · d world / d parameters). Residuals are
divided by the model-tolerance weight (kinmodel.KinematicModel), robustified per
observation (2-D length: Huber, Cauchy or none) and summed into JᵀWJ (P, P), JᵀWr (P,)
and the robust cost. An observation not seen (NaN pixel) or behind the camera contributes
nothing. Shapes: F frames, C cameras, M markers, P parameters, N = C * M * 2.
"""

from __future__ import annotations

import numpy as np
from numba import njit

LOSS_CODES = {"huber": 0, "cauchy": 1, "linear": 2}


@njit(cache=True, nogil=True)
def _robust(r2: float, loss: int, scale: float):
    """(weight, rho) of one observation's squared residual length."""
    if loss == 0:
        e = np.sqrt(r2)
        if e <= scale:
            return 1.0, r2
        return scale / e, 2.0 * scale * e - scale * scale
    if loss == 1:
        s2 = scale * scale
        return 1.0 / (1.0 + r2 / s2), s2 * np.log1p(r2 / s2)
    return 1.0, r2


@njit(cache=True, nogil=True)
def normal_equations(markers, d_world, pixels, rotation, translation, intrinsics, distortion,
                     marker_sd, noise_px, loss, scale, residual, weight, cost, hessian, gradient):
    """Fill residual (F, N), weight (F, N), cost (F,), hessian (F, P, P), gradient (F, P).

    markers (F, M, 3) world; d_world (F, M, 3, P); pixels (F, C, M, 2); rotation (C, 3, 3)
    and translation (C, 3) cam_from_world; intrinsics (C, 5) fx, skew, cx, fy, cy;
    distortion (C, 5) k1 k2 p1 p2 k3; marker_sd (M,) m, empty for an exact model;
    noise_px the pixel SD the tolerance is weighed against; loss a LOSS_CODES value.
    """
    n_frames, n_markers = markers.shape[0], markers.shape[1]
    n_cams, n_params = rotation.shape[0], d_world.shape[3]
    tolerant = marker_sd.shape[0] > 0
    a = np.empty((2, 3))
    row = np.empty((2, n_params))
    for f in range(n_frames):
        for p in range(n_params):
            gradient[f, p] = 0.0
            for q in range(n_params):
                hessian[f, p, q] = 0.0
        total = 0.0
        for c in range(n_cams):
            fx, skew, cx, fy, cy = intrinsics[c, 0], intrinsics[c, 1], intrinsics[c, 2], intrinsics[c, 3], intrinsics[c, 4]
            k1, k2, p1, p2, k3 = distortion[c, 0], distortion[c, 1], distortion[c, 2], distortion[c, 3], distortion[c, 4]
            for m in range(n_markers):
                i = 2 * (c * n_markers + m)
                residual[f, i] = 0.0
                residual[f, i + 1] = 0.0
                weight[f, i] = 1.0
                weight[f, i + 1] = 1.0
                u_obs, v_obs = pixels[f, c, m, 0], pixels[f, c, m, 1]
                if not np.isfinite(u_obs):
                    continue
                wx, wy, wz = markers[f, m, 0], markers[f, m, 1], markers[f, m, 2]
                px = rotation[c, 0, 0] * wx + rotation[c, 0, 1] * wy + rotation[c, 0, 2] * wz + translation[c, 0]
                py = rotation[c, 1, 0] * wx + rotation[c, 1, 1] * wy + rotation[c, 1, 2] * wz + translation[c, 1]
                pz = rotation[c, 2, 0] * wx + rotation[c, 2, 1] * wy + rotation[c, 2, 2] * wz + translation[c, 2]
                if not pz > 0.0:
                    continue
                inv_z = 1.0 / pz
                x, y = px * inv_z, py * inv_z
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
                yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
                dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
                dxd_dx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
                dxd_dy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
                dyd_dx = dxd_dy
                dyd_dy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
                du_dx, du_dy = fx * dxd_dx + skew * dyd_dx, fx * dxd_dy + skew * dyd_dy
                dv_dx, dv_dy = fy * dyd_dx, fy * dyd_dy
                tw = 1.0
                if tolerant:
                    model_px = marker_sd[m] * 0.5 * (fx + fy) * inv_z
                    tw = 1.0 / np.sqrt(1.0 + (model_px / noise_px) ** 2)
                ru = (u_obs - (fx * xd + skew * yd + cx)) * tw
                rv = (v_obs - (fy * yd + cy)) * tw
                # d pixel / d camera point, then by the world point (· R)
                j00, j01, j02 = du_dx * inv_z, du_dy * inv_z, -(du_dx * x + du_dy * y) * inv_z
                j10, j11, j12 = dv_dx * inv_z, dv_dy * inv_z, -(dv_dx * x + dv_dy * y) * inv_z
                for k in range(3):
                    a[0, k] = (j00 * rotation[c, 0, k] + j01 * rotation[c, 1, k] + j02 * rotation[c, 2, k]) * tw
                    a[1, k] = (j10 * rotation[c, 0, k] + j11 * rotation[c, 1, k] + j12 * rotation[c, 2, k]) * tw
                for p in range(n_params):
                    row[0, p] = a[0, 0] * d_world[f, m, 0, p] + a[0, 1] * d_world[f, m, 1, p] + a[0, 2] * d_world[f, m, 2, p]
                    row[1, p] = a[1, 0] * d_world[f, m, 0, p] + a[1, 1] * d_world[f, m, 1, p] + a[1, 2] * d_world[f, m, 2, p]
                w, rho = _robust(ru * ru + rv * rv, loss, scale)
                residual[f, i], residual[f, i + 1] = ru, rv
                weight[f, i], weight[f, i + 1] = w, w
                total += rho
                for p in range(n_params):
                    gradient[f, p] += w * (ru * row[0, p] + rv * row[1, p])
                    for q in range(p + 1):
                        hessian[f, p, q] += w * (row[0, p] * row[0, q] + row[1, p] * row[1, q])
        cost[f] = total
        for p in range(n_params):
            for q in range(p):
                hessian[f, q, p] = hessian[f, p, q]


@njit(cache=True, nogil=True)
def world_markers(joints, rotation, translation, first, second, revolute, parents, at_zero, joint_links,
                  axes, marker_links, marker_positions, moves, n_links, markers, d_world):
    """Fill markers (F, M, 3) in the world and d_world (F, M, 3, P), their derivatives by the
    parameters (as kinmodel.KinematicModel.world_markers: revolute a x (p - o), prismatic a,
    base rotation increment -[p - t]x, base translation the identity).

    joints (F, J); rotation (F, 3, 3) and translation (F, 3) ``world_from_base``, or both
    empty (F = 0 rows) for a fixed base; first, second (J, 4, 4) the joints' motion terms
    (mocap.machine.Machine._motion_terms); revolute (J,); parents (J,) parent links;
    at_zero (J, 4, 4); joint_links (J,); axes (J, 3) in the links' frames; marker_links (M,);
    marker_positions (M, 3) on their links; moves (J, M) which joints move which markers.
    """
    n_frames, n_joints = joints.shape
    n_markers, n_params = marker_positions.shape[0], d_world.shape[3]
    has_base = rotation.shape[0] > 0
    poses = np.empty((n_links, 4, 4))
    motion = np.empty((4, 4))
    local = np.empty((4, 4))
    ax = np.empty(3)
    for f in range(n_frames):
        poses[0] = np.eye(4)
        if has_base:
            poses[0, :3, :3] = rotation[f]
            poses[0, :3, 3] = translation[f]
        for j in range(n_joints):
            q = joints[f, j]
            a = np.sin(q) if revolute[j] else q
            b = 1.0 - np.cos(q) if revolute[j] else 0.0
            for r in range(4):
                for s in range(4):
                    motion[r, s] = (1.0 if r == s else 0.0) + a * first[j, r, s] + b * second[j, r, s]
            for r in range(4):
                for s in range(4):
                    local[r, s] = (at_zero[j, r, 0] * motion[0, s] + at_zero[j, r, 1] * motion[1, s]
                                   + at_zero[j, r, 2] * motion[2, s] + at_zero[j, r, 3] * motion[3, s])
            parent, link = parents[j], joint_links[j]
            for r in range(4):
                for s in range(4):
                    poses[link, r, s] = (poses[parent, r, 0] * local[0, s] + poses[parent, r, 1] * local[1, s]
                                         + poses[parent, r, 2] * local[2, s] + poses[parent, r, 3] * local[3, s])
        for m in range(n_markers):
            link = marker_links[m]
            for r in range(3):
                markers[f, m, r] = (poses[link, r, 0] * marker_positions[m, 0] + poses[link, r, 1] * marker_positions[m, 1]
                                    + poses[link, r, 2] * marker_positions[m, 2] + poses[link, r, 3])
            for r in range(3):
                for p in range(n_params):
                    d_world[f, m, r, p] = 0.0
        for j in range(n_joints):
            link = joint_links[j]
            for r in range(3):
                ax[r] = poses[link, r, 0] * axes[j, 0] + poses[link, r, 1] * axes[j, 1] + poses[link, r, 2] * axes[j, 2]
            for m in range(n_markers):
                if not moves[j, m]:
                    continue
                if revolute[j]:
                    lx = markers[f, m, 0] - poses[link, 0, 3]
                    ly = markers[f, m, 1] - poses[link, 1, 3]
                    lz = markers[f, m, 2] - poses[link, 2, 3]
                    d_world[f, m, 0, j] = ax[1] * lz - ax[2] * ly
                    d_world[f, m, 1, j] = ax[2] * lx - ax[0] * lz
                    d_world[f, m, 2, j] = ax[0] * ly - ax[1] * lx
                else:
                    d_world[f, m, 0, j] = ax[0]
                    d_world[f, m, 1, j] = ax[1]
                    d_world[f, m, 2, j] = ax[2]
        if has_base:
            for m in range(n_markers):
                lx = markers[f, m, 0] - translation[f, 0]
                ly = markers[f, m, 1] - translation[f, 1]
                lz = markers[f, m, 2] - translation[f, 2]
                # e_i x lever for i = x, y, z
                d_world[f, m, 1, n_joints] = -lz
                d_world[f, m, 2, n_joints] = ly
                d_world[f, m, 0, n_joints + 1] = lz
                d_world[f, m, 2, n_joints + 1] = -lx
                d_world[f, m, 0, n_joints + 2] = -ly
                d_world[f, m, 1, n_joints + 2] = lx
                for r in range(3):
                    d_world[f, m, r, n_joints + 3 + r] = 1.0
