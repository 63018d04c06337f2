"""Relabel and recalibrate one camera of a processed session, then redo what follows.

A camera whose calibration is off (a marker clicked on the wrong disk, a camera knocked
after the calibration frame): correct its rows in a labels CSV (camera,frame,marker,x,y;
the other cameras' rows may stay), and this script calibrates that camera alone against the
machine at the calibration frame, puts it into the session's calibration in place of the
old one (its time offset and frame rate kept), and triangulates, fits and analyses again.

    python scripts/recalibrate_camera.py sessions/day1 cam2 relabelled.csv
"""

import argparse
from pathlib import Path

import mocap


def recalibrate(session: mocap.Session, camera: str, labels: Path) -> mocap.Cameras:
    machine = session.machine()
    old = session.cameras()
    if camera not in old.names:
        raise mocap.InputError(f"no camera {camera!r} in the calibration (it has {', '.join(old.names)})")
    relabelled = mocap.read_tracks(labels).of_camera(camera)
    frame = int(old.metadata.get("frame", relabelled.frame.min() if len(relabelled) else 0))
    fresh = mocap.calibrate(machine, relabelled, size=old.camera(camera).size, frame=frame)
    k = old.names.index(camera)
    cameras = tuple(fresh.cameras[0] if i == k else c for i, c in enumerate(old.cameras))
    return mocap.Cameras(cameras, old.extras, old.metadata)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("session", type=Path, help="the session folder")
    parser.add_argument("camera", help="the camera to recalibrate")
    parser.add_argument("labels", type=Path, help="labels CSV with the camera's corrected rows")
    args = parser.parse_args()
    session = mocap.Session(args.session)
    try:
        cameras = recalibrate(session, args.camera, args.labels)
        session.write_cameras(cameras)
        for stage in (session.triangulate, session.fit, session.analyze):
            print(stage())
    except mocap.InputError as exc:
        print(f"error: {exc}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
