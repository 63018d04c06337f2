"""The automatic starting point: no initial guess needed.

1. Each camera that sees at least four markers on the base link is placed by PnP of those
   markers over a grid of focal lengths, then a 1-D search of the focal length around the
   best (a user's guess is refined on those markers instead).
2. The joint values follow along the chain: each joint is searched on a grid over its
   limits, keeping a few hypotheses (a beam) scored by the reprojection of every marker on
   the links placed so far, so that an ambiguity at one link is settled by the next. After
   each link the cameras are posed again (PnP, focal length kept) on every marker placed so
   far, so that the next link is searched with cameras that agree with the links before it.
   A joint whose link shows no marker is searched together with the next one that does.
3. Cameras that saw too few base markers are placed by PnP of all their markers, now that
   the machine's pose is known.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from mocap.core.camera import Camera, intrinsic_matrix
from mocap.core.geometry import Rigid
from mocap.core.machine import REVOLUTE, Machine

FOCAL_GRID = np.geomspace(0.2, 12.0, 28)  # focal lengths tried, in image widths
UNPLACED_PX = 1e9  # the RMS the focal search gives a focal length at which PnP places no camera
BEAM = 4
GRID_STEP_DEG = 3.0
MAX_PENDING = 1024  # combinations of unfixed joints' values tried with the next joint
WILD_RMS_PX = 3.0  # a placement's RMS above any pixel noise and tape error of the base: a wild pixel suspected
LEFT_OUT_GAIN = 4.0  # how many times better the others must be explained without one point
LEFT_OUT_TRIED = 8  # points left out in turn, the worst fitted first

log = logging.getLogger(__name__)


def wild_point(points: np.ndarray, pixels: np.ndarray, template: Camera, focal: float | None = None) -> int | None:
    """The one point of N >= 5 whose pixel is wild, or None. A wild pixel bends every
    point's placement (a focal length and pose that split its error): when the placement's
    RMS is far above any pixel noise, the points fitted worst are left out in turn (up to
    LEFT_OUT_TRIED), and the one whose leaving out lets the others be explained several
    times better is named."""
    if len(points) < 5:
        return None
    camera, rms = place_camera(points, pixels, template, focal)
    if rms <= WILD_RMS_PX:
        return None
    worst = np.argsort(-np.linalg.norm(camera.project(points) - pixels, axis=1))[:LEFT_OUT_TRIED]
    best, best_k = rms, None
    for k in worst:
        keep = np.arange(len(points)) != k
        rms_k = place_camera(points[keep], pixels[keep], template, focal)[1]
        if rms_k < best:
            best, best_k = rms_k, int(k)
    if best * LEFT_OUT_GAIN > rms:
        return None
    log.info("camera %s: one of its %d points looks wild (placed at %.2f px rms without it, %.2f px with it)",
             template.name, len(points), best, rms)
    return best_k


def place_camera(
    points: np.ndarray, pixels: np.ndarray, template: Camera, focal: float | None = None
) -> tuple[Camera, float]:
    """A camera from N >= 4 known 3-D points and their pixels, focal length searched when
    not given: PnP on a grid of focal lengths, then a bounded 1-D search of the RMS
    reprojection error around the best. Returns the camera and that RMS (px)."""
    principal = template.matrix[:2, 2]

    def rms_at(f: float) -> float:
        pose = _pnp(points, pixels, intrinsic_matrix(f, principal))
        return np.inf if pose is None else _rms(points, pixels, pose, f, principal)

    if focal is None:
        grid = FOCAL_GRID * template.size[0]
        errors = np.array([rms_at(f) for f in grid])
        if not np.any(np.isfinite(errors)):
            return template, np.inf
        k = int(np.argmin(errors))
        low, high = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        search = minimize_scalar(
            lambda log_f: min(rms_at(np.exp(log_f)), UNPLACED_PX),  # finite: the search's parabola steps stay defined
            bounds=(np.log(low), np.log(high)),
            method="bounded",
            options={"xatol": 1e-4},
        )
        focal = float(np.exp(search.x)) if search.fun <= errors[k] else float(grid[k])
    pose = _pnp(points, pixels, intrinsic_matrix(focal, principal))
    if pose is None:
        return template, np.inf
    camera = Camera(
        template.name,
        template.size,
        intrinsic_matrix(focal, principal),
        np.zeros(5),
        Rigid.from_rotvec(*pose),
    )
    return camera, _rms(points, pixels, pose, focal, principal)


def refine_camera(points: np.ndarray, pixels: np.ndarray, camera: Camera) -> Camera:
    """Rotation, translation and focal length of `camera` refined on N >= 4 known points."""
    principal = camera.matrix[:2, 2]
    pose = camera.cam_from_world

    def residuals(x):
        return (_project(points, x[:3], x[3:6], x[6], principal) - pixels).ravel()

    x0 = np.r_[pose.rotvec, pose.translation, camera.focal]
    x = least_squares(residuals, x0, method="trf", x_scale="jac").x
    return Camera(
        camera.name, camera.size, intrinsic_matrix(abs(x[6]), principal), np.zeros(5),
        Rigid.from_rotvec(x[:3], x[3:6]),
    )


def _pnp(points, pixels, matrix):
    flags = cv2.SOLVEPNP_SQPNP if len(points) >= 3 else cv2.SOLVEPNP_ITERATIVE
    try:
        ok, rvec, tvec = cv2.solvePnP(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(pixels, dtype=np.float64),
            matrix,
            None,
            flags=flags,
        )
    except cv2.error:
        return None
    if not ok:
        return None
    return rvec.reshape(3), tvec.reshape(3)


def _project(points, rvec, tvec, f, principal):
    rotation = cv2.Rodrigues(rvec)[0]
    cam = points @ rotation.T + tvec
    if np.all(cam[:, 2] > 0):
        return f * cam[:, :2] / cam[:, 2:3] + principal
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = f * cam[:, :2] / cam[:, 2:3] + principal
    return np.where(cam[:, 2:3] > 0, uv, 1e6)


def _rms(points, pixels, pose, f, principal):
    uv = _project(points, pose[0], pose[1], f, principal)
    return float(np.sqrt(np.mean(np.sum((uv - pixels) ** 2, axis=1))))


def joint_grid(machine: Machine, j: int) -> np.ndarray:
    """Values tried for joint j: every 3 degrees over a revolute joint's limits, 60 steps
    over a prismatic joint's (±2 m when unbounded)."""
    low, high = machine.joint_limits[j]
    if machine.joints[j].type == REVOLUTE:
        n = int(np.ceil((high - low) / np.radians(GRID_STEP_DEG))) + 1
        return np.linspace(low, high, n)
    low = low if np.isfinite(low) else -2.0
    high = high if np.isfinite(high) else 2.0
    return np.linspace(low, high, 61)


def joints_along_chain(
    machine: Machine, cameras: list[Camera], obs_camera, obs_marker, obs_xy, start: np.ndarray
) -> np.ndarray:
    """Joint values (J,) found link by link with a beam search; `cameras[c]` None for cameras
    not yet placed; `start` (J,) the values used for links not yet reached.

    A joint that no observed marker fixes (its link's markers all unseen) is searched over
    its whole grid together with the next joint that has markers."""
    marker_link = machine.marker_links[obs_marker]
    placed = np.array([cameras[c] is not None for c in obs_camera], dtype=bool)
    beam = [start.astype(float)]
    pending: list[int] = []  # joints passed with no observed marker to fix them
    for j, link in enumerate(machine.joint_links):
        moved = machine.moves[j]
        reached = np.isin(marker_link, [l for l in range(len(machine.links)) if l <= link])
        use = placed & reached
        if not np.any(use & moved[marker_link]):
            pending.append(j)
            continue  # no marker fixes this joint yet; it is searched with the next one
        grid = joint_grid(machine, j)
        earlier = np.stack([_with_pending(machine, b, pending) for b in beam])  # (B, K, J)
        n_beam, n_variants = earlier.shape[:2]
        trial = np.repeat(earlier.reshape(-1, machine.n_joints), len(grid), axis=0)  # (B * K * G, J)
        trial[:, j] = np.tile(grid, n_beam * n_variants)
        # markers that joint j moves are scored at every grid value, the others once per variant
        moving = use & moved[marker_link]
        fixed = use & ~moved[marker_link]
        cost = _grid_cost(machine, cameras, trial, obs_camera[moving], obs_marker[moving], obs_xy[moving])
        if np.any(fixed):
            still = earlier.reshape(-1, machine.n_joints)
            still_cost = _grid_cost(machine, cameras, still, obs_camera[fixed], obs_marker[fixed], obs_xy[fixed])
            cost += np.repeat(still_cost, len(grid))
        cost = cost.reshape(n_beam, n_variants, len(grid))
        best = np.argmin(cost, axis=1)  # (B, G): the best variant of the earlier joints
        trial = trial.reshape(n_beam, n_variants, len(grid), -1)
        hypotheses = []
        for b, row in enumerate(np.min(cost, axis=1)):
            for k in _local_minima(row, 3):
                hypotheses.append((row[k], trial[b, best[b, k], k]))
        hypotheses.sort(key=lambda h: h[0])
        beam = [h[1] for h in hypotheses[:BEAM]]
        pending = []
        if j < machine.n_joints - 1:  # the next links are searched with cameras posed on this one too
            cameras = _reposed(machine, cameras, beam[0], obs_camera[use], obs_marker[use], obs_xy[use])
    return beam[0]


def _reposed(machine, cameras, joints, obs_camera, obs_marker, obs_xy):
    """The placed cameras posed again by PnP (focal length kept) on every marker reached so
    far, at the joint values `joints` (J,) of the best hypothesis."""
    world = machine.markers(joints[None], index=obs_marker)[0]
    out = list(cameras)
    for c, camera in enumerate(cameras):
        rows = obs_camera == c
        if camera is None or np.sum(rows) < 4:
            continue
        pose = _pnp(world[rows], obs_xy[rows], camera.matrix)
        if pose is not None:
            out[c] = camera.with_pose(Rigid(cv2.Rodrigues(pose[0])[0], pose[1]))
    return out


def _with_pending(machine: Machine, joints: np.ndarray, pending: list[int]) -> np.ndarray:
    """Variants (K, J) of a hypothesis `joints` (J,): every combination of the pending
    joints' grids, thinned to at most MAX_PENDING; the hypothesis itself when none pend."""
    if not pending:
        return joints[None]
    grids = [joint_grid(machine, p) for p in pending]
    per_joint = max(2, int(MAX_PENDING ** (1.0 / len(grids))))
    grids = [g[:: max(1, int(np.ceil(len(g) / per_joint)))] for g in grids]
    combos = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, len(grids))
    out = np.repeat(joints[None], len(combos), axis=0)
    out[:, pending] = combos
    return out


def _grid_cost(machine, cameras, joints, obs_camera, obs_marker, obs_xy) -> np.ndarray:
    """Robust reprojection cost (G,) of the observed markers for G joint vectors (G, J)."""
    world = machine.markers(joints, index=obs_marker)  # (G, N, 3)
    cost = np.zeros(len(joints))
    for c in np.unique(obs_camera):
        rows = obs_camera == c
        uv = cameras[c].project(world[:, rows])
        err = np.linalg.norm(uv - obs_xy[rows], axis=-1)
        err = np.where(np.isfinite(err), err, 1e4)
        cost += np.sum(np.log1p((err / 5.0) ** 2), axis=1)  # Cauchy: a wrong marker counts little
    return cost


def _local_minima(cost: np.ndarray, k: int) -> list[int]:
    """Indices of up to k lowest local minima of a 1-D cost."""
    left = np.concatenate(([np.inf], cost[:-1]))
    right = np.concatenate((cost[1:], [np.inf]))
    minima = np.nonzero((cost <= left) & (cost <= right))[0]
    return list(minima[np.argsort(cost[minima])][:k])
