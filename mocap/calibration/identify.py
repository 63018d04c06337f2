"""Identifiability: the paper's counts before a fit, the Jacobian's rank and conditioning after.

A degenerate set of observations raises DegenerateError naming the cause, never a silently
wrong answer.
"""

from __future__ import annotations

import numpy as np

from mocap.core.machine import Machine
from mocap.errors import DegenerateError

COLLINEAR_RATIO = 1e-3  # second / first singular value of centred points below which they are a line
RANK_TOL = 1e-10  # relative singular value treated as zero
CONDITION_LIMIT = 1e7  # condition number of the column-scaled Jacobian beyond which we refuse


def check_counts(
    machine: Machine,
    camera_names: list[str],
    obs_camera: np.ndarray,
    obs_marker: np.ndarray,
    per_camera: bool,
    camera_unknowns: int,
) -> None:
    """The paper's counting rules, per camera and per joint, before any fit."""
    marker_link = machine.marker_links[obs_marker]
    base_ok = []
    for c, name in enumerate(camera_names):
        mine = obs_camera == c
        markers = np.unique(obs_marker[mine])
        if len(markers) < 4:
            raise DegenerateError(
                f"camera {name!r} sees {len(markers)} marker(s): its {camera_unknowns} "
                f"parameters need at least 4 non-coplanar markers ({2 * len(markers)} equations "
                f"for {camera_unknowns} unknowns); use a frame where it sees more"
            )
        base = np.unique(obs_marker[mine & (marker_link == 0)])
        base_ok.append(len(base) >= 4)
        if len(base) >= 3:
            _check_not_collinear(machine, base, name)
    if per_camera and not all(base_ok):
        name = camera_names[base_ok.index(False)]
        raise DegenerateError(
            f"camera {name!r} sees fewer than 4 markers on the base link "
            f"{machine.links[0].name!r}: with --per-camera each camera must be placed by the base "
            "alone; calibrate the cameras together instead"
        )
    if not any(base_ok):
        raise DegenerateError(
            f"no camera sees 4 or more markers on the base link {machine.links[0].name!r}: the "
            "base needs at least 4 non-coplanar markers to fix the world frame"
        )
    groups = [obs_camera == c for c in range(len(camera_names))] if per_camera else [slice(None)]
    for g, group in enumerate(groups):
        seen_links = set(marker_link[group].tolist())
        moves = machine.moves
        for j, joint in enumerate(machine.joints):
            if not any(moves[j, l] for l in seen_links):
                who = f" by camera {camera_names[g]!r}" if per_camera else ""
                raise DegenerateError(
                    f"joint {joint.name!r} is unknown but no marker on link "
                    f"{machine.links[machine.joint_links[j]].name!r} or beyond it is seen{who}; "
                    "each moving link needs at least one observed marker"
                )
        n_moving = len(np.unique(obs_marker[group][marker_link[group] > 0]))
        if n_moving < machine.n_joints:
            raise DegenerateError(
                f"{n_moving} marker(s) seen on moving links for {machine.n_joints} unknown joint "
                "values: each moving link adds one unknown and needs one more marker"
            )


def _check_not_collinear(machine: Machine, markers: np.ndarray, camera: str) -> None:
    points = machine.marker_positions[markers]
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if s[0] == 0 or s[1] / s[0] < COLLINEAR_RATIO:
        names = ", ".join(machine.marker_names[m] for m in markers)
        raise DegenerateError(
            f"markers {names} seen by camera {camera!r} on the base link lie on a line: they "
            "cannot fix the camera; paint markers spread over the link's surfaces"
        )


def check_jacobian(jacobian: np.ndarray, names: list[str], kinds: list[tuple]) -> tuple[int, float]:
    """Rank and condition number of the column-scaled Jacobian; raises when degenerate.

    `kinds[i]` is ("camera", camera, parameter) or ("joint", camera or None, joint) for
    parameter i. The right singular vector of the smallest singular value names the
    parameters that the observations cannot tell apart.
    """
    scale = np.linalg.norm(jacobian, axis=0)
    zero = np.nonzero(scale == 0)[0]
    if len(zero):
        raise DegenerateError(_cause([names[i] for i in zero], [kinds[i] for i in zero]))
    _, s, vt = np.linalg.svd(jacobian / scale, full_matrices=False)
    rank = int(np.sum(s > RANK_TOL * s[0]))
    condition = float(s[0] / s[-1]) if s[-1] > 0 else np.inf
    if rank < len(names) or condition > CONDITION_LIMIT:
        weights = np.abs(vt[-1])
        order = [i for i in np.argsort(weights)[::-1] if weights[i] > 0.2]
        raise DegenerateError(_cause([names[i] for i in order], [kinds[i] for i in order], condition))
    return rank, condition


def inverse_information(information: np.ndarray) -> np.ndarray:
    """(..., P, P) the covariance from an information matrix (..., P, P), inverted after
    scaling its diagonal to one: parameters of unlike units (radians, metres, a focal length
    of 10^5 px) make the raw matrix's condition pass 1e15, where a plain pseudo-inverse
    drops the weak directions (a camera's distance along its line of sight) and states a
    standard deviation a hundred times too small. Directions of no information at all
    (gauge) stay zero."""
    diagonal = np.diagonal(information, axis1=-2, axis2=-1)
    scale = np.where(diagonal > 0, 1.0 / np.sqrt(np.where(diagonal > 0, diagonal, 1.0)), 0.0)
    scaled = information * scale[..., :, None] * scale[..., None, :]
    return np.linalg.pinv(scaled, rcond=1e-12, hermitian=True) * scale[..., :, None] * scale[..., None, :]


def _cause(names: list[str], kinds: list[tuple], condition: float | None = None) -> str:
    """A sentence naming what cannot be determined, from the parameters involved."""
    how = "" if condition is None else f" (condition number {condition:.1e})"
    joints = [k[2] for k in kinds if k[0] == "joint"]
    camera_params = [k for k in kinds if k[0] == "camera"]
    cameras = sorted({k[1] for k in camera_params})
    if joints and not camera_params:
        return (
            f"the markers cannot fix joint(s) {', '.join(joints)}{how}: their markers lie on the "
            "joint axis or move too little with it; paint markers away from the axis"
        )
    if any(k[2] == "f" for k in camera_params):
        return (
            f"focal length and distance of camera(s) {', '.join(cameras)} cannot be told apart"
            f"{how}: the markers seen are nearly a plane facing the camera or too shallow in "
            "depth; use a view where the machine shows depth, or give the focal length"
        )
    return (
        f"the observations do not determine {', '.join(names)}{how}: the markers seen are "
        "degenerate (collinear, coplanar or too few); use more, better spread markers"
    )
