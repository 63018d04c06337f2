"""A calibration result as the calibration file, the reference points and a text report."""

from __future__ import annotations

import numpy as np

from mocap.calibration.dlt import DltResult
from mocap.calibration.solve import CalibrationResult
from mocap.core.calibration import Calibration, joints_to_table
from mocap.core.camera import Camera
from mocap.core.machine import REVOLUTE, Machine
from mocap.core.points import Points
from mocap.reconstruct.camera_share import CameraCovariance

_DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


def paper_table(camera: Camera, sd: np.ndarray | None = None) -> dict:
    """The paper's 7 parameters of a camera in file units (degrees, metres, pixels)."""
    paper = camera.to_paper()
    table = {
        "azimuth_deg": float(np.degrees(paper.azimuth)),
        "elevation_deg": float(np.degrees(paper.elevation)),
        "tilt_deg": float(np.degrees(paper.tilt)),
        "position": paper.position.tolist(),
        "focal_px": float(paper.focal),
    }
    if sd is not None:
        table["sd"] = {
            "azimuth_deg": float(np.degrees(sd[0])),
            "elevation_deg": float(np.degrees(sd[1])),
            "tilt_deg": float(np.degrees(sd[2])),
            "position": sd[3:6].tolist(),
            "focal_px": float(sd[6]),
        }
    return table


def _joint_sd_table(sd: np.ndarray, machine: Machine) -> dict:
    return {
        j.name: float(np.degrees(s) if j.type == REVOLUTE else s) for j, s in zip(machine.joints, sd)
    }


def to_calibration(result: CalibrationResult, frame: int) -> Calibration:
    """The DESIGN.md calibration file of a model-based result."""
    machine = result.machine
    std = result.std
    names = result.parameter_names
    extras = []
    for c, camera in enumerate(result.cameras):
        prefix = f"{camera.name}."
        camera_sd = {n[len(prefix) :]: float(s) for n, s in zip(names, std) if n.startswith(prefix)}
        sd = {
            "rotation": [camera_sd[f"r{a}"] for a in "xyz"],
            "translation": [camera_sd[f"t{a}"] for a in "xyz"],
            "focal_px": camera_sd["f"],
        }
        sd.update({k: camera_sd[k] for k in ("cx", "cy", *_DISTORTION_NAMES) if k in camera_sd})
        extra = {
            "error": result.camera_rms(camera.name),
            "sd": sd,
            "paper": paper_table(camera, result.paper_sd[c]),
        }
        if result.per_camera:
            extra["joints"] = joints_to_table(result.joints[c], machine)
            extra["joints_sd"] = _joint_sd_table(result.joints_sd[c], machine)
        extras.append(extra)
    metadata = {
        "machine": machine.name,
        "method": "model",
        "frame": int(frame),
        "error": result.rms_px,
        "sigma_px": result.sigma_px,
        "condition": result.condition,
        "outliers": [f"{r.camera}:{r.marker}" for r in result.outliers],
    }
    if result.warnings:
        metadata["warnings"] = list(result.warnings)
    if result.estimated_tolerance is not None:
        metadata["estimated_tolerance"] = float(result.estimated_tolerance)
    metadata["camera_covariance"] = CameraCovariance.of_cameras(
        result.parameter_names, result.covariance, result.cameras).to_table()
    if not result.per_camera:
        metadata["joints"] = joints_to_table(result.joints, machine)
        metadata["joints_sd"] = _joint_sd_table(result.joints_sd, machine)
    return Calibration(result.cameras, tuple(extras), metadata)


def dlt_to_calibration(results: list[DltResult], frame: int, machine_name: str) -> Calibration:
    extras = tuple(
        {"error": r.rms_px, "paper": paper_table(r.camera)} for r in results
    )
    rms = float(np.sqrt(np.mean(np.concatenate([np.sum(r.residuals**2, axis=1) for r in results]))))
    metadata = {"machine": machine_name, "method": "dlt", "frame": int(frame), "error": rms}
    return Calibration(tuple(r.camera for r in results), extras, metadata)


def reference_points(result: CalibrationResult, frame: int) -> Points:
    """Every marker of the fitted model at the calibration frame (base frame, metres), with
    its RMS residual over the cameras that saw it and their number."""
    machine = result.machine
    error = np.full(len(machine.marker_names), np.nan)
    for m, name in enumerate(machine.marker_names):
        sq = [np.sum(r.residual**2) for r in result.residuals if r.marker == name and not r.outlier]
        if sq:
            error[m] = np.sqrt(np.mean(sq))
    n = len(machine.marker_names)
    return Points(
        np.full(n, frame, dtype=int),
        np.array(machine.marker_names, dtype=object),
        result.markers_world,
        error,
        result.marker_views,
    )


def format_report(result: CalibrationResult, frame: int) -> str:
    """A readable report: both views of every camera with standard deviations, joint values,
    residuals per marker, outliers and identifiability."""
    machine = result.machine
    lines = [f"machine {machine.name!r}, frame {frame}: rms {result.rms_px:.3f} px, "
             f"noise estimate {result.sigma_px:.3f} px"]
    std = dict(zip(result.parameter_names, result.std))
    for c, camera in enumerate(result.cameras):
        n = camera.name
        mine = [r for r in result.residuals if r.camera == n]
        lines.append(
            f"camera {n} {camera.size[0]}x{camera.size[1]}: rms {result.camera_rms(n):.3f} px over "
            f"{sum(not r.outlier for r in mine)} markers"
        )
        fx, cx, cy = camera.matrix[0, 0], camera.matrix[0, 2], camera.matrix[1, 2]
        lines.append(
            f"  opencv: f {fx:.2f} ± {std[n + '.f']:.2f} px, principal point ({cx:.2f}, {cy:.2f})"
            + (f" ± ({std[n + '.cx']:.2f}, {std[n + '.cy']:.2f})" if n + ".cx" in std else " (fixed)")
        )
        rvec = camera.cam_from_world.rotvec
        lines.append(
            "  opencv: rotation (Rodrigues) " + _vec(rvec, [std[f"{n}.r{a}"] for a in "xyz"], 5)
            + ", translation " + _vec(camera.cam_from_world.translation, [std[f"{n}.t{a}"] for a in "xyz"], 3)
            + " m"
        )
        dist = [k for k in _DISTORTION_NAMES if f"{n}.{k}" in std]
        if dist:
            lines.append("  distortion: " + ", ".join(
                f"{k} {camera.distortion[_DISTORTION_NAMES.index(k)]:.5f} ± {std[n + '.' + k]:.5f}" for k in dist))
        paper, sd = camera.to_paper(), result.paper_sd[c]
        lines.append(
            f"  paper: azimuth {np.degrees(paper.azimuth):.3f} ± {np.degrees(sd[0]):.3f}°, "
            f"elevation {np.degrees(paper.elevation):.3f} ± {np.degrees(sd[1]):.3f}°, "
            f"tilt {np.degrees(paper.tilt):.3f} ± {np.degrees(sd[2]):.3f}°, "
            f"position {_vec(paper.position, sd[3:6], 3)} m, M {paper.focal:.2f} ± {sd[6]:.2f} px"
        )
        lines.append("  residuals (px): " + ", ".join(
            f"{r.marker} {np.linalg.norm(r.residual):.2f}{'*' if r.outlier else ''}" for r in mine))
    joint_rows = [result.joints] if not result.per_camera else list(result.joints)
    sd_rows = [result.joints_sd] if not result.per_camera else list(result.joints_sd)
    for k, (q, s) in enumerate(zip(joint_rows, sd_rows)):
        who = f" ({result.cameras[k].name})" if result.per_camera else ""
        parts = []
        for joint, v, e in zip(machine.joints, q, s):
            if joint.type == REVOLUTE:
                parts.append(f"{joint.name} {np.degrees(v):.3f} ± {np.degrees(e):.3f}°")
            else:
                parts.append(f"{joint.name} {v:.4f} ± {e:.4f} m")
        if parts:
            lines.append(f"joints{who}: " + ", ".join(parts))
    if result.marker_offsets is not None:
        moved = np.linalg.norm(result.marker_offsets, axis=1)
        worst = np.argsort(-moved)[:3]
        within = ("the model's tolerance" if result.estimated_tolerance is None else
                  f"an estimated tolerance of {100 * result.estimated_tolerance:.1f} % (none stated; the residuals "
                  "showed the markers off beyond the pixel noise)")
        lines.append(f"markers' positions fitted within {within}, largest moves: " + ", ".join(
            f"{machine.marker_names[m]} {moved[m]:.3f} m" for m in worst))
    if result.outliers:
        lines.append("outliers (dropped): " + ", ".join(
            f"{r.camera}:{r.marker} {np.linalg.norm(r.residual):.1f} px" for r in result.outliers))
    lines.append(
        f"identifiability: rank {result.rank} of {len(result.parameters)} parameters, "
        f"condition number {result.condition:.2e}"
    )
    lines.extend(f"warning: {w}" for w in result.warnings)
    return "\n".join(lines)


def format_dlt_report(results: list[DltResult], frame: int) -> str:
    lines = [f"DLT, frame {frame}"]
    for r in results:
        paper = r.camera.to_paper()
        k = r.camera.matrix
        lines.append(
            f"camera {r.camera.name}: rms {r.rms_px:.3f} px over {len(r.residuals)} points; "
            f"fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} skew {k[0, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}; "
            f"centre {_vec(paper.position, None, 3)} m"
        )
    return "\n".join(lines)


def _vec(values, sds, digits: int) -> str:
    if sds is None:
        return "(" + ", ".join(f"{v:.{digits}f}" for v in values) + ")"
    return "(" + ", ".join(f"{v:.{digits}f} ± {s:.{digits}f}" for v, s in zip(values, sds)) + ")"
