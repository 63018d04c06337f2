"""The export stages: load a session or a machine model -> convert -> write -> a short report."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.errors import InputError
from mocap.interchange.markers import marker_table
from mocap.interchange.reconstruction import reconstruction
from mocap.io.session import Session

MARKER_FORMATS = ("c3d", "trc")


def _session(root: str | Path) -> Session:
    session = Session.open(root)
    if not session.config_path.is_file():
        raise InputError("no session.toml: give a session folder", path=root)
    return session


def export_markers(root: str | Path, fmt: str, out: str | Path) -> str:
    """Write the triangulated markers and the motion's named points as a C3D or TRC file."""
    from mocap.io.motion_csv import load_motion
    from mocap.io.points_csv import load_points

    if fmt not in MARKER_FORMATS:
        raise InputError(f"unknown marker format {fmt!r}; use one of {', '.join(MARKER_FORMATS)}")
    session = _session(root)
    config = session.config()
    machine = session.machine()
    points = load_points(session.points_path) if session.points_path.is_file() else None
    motion = load_motion(session.motion_path, machine) if session.motion_path.is_file() else None
    if points is None and motion is None:
        raise InputError(
            f"neither {session.points_path.name} nor {session.motion_path.name} in results/: run the session first",
            path=session.results_dir,
        )
    table = marker_table(points, motion, config.cameras[0].fps, machine.marker_names)
    if fmt == "c3d":
        from mocap.io.c3d import save_c3d

        save_c3d(table, out)
    else:
        from mocap.io.trc import save_trc

        save_trc(table, out)
    seen = np.isfinite(table.xyz[..., 0])
    return (
        f"{len(table.names)} markers and points over {len(table.frame)} frames at {table.rate:g} fps "
        f"({seen.mean():.0%} seen) written to {out}"
    )


def export_urdf(machine_path: str | Path, out: str | Path) -> str:
    from mocap.io.machine_toml import load_machine
    from mocap.io.urdf import save_urdf

    machine = load_machine(machine_path)
    save_urdf(machine, out)
    return (
        f"{len(machine.links)} links, {machine.n_joints} joints, {len(machine.marker_names)} markers and "
        f"{len(machine.point_names)} named points written to {out}"
    )


_MODEL_FILES = {f"{name}.{ext}" for name in ("cameras", "images", "points3D", "rigs", "frames") for ext in ("txt", "bin")}


def _check_model_folder(out: str | Path) -> None:
    """`out` may be replaced only if it is absent or an earlier COLMAP model."""
    out = Path(out)
    if out.is_file():
        raise InputError("is a file; --out names the folder of the COLMAP model", path=out)
    if out.is_dir() and any(p.name not in _MODEL_FILES for p in out.iterdir()):
        raise InputError("exists and holds more than a COLMAP model; choose another --out", path=out)


def export_colmap(root: str | Path, out: str | Path, calibration_path: str | Path | None = None) -> str:
    """Write a COLMAP text model of the session: its cameras, one image per camera and
    triangulated frame, the triangulated markers with their 2-D tracks."""
    from mocap.io.atomic import atomic_dir
    from mocap.io.colmap import write_model
    from mocap.io.points_csv import load_points
    from mocap.io.cameras_toml import load_calibration
    from mocap.io.tracks_csv import load_tracks
    from mocap.reconstruct.timing import on_reference_clock

    _check_model_folder(out)
    session = _session(root)
    if calibration_path is None:
        refined = session.refined_calibration_path
        calibration_path = refined if refined.is_file() else session.calibration_path
    if not session.points_path.is_file():
        raise InputError("no triangulated points: run the session (or `mocap triangulate`) first",
                         path=session.points_path)
    tracks_paths = [session.tracks_path(name) for name in session.camera_names]
    calibration, tracks = load_calibration(calibration_path), load_tracks(tracks_paths)
    markers = tracks.checked_against(calibration, session.machine(), calibration_path,
                                     ", ".join(map(str, tracks_paths)))
    clock = on_reference_clock(calibration, tracks, markers)
    points = load_points(session.points_path)
    scene = reconstruction(calibration.names, markers, clock.frame, clock.pixels, points)
    with atomic_dir(out) as tmp:
        write_model(tmp, list(calibration.cameras), list(scene.image_names), scene.image_cameras,
                    list(scene.keypoints), scene.points, scene.tracks)
    return (
        f"{len(calibration.cameras)} cameras, {len(scene.image_names)} images, {len(scene.points)} points "
        f"with {len(scene.tracks)} observations written to {out}"
    )
