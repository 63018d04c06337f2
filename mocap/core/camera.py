"""Cameras: the OpenCV pinhole model with distortion, and the paper's 7-parameter view.

OpenCV convention (how cameras are stored): ``x_cam = R @ X_world + t`` with the camera's z
axis forward, x right, y down; pixels ``u = fx * x' + s * y' + cx``, ``v = fy * y' + cy``
where (x', y') are the distorted normalised coordinates (k1, k2, p1, p2, k3). The centre of
the top-left pixel is (0, 0).

The paper's view (PAPER.md): camera frame {C} with its X axis the optical axis, Y to the
left and Z up (right-handed), orientation ``world_from_paper = Rz(azimuth) Ry(elevation)
Rx(tilt)``, position (X_C, Y_C, Z_C) in the world, and image coordinates measured from the
principal point: ``x = M * y_C / x_C`` (positive leftward) and ``y = M * z_C / x_C``
(positive upward), so ``x = cx - u`` and ``y = cy - v`` for an undistorted camera with
``fx = fy = M``. A positive elevation turns the optical axis downward (right-hand rule
about y). The conversion between the two views is exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mocap.core.geometry import Rigid

# paper camera axes -> OpenCV camera axes: x_cv = -Y_p, y_cv = -Z_p, z_cv = X_p
# the lens models a fit may free: their coefficients' places in OpenCV's (k1, k2, p1, p2, k3)
DISTORTION_MODELS = {"none": (), "k1": (0,), "k1k2": (0, 1), "full": (0, 1, 2, 3, 4)}
CV_FROM_PAPER = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class PaperCamera:
    """The paper's 7 parameters: angles in rad, position in metres, M in pixels."""

    azimuth: float
    elevation: float
    tilt: float
    position: np.ndarray
    focal: float

    def __post_init__(self) -> None:
        position = np.asarray(self.position, dtype=float)
        if position.shape != (3,):
            raise ValueError(f"PaperCamera.position must have shape (3,), got {position.shape}")
        object.__setattr__(self, "position", position)

    def as_vector(self) -> np.ndarray:
        """(7,) = azimuth, elevation, tilt (rad), X_C, Y_C, Z_C (m), M (px)."""
        return np.r_[self.azimuth, self.elevation, self.tilt, self.position, self.focal]

    @classmethod
    def from_vector(cls, vector: np.ndarray) -> PaperCamera:
        v = np.asarray(vector, dtype=float)
        return cls(v[0], v[1], v[2], v[3:6], v[6])


@dataclass(frozen=True)
class Camera:
    """One calibrated camera.

    Attributes: `name`; `size` (width, height) px; `matrix` K (3, 3); `distortion` (5,)
    k1, k2, p1, p2, k3; `cam_from_world` the rigid transform world -> OpenCV camera frame.
    """

    name: str
    size: tuple[int, int]
    matrix: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    cam_from_world: Rigid = field(default_factory=Rigid.identity)

    def __post_init__(self) -> None:
        matrix = np.asarray(self.matrix, dtype=float)
        distortion = np.asarray(self.distortion, dtype=float).reshape(-1)
        if matrix.shape != (3, 3):
            raise ValueError(f"camera {self.name!r}: matrix must be (3, 3), got {matrix.shape}")
        if distortion.shape[0] > 5:
            raise ValueError(f"camera {self.name!r}: at most 5 distortion coefficients")
        distortion = np.r_[distortion, np.zeros(5 - distortion.shape[0])]
        object.__setattr__(self, "matrix", matrix)
        object.__setattr__(self, "distortion", distortion)
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))

    @property
    def center(self) -> np.ndarray:
        """Camera centre in the world frame (3,)."""
        return self.cam_from_world.inverse().translation

    @property
    def focal(self) -> float:
        """Mean of fx and fy (px)."""
        return 0.5 * (self.matrix[0, 0] + self.matrix[1, 1])

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixels of world points (*, 3) -> (*, 2); NaN for points at or behind the camera."""
        points_cam = self.cam_from_world.apply(points_world)
        return project_cam(points_cam, self.matrix, self.distortion)

    def with_pose(self, cam_from_world: Rigid) -> Camera:
        return replace(self, cam_from_world=cam_from_world)

    def to_paper(self) -> PaperCamera:
        """The paper's view: exact when fx == fy, no skew and no distortion (M = mean focal)."""
        from scipy.spatial.transform import Rotation  # here: scipy.spatial takes a while to import

        world_from_paper = self.cam_from_world.rotation.T @ CV_FROM_PAPER
        azimuth, elevation, tilt = Rotation.from_matrix(world_from_paper).as_euler("ZYX")
        return PaperCamera(azimuth, elevation, tilt, self.center, self.focal)

    @classmethod
    def from_paper(
        cls,
        name: str,
        size: tuple[int, int],
        paper: PaperCamera,
        principal_point: tuple[float, float] | None = None,
        distortion: np.ndarray | None = None,
    ) -> Camera:
        """OpenCV camera from the paper's parameters; principal point defaults to the image centre."""
        if principal_point is None:
            principal_point = default_principal_point(size)
        from scipy.spatial.transform import Rotation

        world_from_paper = Rotation.from_euler(
            "ZYX", [paper.azimuth, paper.elevation, paper.tilt]
        ).as_matrix()
        cam_from_world_rotation = CV_FROM_PAPER @ world_from_paper.T
        translation = -cam_from_world_rotation @ paper.position
        matrix = intrinsic_matrix(paper.focal, principal_point)
        return cls(
            name,
            size,
            matrix,
            np.zeros(5) if distortion is None else distortion,
            Rigid(cam_from_world_rotation, translation),
        )


def default_principal_point(size: tuple[int, int]) -> tuple[float, float]:
    """The image centre in OpenCV pixels (top-left pixel centre at 0, 0)."""
    return ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0)


def intrinsic_matrix(focal: float, principal_point: tuple[float, float]) -> np.ndarray:
    return np.array(
        [[focal, 0.0, principal_point[0]], [0.0, focal, principal_point[1]], [0.0, 0.0, 1.0]]
    )


def project_cam(
    points_cam: np.ndarray, matrix: np.ndarray, distortion: np.ndarray, with_jacobian: bool = False
):
    """Pixels of camera-frame points.

    points_cam: (*, 3) in the OpenCV camera frame; matrix (3, 3); distortion (5,).
    Returns uv (*, 2), NaN where z <= 0 or the input is NaN; with `with_jacobian` also
    d(uv)/d(points_cam) of shape (*, 2, 3).
    """
    p = np.asarray(points_cam, dtype=float)
    z = p[..., 2]
    behind = ~(z > 0)
    z_safe = np.where(behind, np.nan, z)
    x = p[..., 0] / z_safe
    y = p[..., 1] / z_safe
    fx, s, cx = matrix[0]
    fy, cy = matrix[1, 1], matrix[1, 2]
    if not np.any(distortion):  # the pinhole alone
        uv = np.stack([fx * x + s * y + cx, fy * y + cy], axis=-1)
        if not with_jacobian:
            return uv
        inv_z = 1.0 / z_safe
        jac = np.zeros(p.shape[:-1] + (2, 3))
        jac[..., 0, 0] = fx * inv_z
        jac[..., 0, 1] = s * inv_z
        jac[..., 0, 2] = -(fx * x + s * y) * inv_z
        jac[..., 1, 1] = fy * inv_z
        jac[..., 1, 2] = -fy * y * inv_z
        return uv, jac
    uv = np.stack(distorted(x, y, matrix, distortion), axis=-1)
    if not with_jacobian:
        return uv
    jac = np.stack(distorted_jacobian(x, y, 1.0 / z_safe, matrix, distortion), axis=-1)
    return uv, jac.reshape(p.shape[:-1] + (2, 3))


def distorted(x, y, matrix, distortion):
    """The pixel (u, v) of normalised coordinates x, y (scalars or arrays alike) through the
    OpenCV lens (k1, k2, p1, p2, k3) and `matrix` (3, 3). The one lens model: `project_cam`
    runs it on arrays, numba compiles it for the kernels (`camera_kernel.project_point`)."""
    fx, s, cx = matrix[0, 0], matrix[0, 1], matrix[0, 2]
    fy, cy = matrix[1, 1], matrix[1, 2]
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return fx * xd + s * yd + cx, fy * yd + cy


def distorted_jacobian(x, y, inv_z, matrix, distortion):
    """d(u, v) / d(X, Y, Z) of the camera-frame point (X, Y, Z) = (x, y, 1) / inv_z through
    `distorted`, as its six entries row by row (du/dX, du/dY, du/dZ, dv/dX, dv/dY, dv/dZ);
    scalars or arrays alike, as `distorted`."""
    fx, s = matrix[0, 0], matrix[0, 1]
    fy = matrix[1, 1]
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    dxd_dx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    du_dx = fx * dxd_dx + s * dyd_dx
    du_dy = fx * dxd_dy + s * dyd_dy
    dv_dx = fy * dyd_dx
    dv_dy = fy * dyd_dy
    # (x, y) = (X / Z, Y / Z): d/dX = (1/Z, 0), d/dY = (0, 1/Z), d/dZ = (-x/Z, -y/Z)
    return (du_dx * inv_z, du_dy * inv_z, -(du_dx * x + du_dy * y) * inv_z,
            dv_dx * inv_z, dv_dy * inv_z, -(dv_dx * x + dv_dy * y) * inv_z)


def project(cameras: list[Camera], points_world: np.ndarray) -> np.ndarray:
    """Pixels of world points in every camera: points (*, N, 3) -> (C, *, N, 2), NaN-aware."""
    return np.stack([camera.project(points_world) for camera in cameras])
