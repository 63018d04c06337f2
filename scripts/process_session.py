"""Process one field session: copy this script, edit the paths below, run it.

    python scripts/process_session.py

It writes the session folder's session.toml from the paths below and runs the whole chain
(calibrate, track, sync, triangulate, fit, Rerun replay) inside that folder. Before the
first run, digitise each camera's markers in its calibration frame — the machine holding
still at the start of the session — into SESSION/calibration/labels.csv, one row per
marker you can see (any image viewer that shows pixel coordinates will do):

    camera,frame,marker,x,y
    cam1,0,U1,1022.4,611.0
    cam1,0,U2,1187.9,588.2
    ...

Marker names are the machine model's (calibrations/machines/*.toml). At least four
markers on the undercarriage per camera and one on every moving link; more is better.
"""

from pathlib import Path

from mocap.io.session_toml import SessionCamera, SessionConfig, save_session_config
from mocap.pipeline import RunOptions, run_session

# --- edit these ------------------------------------------------------------------------------
SESSION = Path("sessions/2026-12-01-pit3-shovel12")
MACHINE = "calibrations/machines/hitachi_ex3500.toml"  # or a shipped model's name
CAMERAS = [  # in order: the first camera is the reference clock
    SessionCamera("cam1", "/data/pit3/2026-12-01/cam1.mp4", 29.97),
    SessionCamera("cam2", "/data/pit3/2026-12-01/cam2.mp4", 29.97),
    SessionCamera("cam3", "/data/pit3/2026-12-01/cam3.mp4", 30.0),
]
CALIBRATION_FRAME = 0  # each camera's frame in which the labels were digitised
REFINE = True  # bundle-adjust the cameras over the session's frames before the final fit
# ---------------------------------------------------------------------------------------------


def main() -> int:
    SESSION.mkdir(parents=True, exist_ok=True)
    machine = str(Path(MACHINE).resolve()) if Path(MACHINE).suffix == ".toml" else MACHINE
    config = SessionConfig(machine, tuple(CAMERAS), {"calibration_frame": CALIBRATION_FRAME})
    save_session_config(config, SESSION / "session.toml")
    return run_session(SESSION, RunOptions(refine=REFINE))


if __name__ == "__main__":
    raise SystemExit(main())
