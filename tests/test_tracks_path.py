"""The tracks file's path through the house at run time: from the stage down through the
formats to the core, entering each module once (no module entered again after the path
has left it), whether the file is CSV or Parquet."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mocap.core.calibration import Calibration
from mocap.core.camera import Camera
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io.cameras_toml import save_calibration
from mocap.io.tracks_csv import save_tracks
from mocap.reconstruct.stage import load_inputs


def _entered(call) -> tuple[list[str], object]:
    """The mocap modules `call` enters (called from another module), in order, a module
    repeated only when it is entered again after another one was; and `call`'s result.
    Coming back to a caller is not entering it."""
    order: list[str] = []

    def profile(frame, event, arg) -> None:
        if event == "call":
            name = frame.f_globals.get("__name__", "")
            caller = frame.f_back.f_globals.get("__name__", "") if frame.f_back else ""
            if name.startswith("mocap.") and name != caller and (not order or order[-1] != name):
                order.append(name)

    sys.setprofile(profile)
    try:
        result = call()
    finally:
        sys.setprofile(None)
    return order, result


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_the_tracks_file_enters_each_module_once(tmp_path, suffix):
    rng = np.random.default_rng(3)
    cameras = tuple(Camera(f"cam{k}", (640, 480), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
                    for k in (1, 2))
    save_calibration(Calibration(cameras), tmp_path / "cameras.toml")
    frames = np.repeat(np.arange(50), 6)
    tracks = Tracks.from_rows(np.tile(["cam1", "cam1", "cam1", "cam2", "cam2", "cam2"], 50), frames,
                              np.tile(["A", "B", "C"], 100), rng.uniform(0, 480, (300, 2)))
    save_tracks(tracks, tmp_path / f"tracks{suffix}")
    calibration_path, tracks_path = tmp_path / "cameras.toml", tmp_path / f"tracks{suffix}"
    order, (_, loaded, markers) = _entered(lambda: load_inputs(calibration_path, [tracks_path]))
    assert markers == ("A", "B", "C") and len(loaded) == 300
    tracks_part = order[order.index("mocap.io.tracks_csv"):]
    assert tracks_part[:4] == ["mocap.io.tracks_csv", "mocap.io.text", "mocap.io.columnar", "mocap.core.tracks"]
    # then only the calibration's own types, which the core's check against it reads
    assert set(tracks_part[4:]) <= {"mocap.core.calibration", "mocap.core.camera"}, tracks_part


def test_the_path_still_names_a_bad_row(tmp_path):
    (tmp_path / "tracks.csv").write_text("camera,frame,marker,x,y\ncam1,0,A,1,2\ncam1,1,A, 3x,4\n")
    from mocap.io.tracks_csv import load_tracks

    with pytest.raises(InputError, match=r"line 3: x '3x' is not a number"):
        load_tracks(tmp_path / "tracks.csv")
    (tmp_path / "lone_cr.csv").write_bytes(b"camera,frame,marker,x,y\rcam1,0,A,1,2\rcam1,1,A,3,4\r")
    assert len(load_tracks(tmp_path / "lone_cr.csv")) == 2  # old Mac line ends, read as before
