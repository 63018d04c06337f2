"""The session file ``session.toml``: one field session (one set-up of the cameras).

    machine = "hitachi_ex3500"          # a shipped model's name, or a TOML path relative to the folder
    [[cameras]]                         # in order; the first is the reference clock
    name = "cam1"
    video = "videos/cam1.mp4"           # relative to the session folder
    fps = 29.97
    [options]                           # free-form stage options, e.g. calibration_frame = 0
    [metadata]                          # free-form, e.g. machine_id = "EX3500 #2", date = 2026-11-30
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mocap.errors import InputError
from mocap.io import toml_writer
from mocap.io.atomic import write_text
from mocap.io.cameras_toml import MAX_FPS
from mocap.io.text import read_toml

_TOP_KEYS = {"machine", "cameras", "options", "metadata"}
_CAMERA_KEYS = {"name", "video", "fps"}


@dataclass(frozen=True)
class SessionCamera:
    name: str
    video: str
    fps: float


@dataclass(frozen=True)
class SessionConfig:
    machine: str
    cameras: tuple[SessionCamera, ...]
    options: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)


def load_session_config(path: str | Path) -> SessionConfig:
    path = Path(path)
    data = read_toml(path, "is this a session folder?")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise InputError(f"unknown key(s) {unknown}; allowed: {sorted(_TOP_KEYS)}", path=path)
    machine = data.get("machine")
    if not isinstance(machine, str) or not machine:
        raise InputError("'machine' must name a machine model", path=path)
    raw_cameras = data.get("cameras")
    if not isinstance(raw_cameras, list) or not raw_cameras:
        raise InputError("no [[cameras]]: list each camera with name, video and fps", path=path)
    cameras = []
    for k, raw in enumerate(raw_cameras):
        where = f"cameras[{k}]"
        if not isinstance(raw, dict):
            raise InputError("must be a table", path=path, where=where)
        unknown = sorted(set(raw) - _CAMERA_KEYS)
        if unknown:
            raise InputError(f"unknown key(s) {unknown}; allowed: {sorted(_CAMERA_KEYS)}", path=path, where=where)
        name, video, fps = raw.get("name"), raw.get("video"), raw.get("fps")
        if not isinstance(name, str) or not name:
            raise InputError("'name' must be a non-empty string", path=path, where=where)
        if not isinstance(video, str) or not video:
            raise InputError("'video' must be a path", path=path, where=where)
        if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not 0 < fps <= MAX_FPS:
            raise InputError(f"'fps' must be a positive number (at most {MAX_FPS:g}), got {fps!r}", path=path,
                             where=where)
        cameras.append(SessionCamera(name, video, float(fps)))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise InputError(f"camera names repeat: {names}", path=path)
    options = data.get("options", {})
    if not isinstance(options, dict):
        raise InputError("[options] must be a table", path=path)
    metadata = data.get("metadata", {})
    if not isinstance(metadata, dict):
        raise InputError("[metadata] must be a table", path=path)
    return SessionConfig(machine, tuple(cameras), options, metadata)


def save_session_config(config: SessionConfig, path: str | Path) -> None:
    data = {
        "machine": config.machine,
        "cameras": [{"name": c.name, "video": c.video, "fps": c.fps} for c in config.cameras],
    }
    if config.options:
        data["options"] = config.options
    if config.metadata:
        data["metadata"] = config.metadata
    write_text(path, toml_writer.dumps(data))
