"""Where a calibration's fit starts: the cameras placed by PnP on the base link's markers,
the joint values searched along the chain, and the new starts tried when a fit named
outliers or left its residuals above the noise (the cameras placed again, a joint swept
across its range)."""

from __future__ import annotations

import logging
from dataclasses import replace

import cv2
import numpy as np

from mocap.calibration import initial
from mocap.calibration.context import CalibrationResult, FitContext
from mocap.calibration.problem import Layout, Observations
from mocap.core.camera import Camera, PaperCamera
from mocap.core.guess import Guess
from mocap.core.machine import Machine

log = logging.getLogger(__name__)


def starting_point(context: FitContext) -> np.ndarray:
    """The parameter vector (P,) to start the fit from, found from the context's observations alone."""
    machine, observations, templates, options = context.machine, context.observations, context.templates, context.options
    groups = [[c] for c in range(len(templates))] if options.per_camera else [list(range(len(templates)))]
    cameras: list[Camera | None] = [None] * len(templates)
    joints = np.zeros((len(templates), machine.n_joints)) if options.per_camera else None
    for group in groups:
        mask = np.isin(observations.camera, group)
        placed, q = _start(machine, observations.select(mask), templates, group, context.guess,
                           options.fixed_intrinsics)
        for c in group:
            cameras[c] = placed[c]
            if templates[c].name in options.fixed_intrinsics:  # a guess's focal length gives way to the known one
                cameras[c] = replace(templates[c], cam_from_world=placed[c].cam_from_world)
        if options.per_camera:
            joints[group[0]] = q
        else:
            joints = q
    return context.layout.pack(cameras, joints)


def _start(machine, obs: Observations, templates, group, guess: Guess | None, known=frozenset()):
    """Starting cameras (a list by camera index, None outside `group`) and joint values for
    the cameras in `group`; the cameras named in `known` keep their templates' intrinsics."""
    cameras: list[Camera | None] = [None] * len(templates)
    base = machine.marker_links[obs.marker] == 0
    if guess is not None and guess.cameras:
        for c in group:
            paper: PaperCamera = guess.cameras[templates[c].name]
            cameras[c] = Camera.from_paper(
                templates[c].name, templates[c].size, paper, tuple(templates[c].matrix[:2, 2])
            )
            rows = (obs.camera == c) & base
            if guess.joints is None and np.sum(rows) >= 4:
                cameras[c] = initial.refine_camera(
                    machine.marker_positions[obs.marker[rows]], obs.xy[rows], cameras[c]
                )
    else:
        for c in group:
            rows = (obs.camera == c) & base
            if np.sum(rows) >= 4:
                cameras[c], rms = placed_camera(machine.marker_positions[obs.marker[rows]], obs.xy[rows],
                                                templates[c], known)
                log.info("camera %s placed from the base link, rms %.2f px", templates[c].name, rms)
    start = neutral_joints(machine)
    if guess is not None and guess.joints is not None:
        joints = machine.clip_to_limits(np.asarray(guess.joints, dtype=float))
    else:
        joints = initial.joints_along_chain(machine, cameras, obs.camera, obs.marker, obs.xy, start)
    for c in group:
        if cameras[c] is None:
            rows = obs.camera == c
            world = machine.markers(joints[None])[0][obs.marker[rows]]
            cameras[c], rms = placed_camera(world, obs.xy[rows], templates[c], known)
            log.info("camera %s placed from all its markers, rms %.2f px", templates[c].name, rms)
    return cameras, joints


def wild_base_pixels(context: FitContext) -> list[int]:
    """The observations (indices) that look wild among each camera's five or more base
    markers (`initial.wild_point`, on the pixels undistorted for a known lens)."""
    machine, observations, known = context.machine, context.observations, context.options.fixed_intrinsics
    base = machine.marker_links[observations.marker] == 0
    wild = []
    for c, template in enumerate(context.templates):
        rows = np.flatnonzero((observations.camera == c) & base)
        if len(rows) < 5:
            continue
        pixels, focal = observations.xy[rows], None
        if template.name in known:
            pixels, focal = undistorted(pixels, template), template.focal
        k = initial.wild_point(machine.marker_positions[observations.marker[rows]], pixels, template, focal)
        if k is not None:
            wild.append(int(rows[k]))
    return wild


def chained_start(context: FitContext, x0: np.ndarray) -> np.ndarray | None:
    """The start x0 (P,) again where some camera saw fewer than four base markers (placed
    at joint values the others fixed alone): the joints searched along the chain with every
    camera as placed, then those cameras placed again on all their markers at these joint
    values. None when every camera was placed from the base link."""
    machine, observations, templates, layout = context.machine, context.observations, context.templates, context.layout
    cameras, joints = layout.unpack(x0, templates)
    base = machine.marker_links[observations.marker] == 0
    late = [c for c in range(len(templates)) if np.sum((observations.camera == c) & base) < 4]
    if not late:
        return None
    joints = initial.joints_along_chain(machine, cameras, observations.camera, observations.marker, observations.xy,
                                        joints)
    world = machine.markers(joints[None])[0]
    for c in late:
        rows = observations.camera == c
        placed, rms = placed_camera(world[observations.marker[rows]], observations.xy[rows], templates[c],
                                    context.options.fixed_intrinsics)
        if np.isfinite(rms):
            cameras[c] = placed
    return layout.pack(cameras, joints)


def replaced_cameras(context: FitContext, result: CalibrationResult, doubtful) -> list[Camera]:
    """The result's cameras, those in `doubtful` placed again by PnP of all their markers at
    the fitted joint values."""
    observations = context.observations
    cameras = list(result.cameras)
    for c in doubtful:
        joints = result.joints[c] if result.per_camera else result.joints
        rows = observations.camera == c
        world = result.machine.markers(np.asarray(joints)[None])[0][observations.marker[rows]]
        placed, rms = placed_camera(world, observations.xy[rows], context.templates[c],
                                    context.options.fixed_intrinsics)
        if np.isfinite(rms):
            cameras[c] = placed
    return cameras


def worst_links_markers(context: FitContext, result: CalibrationResult, links: int = 1) -> np.ndarray:
    """The markers (indices) of the `links` moving links whose observations' residuals have
    the largest RMS (outliers left out)."""
    machine = context.machine
    error = np.array([np.linalg.norm(r.residual) if not r.outlier else np.nan for r in result.residuals])
    link = machine.marker_links[context.observations.marker]
    moving = [k for k in np.unique(link) if k != 0 and np.isfinite(error[link == k]).any()]
    rms = [np.sqrt(np.nanmean(error[link == k] ** 2)) for k in moving]
    worst = [moving[i] for i in np.argsort(rms)[::-1][:links]]
    return np.flatnonzero(np.isin(machine.marker_links, worst))


def swept_joints(context: FitContext, result: CalibrationResult, dropped: np.ndarray) -> list:
    """Starts (callables of no argument) with the joint of each dropped marker's link set
    across its range, the rest as fitted: that joint's mirror solutions."""
    machine, layout = context.machine, context.layout
    cameras = list(result.cameras)
    limits = machine.joint_limits
    lower = np.where(np.isfinite(limits[:, 0]), limits[:, 0], -1.0)
    upper = np.where(np.isfinite(limits[:, 1]), limits[:, 1], 1.0)
    out = []
    own_joint = {int(link): j for j, link in enumerate(machine.joint_links)}  # the joint that moves each link
    for j in sorted({own_joint[int(link)] for link in machine.marker_links[dropped] if int(link) in own_joint}):
        for level in (np.arange(6) + 0.5) / 6:
            joints = np.array(result.joints, dtype=float)
            joints[j] = lower[j] + level * (upper[j] - lower[j])
            out.append(lambda joints=joints: layout.pack(cameras, joints))
    return out


def neutral_joints(machine: Machine) -> np.ndarray:
    """Zero where the limits allow it, else the middle of the limits."""
    limits = machine.joint_limits
    middle = np.where(np.isfinite(limits).all(axis=1), limits.mean(axis=1), 0.0)
    return np.where((limits[:, 0] <= 0) & (limits[:, 1] >= 0), 0.0, middle)


def bounds_and_start(layout: Layout, machine: Machine, x0: np.ndarray):
    """The parameters' bounds (focal lengths positive, joints within their limits) and x0
    (P,) clipped just inside them."""
    lower = np.full(layout.size, -np.inf)
    upper = np.full(layout.size, np.inf)
    for c in range(layout.n_cameras):
        lower[layout.camera_slice(c).start + 6] = 1.0  # focal length stays positive
    limits = machine.joint_limits
    for c in range(layout.n_cameras if layout.per_camera else 1):
        s = layout.joint_slice(c)
        lower[s], upper[s] = limits[:, 0], limits[:, 1]
    x0 = np.clip(x0, lower + 1e-9 * np.isfinite(lower), upper - 1e-9 * np.isfinite(upper))
    return (lower, upper), x0


def placed_camera(points: np.ndarray, pixels: np.ndarray, template: Camera,
                  known=frozenset()) -> tuple[Camera, float]:
    """A camera placed by PnP on known points; one with known intrinsics (named in `known`)
    keeps its template's focal length and distortion (the pixels undistorted for the PnP)."""
    if template.name not in known:
        return initial.place_camera(points, pixels, template)
    placed, rms = initial.place_camera(points, undistorted(pixels, template), template, focal=template.focal)
    return Camera(template.name, template.size, template.matrix, template.distortion, placed.cam_from_world), rms


def undistorted(pixels: np.ndarray, template: Camera) -> np.ndarray:
    """(N, 2) pixels through the template's lens undistorted, in its pinhole's pixels."""
    return cv2.undistortPoints(np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2),
                               template.matrix, template.distortion, P=template.matrix).reshape(-1, 2)
