"""The tracker's joint fit, compiled (numba): forward kinematics, projection through the
camera's lens with its Jacobian, and robust Gauss-Newton steps, one frame at a time.

`mocap.tracking.model.CameraModel.fit` states the method; this module only computes it, the
same sums in the same order as the vectorised numpy of `Machine.markers_with_jacobian`,
`camera.project_cam` and the fit's normal equations (a few frames of a dozen markers and a
handful of joints: numpy's per-call overhead, not arithmetic, was the cost).

Shapes: F frames, M markers, J joints, L links.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mocap.core.camera_kernel import project_point
from mocap.core.shapes import behind_a_box


@njit(cache=True, nogil=True)
def _link_poses(joints, revolute, parents, joint_links, at_zero, first, second, poses):
    """World-from-link transforms (L, 4, 4) into `poses` for one frame's joints (J,);
    motion(q) = I + a(q) A + b(q) B (see `Machine._motion_terms`), links parents first."""
    n_links = poses.shape[0]
    for i in range(n_links):
        for a in range(4):
            for b in range(4):
                poses[i, a, b] = 1.0 if a == b else 0.0
    motion = np.empty((4, 4))
    step = np.empty((4, 4))
    for j in range(joints.shape[0]):
        q = joints[j]
        if revolute[j]:
            sa, sb = math.sin(q), 1.0 - math.cos(q)
        else:
            sa, sb = q, 0.0
        for a in range(4):
            for b in range(4):
                motion[a, b] = (1.0 if a == b else 0.0) + sa * first[j, a, b] + sb * second[j, a, b]
        for a in range(4):
            for b in range(4):
                total = 0.0
                for k in range(4):
                    total += at_zero[j, a, k] * motion[k, b]
                step[a, b] = total
        parent, link = parents[j], joint_links[j]
        for a in range(4):
            for b in range(4):
                total = 0.0
                for k in range(4):
                    total += poses[parent, a, k] * step[k, b]
                poses[link, a, b] = total


@njit(cache=True, nogil=True)
def _marker_in_camera(pose, position, rotation, translation, world, cam):
    """A marker at `position` (3,) in its link's frame `pose` (4, 4): its world point into
    `world` (3,) and its camera-frame point into `cam` (3,)."""
    for a in range(3):
        world[a] = pose[a, 0] * position[0] + pose[a, 1] * position[1] + pose[a, 2] * position[2] + pose[a, 3]
    for a in range(3):
        cam[a] = rotation[a, 0] * world[0] + rotation[a, 1] * world[1] + rotation[a, 2] * world[2] + translation[a]


@njit(cache=True, nogil=True)
def _markers(joints, chain, marker_links, positions, rotation, translation, matrix, distortion, moves, with_jac,
             uv, duv):
    """One frame's marker pixels (M, 2) into `uv` and, `with_jac`, d(uv)/d(joints)
    (M, 2, J) into `duv` (zero for a marker behind the camera)."""
    revolute, parents, joint_links, at_zero, first, second, axes, n_links = chain
    poses = np.empty((n_links, 4, 4))
    _link_poses(joints, revolute, parents, joint_links, at_zero, first, second, poses)
    n_markers, n_joints = positions.shape[0], joints.shape[0]
    world = np.empty(3)
    cam = np.empty(3)
    jac = np.empty((2, 3))
    dworld = np.empty(3)
    for m in range(n_markers):
        link = marker_links[m]
        _marker_in_camera(poses[link], positions[m], rotation, translation, world, cam)
        ahead = project_point(cam, matrix, distortion, uv[m], jac)
        if not with_jac:
            continue
        # d(uv)/d(world) = jac @ rotation, then by each joint that moves the marker
        for j in range(n_joints):
            duv[m, 0, j] = duv[m, 1, j] = 0.0
            if not (ahead and moves[j, m]):
                continue
            link_j = joint_links[j]
            ax = poses[link_j, 0, 0] * axes[j, 0] + poses[link_j, 0, 1] * axes[j, 1] + poses[link_j, 0, 2] * axes[j, 2]
            ay = poses[link_j, 1, 0] * axes[j, 0] + poses[link_j, 1, 1] * axes[j, 1] + poses[link_j, 1, 2] * axes[j, 2]
            az = poses[link_j, 2, 0] * axes[j, 0] + poses[link_j, 2, 1] * axes[j, 1] + poses[link_j, 2, 2] * axes[j, 2]
            if revolute[j]:
                lx, ly, lz = world[0] - poses[link_j, 0, 3], world[1] - poses[link_j, 1, 3], world[2] - poses[link_j, 2, 3]
                dworld[0], dworld[1], dworld[2] = ay * lz - az * ly, az * lx - ax * lz, ax * ly - ay * lx
            else:
                dworld[0], dworld[1], dworld[2] = ax, ay, az
            for r in range(2):
                total = 0.0
                for a in range(3):
                    total += (jac[r, 0] * rotation[0, a] + jac[r, 1] * rotation[1, a] + jac[r, 2] * rotation[2, a]) * dworld[a]
                duv[m, r, j] = total


@njit(cache=True, nogil=True)
def fit_joints(pixels, start, iterations, scale_px, prior_weight, limits, chain, marker_links, positions, rotation,
               translation, matrix, distortion, moves):
    """Robust Gauss-Newton fits of the joints (F, J) from `start` (F, J) to `pixels`
    (F, M, 2) (NaN: not observed). Returns the joints (F, J), the residuals (F, M) px (NaN
    where not observed) and the fitted pixels (F, M, 2)."""
    n_frames, n_markers = pixels.shape[0], pixels.shape[1]
    n_joints = start.shape[1]
    joints = start.copy()
    residuals = np.full((n_frames, n_markers), np.nan)
    fitted = np.empty((n_frames, n_markers, 2))
    uv = np.empty((n_markers, 2))
    duv = np.zeros((n_markers, 2, n_joints))
    normal = np.empty((n_joints, n_joints))
    gradient = np.empty(n_joints)
    for f in range(n_frames):
        q = joints[f]
        for _ in range(iterations if n_joints > 0 else 0):
            _markers(q, chain, marker_links, positions, rotation, translation, matrix, distortion, moves, True, uv, duv)
            for a in range(n_joints):
                gradient[a] = prior_weight * (q[a] - start[f, a])
                for b in range(n_joints):
                    normal[a, b] = prior_weight if a == b else 0.0
            for m in range(n_markers):
                tx, ty = pixels[f, m, 0], pixels[f, m, 1]
                if not (math.isfinite(tx) and math.isfinite(ty)):
                    continue
                rx, ry = uv[m, 0] - tx, uv[m, 1] - ty
                norm = math.sqrt(rx * rx + ry * ry)
                if not math.isfinite(norm):
                    continue
                weight = min(1.0, scale_px / max(norm, 1e-12))
                for a in range(n_joints):
                    gradient[a] += weight * (duv[m, 0, a] * rx + duv[m, 1, a] * ry)
                    for b in range(n_joints):
                        normal[a, b] += weight * (duv[m, 0, a] * duv[m, 0, b] + duv[m, 1, a] * duv[m, 1, b])
            move = np.linalg.solve(normal, gradient)
            for a in range(n_joints):
                q[a] = min(max(q[a] - move[a], limits[a, 0]), limits[a, 1])
        _markers(q, chain, marker_links, positions, rotation, translation, matrix, distortion, moves, False,
                 fitted[f], duv)
        for m in range(n_markers):
            tx, ty = pixels[f, m, 0], pixels[f, m, 1]
            if math.isfinite(tx) and math.isfinite(ty):
                residuals[f, m] = math.sqrt((fitted[f, m, 0] - tx) ** 2 + (fitted[f, m, 1] - ty) ** 2)
    return joints, residuals, fitted


@njit(cache=True, nogil=True)
def marker_pixels(joints, chain, marker_links, positions, rotation, translation, matrix, distortion, moves):
    """Marker pixels (F, M, 2) at joints (F, J); NaN behind the camera."""
    n_frames, n_markers = joints.shape[0], positions.shape[0]
    out = np.empty((n_frames, n_markers, 2))
    duv = np.zeros((n_markers, 2, joints.shape[1]))
    for f in range(n_frames):
        _markers(joints[f], chain, marker_links, positions, rotation, translation, matrix, distortion, moves, False,
                 out[f], duv)
    return out


@njit(cache=True, nogil=True)
def marker_view(joints, chain, marker_links, positions, rotation, translation, matrix, distortion, boxes, normals,
                width, height, solid, min_facing, box_hides):
    """What the camera sees at joints (F, J) (`CameraModel.view`): marker pixels (F, M, 2),
    whether each is seen (F, M) (in the image, facing the camera by more than `min_facing`
    and not behind another link's box, of the links `box_hides` (L,) marks; with `solid` False,
    in front of the camera and in the image) and px per metre (F, M)."""
    revolute, parents, joint_links, at_zero, first, second, axes, n_links = chain
    n_frames, n_markers = joints.shape[0], positions.shape[0]
    uv = np.empty((n_frames, n_markers, 2))
    seen = np.zeros((n_frames, n_markers), dtype=np.bool_)
    scale = np.empty((n_frames, n_markers))
    poses = np.empty((n_links, 4, 4))
    jac = np.empty((2, 3))
    world = np.empty(3)
    cam = np.empty(3)
    centre = np.empty(3)
    start = np.empty(3)
    end = np.empty(3)
    focal = 0.5 * (matrix[0, 0] + matrix[1, 1])
    for a in range(3):  # the camera's centre in the world: -R^T t
        centre[a] = -(rotation[0, a] * translation[0] + rotation[1, a] * translation[1] + rotation[2, a] * translation[2])
    for f in range(n_frames):
        _link_poses(joints[f], revolute, parents, joint_links, at_zero, first, second, poses)
        for m in range(n_markers):
            link = marker_links[m]
            _marker_in_camera(poses[link], positions[m], rotation, translation, world, cam)
            project_point(cam, matrix, distortion, uv[f, m], jac)
            u, v = uv[f, m, 0], uv[f, m, 1]
            nx = poses[link, 0, 0] * normals[m, 0] + poses[link, 0, 1] * normals[m, 1] + poses[link, 0, 2] * normals[m, 2]
            ny = poses[link, 1, 0] * normals[m, 0] + poses[link, 1, 1] * normals[m, 1] + poses[link, 1, 2] * normals[m, 2]
            nz = poses[link, 2, 0] * normals[m, 0] + poses[link, 2, 1] * normals[m, 1] + poses[link, 2, 2] * normals[m, 2]
            if solid:
                inside = math.isfinite(u) and math.isfinite(v) and 0 <= u <= width - 1 and 0 <= v <= height - 1
                tx, ty, tz = centre[0] - world[0], centre[1] - world[1], centre[2] - world[2]
                facing = (nx * tx + ny * ty + nz * tz) / math.sqrt(tx * tx + ty * ty + tz * tz) > min_facing
                seen[f, m] = inside and facing and not behind_a_box(world, centre, poses, link, boxes, box_hides,
                                                                     start, end)
            else:
                inside = -0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5
                seen[f, m] = cam[2] > 0 and inside
            # px per metre: f / depth, times the square root of the cosine of the viewing angle
            if cam[2] > 0:
                distance = math.sqrt(cam[0] * cam[0] + cam[1] * cam[1] + cam[2] * cam[2])
                ncx = rotation[0, 0] * nx + rotation[0, 1] * ny + rotation[0, 2] * nz
                ncy = rotation[1, 0] * nx + rotation[1, 1] * ny + rotation[1, 2] * nz
                ncz = rotation[2, 0] * nx + rotation[2, 1] * ny + rotation[2, 2] * nz
                cosine = abs(ncx * cam[0] + ncy * cam[1] + ncz * cam[2]) / distance if solid else 1.0
                scale[f, m] = focal / cam[2] * math.sqrt(cosine)
            else:
                scale[f, m] = math.nan
    return uv, seen, scale
