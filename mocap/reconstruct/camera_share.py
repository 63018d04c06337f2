"""What the cameras' own uncertainty adds to each frame's parameter covariance.

A calibration's error is common to every frame it is used on: the fit's covariance from the
pixel noise leaves it out, however many frames there are. With the calibration's
covariance Σ of the cameras' parameters (`CameraCovariance`, as `calibrate` writes it), a
frame's parameters move by X δc for a camera error δc, X = H⁻¹ Jᵀ W D its response (H =
Jᵀ W J the frame's weighted normal matrix, D the predicted pixels' derivative by the camera
parameters), so that X Σ Xᵀ is added to the frame's covariance, as the markers' offsets' is
(mocap.reconstruct.offsets). A triangulated point is the same with its three coordinates
for parameters (`point_covariance`).

Camera parameters, named ``<camera>.<parameter>`` as the calibration names them: ``rx ry
rz`` the Rodrigues vector of ``cam_from_world``, ``tx ty tz`` its translation (m), ``f`` the
focal length (fx, fy in proportion), ``cx cy`` the principal point, ``k1 k2 p1 p2 k3``
the distortion. Shapes: C cameras, F frames, M markers, P parameters, K camera parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.core.camera import Camera, project_cam
from mocap.core.geometry import Rigid, rotvec_to_matrix
from mocap.core.machine import Machine
from mocap.reconstruct.kinmodel import FrameState, KinematicModel

CAMERA_PARAMETERS = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_CHUNK = 2048  # frames at a time
_STEP_SDS = 1e-3  # finite-difference step in SDs of the parameter


@dataclass(frozen=True)
class CameraCovariance:
    """names (K,) ``<camera>.<parameter>``; matrix (K, K) their covariance."""

    names: tuple[str, ...]
    matrix: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.names)
        if np.shape(self.matrix) != (k, k):
            raise ValueError(f"a camera covariance of {k} parameters must be ({k}, {k}), got {np.shape(self.matrix)}")

    @classmethod
    def of_cameras(cls, names, covariance: np.ndarray, cameras) -> CameraCovariance:
        """The cameras' block of a covariance over `names` (joints and the rest left out)."""
        camera_names = {c.name for c in cameras}
        keep = [i for i, n in enumerate(names)
                if "." in n and n.rsplit(".", 1)[0] in camera_names and n.rsplit(".", 1)[1] in CAMERA_PARAMETERS]
        return cls(tuple(names[i] for i in keep), np.asarray(covariance, dtype=float)[np.ix_(keep, keep)])

    def to_table(self) -> dict:
        return {"parameters": list(self.names), "matrix": self.matrix.tolist()}

    @classmethod
    def from_table(cls, table: dict) -> CameraCovariance:
        """From ``{parameters, matrix}``; ValueError unless the matrix is K x K finite numbers,
        symmetric with a non-negative diagonal."""
        names, matrix = tuple(str(n) for n in table["parameters"]), np.asarray(table["matrix"], dtype=float)
        if matrix.shape != (len(names), len(names)) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"{len(names)} parameters need a {len(names)} x {len(names)} matrix of finite numbers")
        diagonal = np.diag(matrix)
        # symmetric to a millionth of each pair's scale: an entry near zero is allowed its rounding
        scale = np.sqrt(np.outer(np.abs(diagonal), np.abs(diagonal))) + 1e-12 * np.abs(matrix).max(initial=0.0)
        if np.any(diagonal < 0) or np.any(np.abs(matrix - matrix.T) > 1e-6 * scale):
            raise ValueError("a covariance is symmetric with a non-negative diagonal")
        return cls(names, matrix)

    def with_cameras(self, cameras) -> CameraCovariance:
        """Only the parameters of `cameras` (by name)."""
        return CameraCovariance.of_cameras(self.names, self.matrix, cameras)


def named_parameters(camera: Camera) -> np.ndarray:
    """(14,) a camera's parameters in the order of CAMERA_PARAMETERS."""
    pose, matrix = camera.cam_from_world, camera.matrix
    return np.r_[pose.rotvec, pose.translation, matrix[0, 0], matrix[0, 2], matrix[1, 2],
                 np.broadcast_to(camera.distortion, 5)]


def perturbed(camera: Camera, parameter: str, delta: float) -> Camera:
    """`camera` with one named parameter moved by `delta`."""
    pose, matrix, distortion = camera.cam_from_world, camera.matrix.copy(), np.broadcast_to(camera.distortion, 5).copy()
    if parameter[0] == "r" and parameter[1:] in ("x", "y", "z"):
        rotvec = pose.rotvec.copy()
        rotvec["xyz".index(parameter[1])] += delta
        pose = Rigid(rotvec_to_matrix(rotvec), pose.translation)
    elif parameter[0] == "t" and parameter[1:] in ("x", "y", "z"):
        translation = pose.translation.copy()
        translation["xyz".index(parameter[1])] += delta
        pose = Rigid(pose.rotation, translation)
    elif parameter == "f":
        scale = (matrix[0, 0] + delta) / matrix[0, 0]
        matrix[0, 0] *= scale
        matrix[1, 1] *= scale
    elif parameter in ("cx", "cy"):
        matrix["xy".index(parameter[1]), 2] += delta
    else:
        distortion[("k1", "k2", "p1", "p2", "k3").index(parameter)] += delta
    return Camera(camera.name, camera.size, matrix, distortion, pose)


def camera_share(machine: Machine, cameras: list[Camera], fit, covariance: CameraCovariance | None) -> np.ndarray | float:
    """(F, P, P) what the calibration's covariance adds to each frame's parameter covariance
    of `fit` (a JointFit of `machine` seen by `cameras`), 0.0 without a covariance. Besides
    the cameras' parameters the covariance may hold markers' offsets ``<marker>.dx`` (m, in
    the marker's link frame, as refine estimates them with the cameras)."""
    if covariance is None or not len(covariance.names) or not np.any(covariance.matrix):
        return 0.0
    index = {c.name: k for k, c in enumerate(cameras)}
    markers = set(machine.marker_names)
    names = [n for n in covariance.names if n.rsplit(".", 1)[0] in index
             or (n.rsplit(".", 1)[0] in markers and n.rsplit(".", 1)[-1] in _OFFSETS)]
    if not names:
        return 0.0
    chosen = [covariance.names.index(n) for n in names]
    sigma = covariance.matrix[np.ix_(chosen, chosen)]
    steps = _STEP_SDS * np.sqrt(np.maximum(np.diag(sigma), 0.0))
    out = np.zeros(fit.covariance.shape)
    weights = np.nan_to_num(fit.weights, nan=0.0)  # (C, F, M): 0 where unseen
    for start in range(0, len(fit.joints), _CHUNK):
        part = slice(start, start + _CHUNK)
        response = _response(machine, cameras, fit, part, weights[:, part], names, steps, index)
        out[part] = response @ sigma @ np.swapaxes(response, 1, 2)
    good = fit.valid & fit.explained
    if not good.any():
        return 0.0
    # a frame the fit did not explain (the smoother fills it) takes its nearest explained frame's
    explained, frames = np.flatnonzero(good), np.arange(len(good))
    place = np.searchsorted(explained, frames)
    after, before = explained[np.minimum(place, len(explained) - 1)], explained[np.maximum(place - 1, 0)]
    nearest = np.where(np.abs(before - frames) < np.abs(after - frames), before, after)
    return out[np.where(good, frames, nearest)]


_OFFSETS = ("dx", "dy", "dz")


def point_covariance(cameras: list[Camera], xyz: np.ndarray, used: np.ndarray, noise_px: float,
                     covariance: CameraCovariance | None = None) -> np.ndarray:
    """(N, 3, 3) the covariance of triangulated points xyz (N, 3) from the views `used`
    (C, N): the pixel noise's, noise_px² (Jᵀ J)⁻¹ (J the used views' projection Jacobian by
    the point), plus, with the calibration's `covariance`, the cameras' share X Σ Xᵀ (X =
    (Jᵀ J)⁻¹ Jᵀ D the point's response to the cameras' parameters, D the used views' pixels'
    derivative by them, one finite difference per parameter for all points at once). NaN
    for a point with fewer than two used views or not finite."""
    xyz, used = np.asarray(xyz, dtype=float), np.asarray(used, dtype=bool)
    index = {c.name: k for k, c in enumerate(cameras)}
    names = [] if covariance is None else [n for n in covariance.names if n.rsplit(".", 1)[0] in index
                                           and n.rsplit(".", 1)[-1] in CAMERA_PARAMETERS]
    normal = np.zeros((len(xyz), 3, 3))
    jacobians, predicted, views = [], [], np.zeros(len(xyz), int)
    for c, camera in enumerate(cameras):
        rot = camera.cam_from_world.rotation
        uv, d_uv = project_cam(xyz @ rot.T + camera.cam_from_world.translation, camera.matrix, camera.distortion, True)
        ok = used[c] & np.isfinite(uv).all(-1)
        jac = np.where(ok[:, None, None], np.nan_to_num(d_uv @ rot), 0.0)  # (N, 2, 3)
        normal += np.swapaxes(jac, 1, 2) @ jac
        views += ok
        jacobians.append(jac)
        predicted.append(uv)
    solvable = (views >= 2) & (np.abs(np.linalg.det(normal)) > 0)
    out = np.full((len(xyz), 3, 3), np.nan)
    inverse = np.linalg.inv(normal[solvable])
    out[solvable] = noise_px**2 * inverse
    if names:
        chosen = [covariance.names.index(n) for n in names]
        sigma = covariance.matrix[np.ix_(chosen, chosen)]
        steps = _STEP_SDS * np.sqrt(np.maximum(np.diag(sigma), 0.0))
        gradient = np.zeros((int(solvable.sum()), 3, len(names)))
        for k, (name, step) in enumerate(zip(names, steps)):
            if not step > 0:
                continue
            owner, parameter = name.rsplit(".", 1)
            c = index[owner]
            moved = perturbed(cameras[c], parameter, step)
            rot = moved.cam_from_world.rotation
            uv = project_cam(xyz[solvable] @ rot.T + moved.cam_from_world.translation, moved.matrix, moved.distortion)
            d_pixel = np.nan_to_num((uv - predicted[c][solvable]) / step)  # (N, 2)
            gradient[:, :, k] = np.einsum("nap,na->np", jacobians[c][solvable], d_pixel)
        response = inverse @ gradient  # (N, 3, K)
        out[solvable] += response @ sigma @ np.swapaxes(response, 1, 2)
    return out


def _response(machine, cameras, fit, part: slice, weights: np.ndarray, names, steps, index) -> np.ndarray:
    """(F, P, K) the frames' parameters' response to the calibration's parameters."""
    joints = np.nan_to_num(fit.joints[part])
    rotation = translation = None
    if fit.base is not None:
        base = np.nan_to_num(fit.base[part])
        rotation, translation = rotvec_to_matrix(base[:, :3]), base[:, 3:]
    state = FrameState(joints, rotation, translation, np.zeros(len(joints)))
    model = KinematicModel(machine, tuple(cameras), base_motion=fit.base is not None)
    world, d_world = model.world_markers(state)
    n_frames, n_params = len(joints), d_world.shape[-1]
    hessian = np.zeros((n_frames, n_params, n_params))
    gradient = np.zeros((n_frames, n_params, len(names)))
    jacobians, predicted = [], []
    for c, camera in enumerate(cameras):
        rot = camera.cam_from_world.rotation
        uv, d_uv = project_cam(world @ rot.T + camera.cam_from_world.translation, camera.matrix, camera.distortion, True)
        jq = np.nan_to_num(d_uv @ rot) @ d_world  # (F, M, 2, P)
        w = weights[c] * np.isfinite(uv[..., 0])
        hessian += np.einsum("fmap,fmaq,fm->fpq", jq, jq, w)
        jacobians.append(jq * w[..., None, None])
        predicted.append(uv)
    for k, (name, step) in enumerate(zip(names, steps)):
        if not step > 0:
            continue
        owner, parameter = name.rsplit(".", 1)
        if owner in index:  # a camera's parameter: its own pixels move
            c = index[owner]
            moved = perturbed(cameras[c], parameter, step)
            rot = moved.cam_from_world.rotation
            uv = project_cam(world @ rot.T + moved.cam_from_world.translation, moved.matrix, moved.distortion)
            d_pixel = np.nan_to_num((uv - predicted[c]) / step)  # (F, M, 2)
            gradient[:, :, k] = np.einsum("fmap,fma->fp", jacobians[c], d_pixel)
            continue
        m = machine.marker_names.index(owner)  # a marker's offset: every camera's pixels of it move
        positions = machine.marker_positions.copy()
        positions[m, _OFFSETS.index(parameter)] += step
        shifted = KinematicModel(replace(machine, marker_positions=positions), tuple(cameras),
                                 base_motion=fit.base is not None).world_markers(state)[0]
        for c, camera in enumerate(cameras):
            rot = camera.cam_from_world.rotation
            uv = project_cam(shifted[:, m] @ rot.T + camera.cam_from_world.translation, camera.matrix, camera.distortion)
            d_pixel = np.nan_to_num((uv - predicted[c][:, m]) / step)  # (F, 2)
            gradient[:, :, k] += np.einsum("fap,fa->fp", jacobians[c][:, m], d_pixel)
    return np.linalg.solve(hessian + 1e-9 * np.eye(n_params), gradient)
