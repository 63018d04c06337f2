"""The kinematic fit's solver, compiled (numba): the whole Levenberg-Marquardt solve of
every frame on its own (`levenberg_marquardt`: no Python runs between iterations), each
iteration building the frame's robust residuals and small normal equations in one pass
without the Jacobian of all observations in memory; and the markers' world positions and
their derivatives by the parameters for every frame (`world_markers`).

Per observation (camera c, marker m) of frame f: the marker's camera-frame position, its
pixel through the OpenCV lens (mocap.core.camera.project_cam) and the pixel's derivative by the
frame's parameters (d pixel / d camera point · R_c · d world / d parameters). Residuals are
divided by the model-tolerance weight (kinmodel.KinematicModel), robustified per
observation (2-D length: Huber, Cauchy or none) and summed into JᵀWJ (P, P), JᵀWr (P,)
and the robust cost. An observation not seen (NaN pixel) or behind the camera contributes
nothing. Shapes: F frames, C cameras, M markers, P parameters, N = C * M * 2.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mocap.reconstruct.linear_kernel import solve_into

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
def _normal_frame(markers, d_world, pixels, rotation, translation, intrinsics, distortion, marker_sd, noise_px,
                  loss, scale, residual, weight, hessian, gradient, a, row):
    """One frame's normal equations: fill residual (N,), weight (N,), hessian (P, P) and
    gradient (P,) from markers (M, 3), d_world (M, 3, P) and pixels (C, M, 2); return the
    robust cost. rotation (C, 3, 3) and translation (C, 3) cam_from_world; intrinsics
    (C, 5) fx, skew, cx, fy, cy; distortion (C, 5) k1 k2 p1 p2 k3; marker_sd (M,) m, empty
    for an exact model; noise_px the pixel SD the tolerance is weighed against; loss a
    LOSS_CODES value. a (2, 3) and row (2, P) are scratch."""
    n_markers, n_cams, n_params = markers.shape[0], rotation.shape[0], d_world.shape[2]
    tolerant = marker_sd.shape[0] > 0
    for p in range(n_params):
        gradient[p] = 0.0
        for q in range(n_params):
            hessian[p, q] = 0.0
    total = 0.0
    for c in range(n_cams):
        fx, skew, cx, fy, cy = intrinsics[c, 0], intrinsics[c, 1], intrinsics[c, 2], intrinsics[c, 3], intrinsics[c, 4]
        k1, k2, p1, p2, k3 = distortion[c, 0], distortion[c, 1], distortion[c, 2], distortion[c, 3], distortion[c, 4]
        for m in range(n_markers):
            i = 2 * (c * n_markers + m)
            residual[i] = 0.0
            residual[i + 1] = 0.0
            weight[i] = 1.0
            weight[i + 1] = 1.0
            u_obs, v_obs = pixels[c, m, 0], pixels[c, m, 1]
            if not np.isfinite(u_obs):
                continue
            wx, wy, wz = markers[m, 0], markers[m, 1], markers[m, 2]
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
                row[0, p] = a[0, 0] * d_world[m, 0, p] + a[0, 1] * d_world[m, 1, p] + a[0, 2] * d_world[m, 2, p]
                row[1, p] = a[1, 0] * d_world[m, 0, p] + a[1, 1] * d_world[m, 1, p] + a[1, 2] * d_world[m, 2, p]
            w, rho = _robust(ru * ru + rv * rv, loss, scale)
            residual[i], residual[i + 1] = ru, rv
            weight[i], weight[i + 1] = w, w
            total += rho
            for p in range(n_params):
                gradient[p] += w * (ru * row[0, p] + rv * row[1, p])
                for q in range(p + 1):
                    hessian[p, q] += w * (row[0, p] * row[0, q] + row[1, p] * row[1, q])
    for p in range(n_params):
        for q in range(p):
            hessian[q, p] = hessian[p, q]
    return total


@njit(cache=True, nogil=True)
def world_frame(joints, rotation, translation, first, second, revolute, parents, at_zero, joint_links, axes,
                 marker_links, marker_positions, moves, markers, d_world, poses, motion, local, ax):
    """One frame of `world_markers`: fill markers (M, 3) and d_world (M, 3, P) for joints
    (J,) and ``world_from_base`` rotation (3, 3) and translation (3,), both empty for a
    fixed base. poses (L, 4, 4), motion and local (4, 4), ax (3,) are scratch."""
    n_joints = joints.shape[0]
    n_markers, n_params = marker_positions.shape[0], d_world.shape[2]
    has_base = rotation.shape[0] > 0
    poses[0] = np.eye(4)
    if has_base:
        poses[0, :3, :3] = rotation
        poses[0, :3, 3] = translation
    for j in range(n_joints):
        q = joints[j]
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
            markers[m, r] = (poses[link, r, 0] * marker_positions[m, 0] + poses[link, r, 1] * marker_positions[m, 1]
                             + poses[link, r, 2] * marker_positions[m, 2] + poses[link, r, 3])
        for r in range(3):
            for p in range(n_params):
                d_world[m, r, p] = 0.0
    for j in range(n_joints):
        link = joint_links[j]
        for r in range(3):
            ax[r] = poses[link, r, 0] * axes[j, 0] + poses[link, r, 1] * axes[j, 1] + poses[link, r, 2] * axes[j, 2]
        for m in range(n_markers):
            if not moves[j, m]:
                continue
            if revolute[j]:
                lx = markers[m, 0] - poses[link, 0, 3]
                ly = markers[m, 1] - poses[link, 1, 3]
                lz = markers[m, 2] - poses[link, 2, 3]
                d_world[m, 0, j] = ax[1] * lz - ax[2] * ly
                d_world[m, 1, j] = ax[2] * lx - ax[0] * lz
                d_world[m, 2, j] = ax[0] * ly - ax[1] * lx
            else:
                d_world[m, 0, j] = ax[0]
                d_world[m, 1, j] = ax[1]
                d_world[m, 2, j] = ax[2]
    if has_base:
        for m in range(n_markers):
            lx = markers[m, 0] - translation[0]
            ly = markers[m, 1] - translation[1]
            lz = markers[m, 2] - translation[2]
            # e_i x lever for i = x, y, z
            d_world[m, 1, n_joints] = -lz
            d_world[m, 2, n_joints] = ly
            d_world[m, 0, n_joints + 1] = lz
            d_world[m, 2, n_joints + 1] = -lx
            d_world[m, 0, n_joints + 2] = -ly
            d_world[m, 1, n_joints + 2] = lx
            for r in range(3):
                d_world[m, r, n_joints + 3 + r] = 1.0


@njit(cache=True, nogil=True)
def world_markers(joints, rotation, translation, first, second, revolute, parents, at_zero, joint_links,
                  axes, marker_links, marker_positions, moves, n_links, markers, d_world):
    """Fill markers (F, M, 3) in the world and d_world (F, M, 3, P), their derivatives by the
    parameters (as kinmodel.KinematicModel.world_markers: revolute a x (p - o), prismatic a,
    base rotation increment -[p - t]x, base translation the identity).

    joints (F, J); rotation (F, 3, 3) and translation (F, 3) ``world_from_base``, or both
    empty (F = 0 rows) for a fixed base; first, second (J, 4, 4) the joints' motion terms
    (mocap.core.machine.Machine._motion_terms); revolute (J,); parents (J,) parent links;
    at_zero (J, 4, 4); joint_links (J,); axes (J, 3) in the links' frames; marker_links (M,);
    marker_positions (M, 3) on their links; moves (J, M) which joints move which markers.
    """
    poses, motion, local, ax = np.empty((n_links, 4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty(3)
    fixed = np.empty((0, 3)), np.empty(0)
    has_base = rotation.shape[0] > 0
    for f in range(joints.shape[0]):
        base_rotation, base_translation = (rotation[f], translation[f]) if has_base else fixed
        world_frame(joints[f], base_rotation, base_translation, first, second, revolute, parents, at_zero,
                     joint_links, axes, marker_links, marker_positions, moves, markers[f], d_world[f],
                     poses, motion, local, ax)


@njit(cache=True, nogil=True)
def _rotvec_matrix(w, out):
    """out (3, 3): the rotation of Rodrigues vector w (3,) (a series near zero)."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    theta = np.sqrt(theta2)
    if theta < 1e-4:
        s, c = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0  # sin(t) / t, (1 - cos(t)) / t²
    else:
        s, c = np.sin(theta) / theta, (1.0 - np.cos(theta)) / theta2
    x, y, z = w[0], w[1], w[2]
    out[0, 0] = 1.0 - c * (y * y + z * z)
    out[1, 1] = 1.0 - c * (x * x + z * z)
    out[2, 2] = 1.0 - c * (x * x + y * y)
    out[0, 1], out[1, 0] = c * x * y - s * z, c * x * y + s * z
    out[0, 2], out[2, 0] = c * x * z + s * y, c * x * z - s * y
    out[1, 2], out[2, 1] = c * y * z - s * x, c * y * z + s * x


@njit(cache=True, nogil=True)
def _matrix_rotvec(r, out):
    """out (3,): the Rodrigues vector of rotation r (3, 3), through its unit quaternion."""
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace >= max(r[0, 0], r[1, 1], r[2, 2]):
        w = 0.5 * np.sqrt(max(1.0 + trace, 0.0))
        x, y, z = (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)
    elif r[0, 0] >= r[1, 1] and r[0, 0] >= r[2, 2]:
        x = 0.5 * np.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        w, y, z = (r[2, 1] - r[1, 2]) / (4 * x), (r[0, 1] + r[1, 0]) / (4 * x), (r[0, 2] + r[2, 0]) / (4 * x)
    elif r[1, 1] >= r[2, 2]:
        y = 0.5 * np.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
        w, x, z = (r[0, 2] - r[2, 0]) / (4 * y), (r[0, 1] + r[1, 0]) / (4 * y), (r[1, 2] + r[2, 1]) / (4 * y)
    else:
        z = 0.5 * np.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
        w, x, y = (r[1, 0] - r[0, 1]) / (4 * z), (r[0, 2] + r[2, 0]) / (4 * z), (r[1, 2] + r[2, 1]) / (4 * z)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    norm = np.sqrt(x * x + y * y + z * z)
    angle = 2.0 * np.arctan2(norm, w)
    factor = angle / norm if norm > 1e-12 else 2.0 / max(w, 1e-300)
    out[0], out[1], out[2] = factor * x, factor * y, factor * z


@njit(cache=True, nogil=True)
def levenberg_marquardt(joints, rotation, translation, pixels, first, second, revolute, parents, at_zero,
                        joint_links, axes, marker_links, marker_positions, moves, n_links, cam_rotation,
                        cam_translation, intrinsics, distortion, marker_sd, noise_px, loss, scale, lower, upper,
                        wrap, iterations, eps_info, converged, known_joints, known_rotation, known_translation,
                        known_hessian, same_px2, cost, hessian, residual, weight):
    """Levenberg-Marquardt of every frame on its own, from and into joints (F, J) and, with
    a moving base, rotation (F, 3, 3) and translation (F, 3) ``world_from_base`` (both
    empty otherwise); pixels (F, C, M, 2); the chain arrays as `world_markers`'s, the
    cameras and robust loss as `_normal_frame`'s.

    Per iteration: solve (H + damping diag(H) + eps_info I) delta = g, step (joints
    clipped to lower / upper (J,), joints that wrap (J,) wrapped into their span, the base
    rotation increment on the left), keep the step if it does not raise the robust cost
    (damping x 0.3, else x 10, within 1e-9 .. 1e9); a frame stops after `iterations` or
    once its cost changes by less than `converged` relatively. With a known solution
    (known_joints (F, J), known_rotation, known_translation, known_hessian (F, P, P); zero
    rows for none) a frame also stops, with cost +inf, once its squared pixel distance
    dᵀHd from it is below same_px2 (full-circle joints compared modulo their span).
    Fills cost (F,), hessian (F, P, P), residual and weight (F, N) at each frame's solution.
    """
    n_frames, n_joints = joints.shape
    n_params = hessian.shape[1]
    n_rows = residual.shape[1]
    has_base = rotation.shape[0] > 0
    has_known = known_joints.shape[0] > 0
    n_markers = marker_positions.shape[0]
    poses, motion, local, ax = np.empty((n_links, 4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty(3)
    a, row = np.empty((2, 3)), np.empty((2, n_params))
    markers, d_world = np.empty((n_markers, 3)), np.empty((n_markers, 3, n_params))
    gradient, t_gradient = np.empty(n_params), np.empty(n_params)
    t_hessian = np.empty((n_params, n_params))
    t_residual, t_weight = np.empty(n_rows, np.float32), np.empty(n_rows, np.float32)
    lhs, rhs, delta = np.empty((n_params, n_params)), np.empty(n_params), np.empty(n_params)
    rhs_column, delta_column = rhs.reshape((n_params, 1)), delta.reshape((n_params, 1))  # views, for solve_into
    t_joints = np.empty(n_joints)
    t_rotation, t_translation, turn = np.empty((3, 3)), np.empty(3), np.empty((3, 3))
    relative, rotvec, gap = np.empty((3, 3)), np.empty(3), np.empty(n_params)
    no_rotation, no_translation = np.empty((0, 3)), np.empty(0)
    for f in range(n_frames):
        base_rotation, base_translation = (rotation[f], translation[f]) if has_base else (no_rotation, no_translation)
        world_frame(joints[f], base_rotation, base_translation, first, second, revolute, parents, at_zero,
                     joint_links, axes, marker_links, marker_positions, moves, markers, d_world, poses, motion,
                     local, ax)
        cost[f] = _normal_frame(markers, d_world, pixels[f], cam_rotation, cam_translation, intrinsics, distortion,
                                marker_sd, noise_px, loss, scale, residual[f], weight[f], hessian[f], gradient,
                                a, row)
        damping = 1e-3
        for _ in range(iterations):
            for p in range(n_params):
                for q in range(n_params):
                    lhs[p, q] = hessian[f, p, q]
                lhs[p, p] += damping * hessian[f, p, p] + eps_info
                rhs[p] = gradient[p]
            solve_into(lhs, rhs_column, delta_column)
            for j in range(n_joints):
                value = joints[f, j] + delta[j]
                if wrap[j]:
                    span = upper[j] - lower[j]
                    value = lower[j] + (value - lower[j]) - span * np.floor((value - lower[j]) / span)
                else:
                    value = min(max(value, lower[j]), upper[j])
                t_joints[j] = value
            if has_base:
                _rotvec_matrix(delta[n_joints : n_joints + 3], turn)
                for r in range(3):
                    for s in range(3):
                        t_rotation[r, s] = (turn[r, 0] * rotation[f, 0, s] + turn[r, 1] * rotation[f, 1, s]
                                            + turn[r, 2] * rotation[f, 2, s])
                    t_translation[r] = translation[f, r] + delta[n_joints + 3 + r]
                trial_rotation, trial_translation = t_rotation, t_translation
            else:
                trial_rotation, trial_translation = no_rotation, no_translation
            world_frame(t_joints, trial_rotation, trial_translation, first, second, revolute, parents, at_zero,
                         joint_links, axes, marker_links, marker_positions, moves, markers, d_world, poses, motion,
                         local, ax)
            t_cost = _normal_frame(markers, d_world, pixels[f], cam_rotation, cam_translation, intrinsics,
                                   distortion, marker_sd, noise_px, loss, scale, t_residual, t_weight, t_hessian,
                                   t_gradient, a, row)
            better = t_cost <= cost[f]
            change = abs(cost[f] - t_cost) / max(cost[f], 1e-12)
            if better:
                joints[f] = t_joints
                if has_base:
                    rotation[f] = t_rotation
                    translation[f] = t_translation
                residual[f] = t_residual
                weight[f] = t_weight
                cost[f] = t_cost
                hessian[f] = t_hessian
                gradient[:] = t_gradient
                damping = min(max(damping * 0.3, 1e-9), 1e9)
            else:
                damping = min(max(damping * 10.0, 1e-9), 1e9)
            going = change >= converged
            if has_known:
                for j in range(n_joints):
                    diff = joints[f, j] - known_joints[f, j]
                    if wrap[j]:
                        span = upper[j] - lower[j]
                        shifted = diff + 0.5 * span
                        diff = shifted - span * np.floor(shifted / span) - 0.5 * span
                    gap[j] = diff
                if has_base:
                    for r in range(3):
                        for s in range(3):
                            relative[r, s] = (rotation[f, r, 0] * known_rotation[f, s, 0]
                                              + rotation[f, r, 1] * known_rotation[f, s, 1]
                                              + rotation[f, r, 2] * known_rotation[f, s, 2])
                    _matrix_rotvec(relative, rotvec)
                    for r in range(3):
                        gap[n_joints + r] = rotvec[r]
                        gap[n_joints + 3 + r] = translation[f, r] - known_translation[f, r]
                distance = 0.0
                for p in range(n_params):
                    for q in range(n_params):
                        distance += gap[p] * known_hessian[f, p, q] * gap[q]
                if distance < same_px2:
                    cost[f] = np.inf
                    going = False
            if not going:
                break
