"""Process one field session: copy this script, edit the paths below, run it.

    python scripts/process_session.py

It writes the session folder's session.toml from the paths below and runs the whole chain
(calibrate, track, sync, triangulate, fit, analyze, Rerun replay) inside that folder, then
prints the dig cycles it found. Before the first run, digitise each camera's markers in its
calibration frame — the machine holding still at the start of the session — into
SESSION/calibration/labels.csv, one row per marker you can see (any image viewer that shows
pixel coordinates will do):

    camera,frame,marker,x,y
    cam1,0,U1,1022.4,611.0
    cam1,0,U2,1187.9,588.2
    ...

Marker names are the machine model's (calibrations/machines/*.toml). At least four
markers on the undercarriage per camera and one on every moving link; more is better.
"""

import mocap

# --- edit these ------------------------------------------------------------------------------
SESSION = "sessions/2026-12-01-pit3-shovel12"
MACHINE = "calibrations/machines/hitachi_ex3500.toml"  # or a shipped model's name
CAMERAS = [  # (name, video, fps) in order: the first camera is the reference clock
    ("cam1", "/data/pit3/2026-12-01/cam1.mp4", 29.97),
    ("cam2", "/data/pit3/2026-12-01/cam2.mp4", 29.97),
    ("cam3", "/data/pit3/2026-12-01/cam3.mp4", 30.0),
]
CALIBRATION_FRAME = 0  # each camera's frame in which the labels were digitised
REFINE = True  # bundle-adjust the cameras over the session's frames before the final fit
# ---------------------------------------------------------------------------------------------


def main() -> int:
    session = mocap.Session.create(SESSION, MACHINE, CAMERAS, CALIBRATION_FRAME)
    code = session.run(refine=REFINE)  # each stage's report printed, as `mocap run`
    if code == 0:
        motion = session.motion()
        print(f"{len(motion)} frames of motion in {session.root / 'results' / 'motion.csv'}")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
