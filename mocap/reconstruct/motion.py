"""From resampled pixels to the machine's motion: kinematic fit, smoothing, named points
with uncertainties, velocities; the pure core of `mocap fit`.

Motion extra columns (DESIGN.md motion CSV): ``filled`` (1 where the smoother predicted
a frame across a gap or a joint that was not observed), ``<point>_speed`` (m/s) and
``<point>_acceleration`` (m/s², magnitude) with smoothing, ``rms_px`` (the fit's residual
RMS), ``observations`` (2-D observations used) and ``unexplained`` (1 where no solution
explains the frame's pixels within the noise: the smoother treats the frame as missing).

With a stated tolerance (the fit options' or the model's) the markers' offsets from their
measured positions are estimated over the session (mocap.reconstruct.offsets) and their
uncertainty, common to all frames, is added to every frame's after smoothing; so is the
calibration's (its covariance of the cameras, and of the markers' offsets where refine
estimated them: mocap.reconstruct.camera_share), an error common to all frames too. With
none stated (nor an exact model stated, a tolerance of 0), markers that the exact model's
fit leaves off in every frame (`mocap.reconstruct.offsets.markers_off`, three or more) have
their offsets estimated within the paper's tape tolerance, ±5 %, with a warning.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.core.motion import Motion
from mocap.io.motion_csv import base_columns
from mocap.reconstruct.base_check import BaseCheck, check_base_motion
from mocap.reconstruct.camera_share import CameraCovariance, camera_share
from mocap.reconstruct.kinfit import FitOptions, JointFit, fit_joints
from mocap.reconstruct.kinmodel import base_matrices
from mocap.reconstruct.offsets import ASSUMED_TOLERANCE, SHOWN_MARKERS, MarkerOffsets, fit_with_offsets, markers_off
from mocap.reconstruct.smooth import Smoothed, SmoothOptions, scatter_scale, smooth
from mocap.reconstruct.uncertainty import point_quantities

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MotionResult:
    """motion: the Motion to write; fit: the per-frame JointFit; smoothed: Smoothed or None;
    offsets: the markers' estimated offsets (MarkerOffsets) with a stated tolerance (or
    with none stated, where the exact model's fit leaves markers off), else None (the fit
    is then of the model with its markers moved by them); base_check: with
    `choose_base`, the check of a fixed base against a moving one (BaseCheck), else None."""

    motion: Motion
    fit: JointFit
    smoothed: Smoothed | None
    offsets: MarkerOffsets | None = None
    base_check: BaseCheck | None = None


def reconstruct_motion(
    machine: Machine,
    cameras: list[Camera],
    frame: np.ndarray,
    time: np.ndarray,
    pixels: np.ndarray,
    fit_options: FitOptions | None = None,
    smooth_options: SmoothOptions | None = None,
    smoothing: bool = True,
    initial: np.ndarray | None = None,
    choose_base: bool = False,
    camera_covariance: CameraCovariance | None = None,
) -> MotionResult:
    """Fit, smooth and measure the machine's motion.

    frame (F,) reference frames; time (F,) s; pixels (C, F, M, 2) on the reference clock.
    With `choose_base` and a fixed base in `fit_options`, the base is fitted per frame
    instead when a sample of frames says it moves (`mocap.reconstruct.base_check`).
    `camera_covariance`: the calibration's, carried into every frame's SDs.
    """
    fit_options = fit_options or FitOptions()
    fit, offsets, shared = _fit(machine, cameras, pixels, fit_options, initial)
    check = None
    if choose_base and not fit_options.base_motion:
        fitted = machine if offsets is None else offsets.apply(machine)
        check = check_base_motion(fitted, cameras, pixels, fit, fit_options)
        if check is not None and check.moves:
            start = np.where(np.isfinite(fit.joints), fit.joints, np.nan_to_num(np.nanmedian(fit.joints, axis=0)))
            fit_options = replace(fit_options, base_motion=True)
            fit, offsets, shared = _fit(machine, cameras, pixels, fit_options, start)
    if offsets is not None:  # the markers' offsets estimated here: the calibration's cameras' part only
        camera_covariance = None if camera_covariance is None else camera_covariance.with_cameras(cameras)
    shared = shared + camera_share(machine if offsets is None else offsets.apply(machine), cameras, fit,
                                   camera_covariance)
    base_motion = fit.base is not None
    values = fit.joints if not base_motion else np.c_[fit.joints, fit.base]
    n_joints = machine.n_joints
    extra = {
        "rms_px": fit.rms_px,
        "observations": fit.n_observations.astype(float),
        "unexplained": (fit.valid & ~fit.explained).astype(float),
    }
    smoothed = None
    if smoothing and len(frame) > 1:
        wrap = np.r_[machine.wraps, np.zeros(6 * base_motion, bool)]
        smoothed = smooth(time, values, fit.information, fit.valid & fit.explained, wrap=wrap, options=smooth_options)
        scale, factor, rho = scatter_scale(values, fit.information, fit.valid & fit.explained & ~smoothed.filled,
                                           smoothed, wrap)
        if scale > 1.0:
            log.info("the fits scatter about the smoothed path %.2f times what their information says and their "
                     "deviations correlate %.2f from frame to frame: the smoothed SDs scaled by %.2f",
                     factor, rho, np.sqrt(scale))
        values = smoothed.values
        covariance = smoothed.covariance * scale
        limits = machine.joint_limits
        span = limits[:, 1] - limits[:, 0]
        joints = values[:, :n_joints]
        wrapped = limits[:, 0] + np.mod(joints - limits[:, 0], np.where(machine.wraps, span, 1.0))
        values = np.c_[np.where(machine.wraps, wrapped, joints), values[:, n_joints:]]
        covariance = covariance + shared
        quantities = point_quantities(machine, values, covariance, base_motion, smoothed.velocities)
        extra["filled"] = smoothed.filled.astype(float)
        for k, name in enumerate(machine.point_names):
            speed = quantities.speed[:, k]
            acceleration = np.gradient(quantities.velocities[:, k], time, axis=0) if len(time) > 2 else np.zeros((len(time), 3))
            extra[f"{name}_speed"] = speed
            extra[f"{name}_acceleration"] = np.linalg.norm(acceleration, axis=-1)
    else:
        covariance = fit.covariance + shared
        quantities = point_quantities(machine, values, covariance, base_motion)
    if base_motion:
        extra.update(base_columns(base_matrices(values[:, n_joints:]), covariance[:, n_joints:, n_joints:]))
    joints_sd = np.sqrt(np.diagonal(covariance, axis1=1, axis2=2)[:, :n_joints])
    motion = Motion(
        joint_names=machine.joint_names,
        point_names=machine.point_names,
        frame=np.asarray(frame, dtype=int),
        time=np.asarray(time, dtype=float),
        joints=values[:, :n_joints],
        points=quantities.points,
        bucket_angle=quantities.bucket_angle,
        joints_sd=joints_sd,
        points_sd=quantities.points_sd,
        bucket_angle_sd=quantities.bucket_angle_sd,
        extra=extra,
    )
    return MotionResult(motion, fit, smoothed, offsets, check)


def _fit(machine: Machine, cameras: list[Camera], pixels: np.ndarray, options: FitOptions,
         initial: np.ndarray | None):
    """The per-frame fit, with the markers' offsets estimated when a tolerance is stated
    or, with none stated, the exact model's fit leaves markers off (`markers_off`):
    (JointFit, MarkerOffsets or None, what the offsets add to each frame's covariance)."""
    if options.tolerance_of(machine):
        result = fit_with_offsets(machine, cameras, pixels, initial=initial, options=options)
        return result.fit, result.offsets, result.shared
    fit = fit_joints(machine, cameras, pixels, initial=initial, options=options)
    off = markers_off(fit) if options.tolerance is None else np.zeros(0, bool)  # an exact model stated stays exact
    if off.sum() < SHOWN_MARKERS:
        return fit, None, 0.0
    log.warning("%d markers (%s) sit off their measured positions in every frame, beyond the pixel noise, and no "
                "tolerance is stated: their offsets are estimated within the paper's %g %% (state --tolerance, or "
                "`tolerance` in the model file)", off.sum(), ", ".join(np.asarray(machine.marker_names)[off][:5]),
                100 * ASSUMED_TOLERANCE.fraction)
    result = fit_with_offsets(machine, cameras, pixels, initial=initial,
                              options=replace(options, tolerance=ASSUMED_TOLERANCE))
    return result.fit, result.offsets, result.shared
