"""Small valid inputs of every kind, written into a folder, for the bad-input corpus: a
two-camera rig around a machine, its calibration, tracks, points, motion, a tiny video and
a session folder. Each corpus case spoils one of them."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import cv2
import numpy as np

from mocap.core.calibration import Calibration, joints_to_table
from mocap.io.cameras_toml import save_calibration
from mocap.io.machine_toml import MACHINES_DIR, load_machine
from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.io.tracks_csv import save_tracks
from mocap.synthetic.scenes import observe, random_joints, ring_of_cameras

SIZE = (320, 240)
FPS = 30.0
FRAMES = 45


def write_rig(root: Path, machine_name: str = "bobcat_225", seed: int = 3) -> dict:
    """machine.toml, cameras.toml, cam1.csv, cam2.csv, tracks.csv (both cameras, with a time
    column), labels.csv (frame 0) and video.mp4 (cam1's size) in `root`; returns the truth."""
    root.mkdir(parents=True, exist_ok=True)
    shutil.copy(MACHINES_DIR / f"{machine_name}.toml", root / "machine.toml")
    machine = load_machine(root / "machine.toml")
    rng = np.random.default_rng(seed)
    rest = machine.markers(np.zeros((1, machine.n_joints)))[0]
    extent = np.ptp(rest, axis=0).max()
    cameras = ring_of_cameras(2, rest.mean(0), (2.5 * extent, 3.5 * extent), rng, size=SIZE,
                              height=(0.3 * extent, 0.8 * extent), spread_deg=90)
    low, high = random_joints(machine, 2, rng)
    phase = np.sin(np.linspace(0, 2 * np.pi, FRAMES))[:, None] * np.linspace(1, 2, machine.n_joints)
    joints = low + (high - low) * 0.5 * (1 + np.sin(phase))  # every joint moving, each its own way
    tracks = observe(cameras, machine, joints, rng, noise_px=0.3)
    tracks = type(tracks).from_rows(tracks.camera, tracks.frame, tracks.marker, tracks.xy,
                                    tracks.frame / FPS + 0.5)
    extras = tuple({"fps": FPS, "time_offset": 0.0} for _ in cameras)
    metadata = {"machine": machine.name, "frame": 0, "joints": joints_to_table(joints[0], machine)}
    save_calibration(Calibration(tuple(cameras), extras, metadata), root / "cameras.toml")
    for camera in cameras:
        save_tracks(tracks.of_camera(camera.name), root / f"{camera.name}.csv")
    save_tracks(tracks, root / "tracks.csv")
    save_tracks(tracks.select(tracks.frame == 0), root / "labels.csv")
    write_video(root / "video.mp4", SIZE, 4)
    return {"machine": machine, "cameras": cameras, "joints": joints, "tracks": tracks}


def write_video(path: Path, size, frames: int) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, size)
    for k in range(frames):
        writer.write(np.full((size[1], size[0], 3), 40 + 10 * k, np.uint8))
    writer.release()


def write_session(root: Path, rig: Path) -> None:
    """A session folder `root` made of the rig's files (videos not trackable: for input errors)."""
    (root / "videos").mkdir(parents=True, exist_ok=True)
    (root / "calibration").mkdir(exist_ok=True)
    shutil.copy(rig / "machine.toml", root / "machine.toml")
    for name in ("cam1", "cam2"):
        shutil.copy(rig / "video.mp4", root / "videos" / f"{name}.mp4")
    shutil.copy(rig / "labels.csv", root / "calibration" / "labels.csv")
    save_session_config(SessionConfig("machine.toml", tuple(
        SessionCamera(name, f"videos/{name}.mp4", FPS) for name in ("cam1", "cam2"))), root / "session.toml")


def snapshot(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `root` (hidden ones too)."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*")) if p.is_file()
    }
