"""A session folder: one object owns every path of the layout in DESIGN.md.

    session.toml  videos/<camera>.mp4  calibration/cameras.toml  tracks/<camera>.csv
    results/points.csv  results/motion.csv  results/session.rrd  truth/ (synthetic only)

Work that writes many files marks its end with a file written last: COMPLETE (a synthetic
session's videos and truth all written) and results/COMPLETE (`mocap run` went through
every stage). A folder without it was interrupted; running the command again finishes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mocap.core.machine import Machine
from mocap.io.atomic import write_text
from mocap.io.machine_toml import load_machine, resolve_machine_path
from mocap.io.session_toml import SessionConfig, load_session_config


@dataclass(frozen=True)
class Session:
    root: Path

    @classmethod
    def open(cls, root: str | Path) -> Session:
        return cls(Path(root))

    @property
    def config_path(self) -> Path:
        return self.root / "session.toml"

    def config(self) -> SessionConfig:
        return load_session_config(self.config_path)

    def machine_path(self) -> Path:
        name = self.config().machine
        local = self.root / name
        return local if local.exists() else resolve_machine_path(name)

    def machine(self) -> Machine:
        return load_machine(self.machine_path())

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.config().cameras)

    def video_path(self, camera: str) -> Path:
        for c in self.config().cameras:
            if c.name == camera:
                return self.root / c.video
        raise KeyError(camera)

    @property
    def calibration_path(self) -> Path:
        return self.root / "calibration" / "cameras.toml"

    @property
    def refined_calibration_path(self) -> Path:
        return self.root / "calibration" / "refined.toml"

    @property
    def reference_points_path(self) -> Path:
        return self.root / "calibration" / "reference_points.csv"

    def tracks_path(self, camera: str) -> Path:
        return self.root / "tracks" / f"{camera}.csv"

    @property
    def results_dir(self) -> Path:
        return self.root / "results"

    @property
    def points_path(self) -> Path:
        return self.results_dir / "points.csv"

    @property
    def motion_path(self) -> Path:
        return self.results_dir / "motion.csv"

    @property
    def recording_path(self) -> Path:
        return self.results_dir / "session.rrd"

    @property
    def truth_dir(self) -> Path:
        return self.root / "truth"

    @property
    def complete_path(self) -> Path:
        """Written last by `mocap synth`: the session's videos and truth are whole."""
        return self.root / "COMPLETE"

    @property
    def results_complete_path(self) -> Path:
        """Written last by `mocap run`: every stage's result is whole."""
        return self.results_dir / "COMPLETE"

    @property
    def is_synthetic(self) -> bool:
        return self.config_path.is_file() and self.truth_dir.is_dir()


def mark_complete(path: Path, what: str) -> None:
    """Write the marker file `path` (last, after every other file of `what`)."""
    write_text(path, f"{what} finished writing this folder; a folder without this file was interrupted\n")
