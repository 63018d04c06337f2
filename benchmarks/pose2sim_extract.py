"""Make tests/data/pose2sim from the Pose2Sim 0.4.15 wheel on PyPI (its demo, BSD-3).

    pip download pose2sim==0.4.15 --no-deps -d /tmp/p2s
    python benchmarks/pose2sim_extract.py /tmp/p2s/pose2sim-0.4.15-py3-none-any.whl --out tests/data/pose2sim

Copied unchanged: the demo's Qualisys calibration (`Calib.qca.txt`), Pose2Sim's conversion of it
to aniposelib's TOML (`Calib_qualisys.toml`), Pose2Sim's own 3-D result of the demo
(`Demo_0-100.trc`, shipped as `opensim/Balancing_for_IK.trc`) and the licence.

Derived: `keypoints.csv`, the demo's OpenPose BODY_25B keypoints (one JSON per camera and
frame) in mocap's tracks format `camera,frame,marker,x,y,score`, `score` OpenPose's
confidence. Only the 21 keypoints of Pose2Sim's BODY_25B skeleton (the TRC's markers) are
kept, and only those OpenPose found (it writes 0, 0, 0 for a keypoint it did not). Where a
camera sees several people, the one kept is the one whose neck lies nearest the neck
triangulated from the cameras that see one person (Pose2Sim's own association rule: the
tracked keypoint `Neck`, by reprojection error), with the pinhole projection Pose2Sim uses.

Derived: `board_corners.csv`, the inner corners of the 4x7 chessboard (60 mm squares, the
demo's `intrinsics_corners_nb` and `intrinsics_square_size`) in the demo's intrinsic
calibration images (`calibration/intrinsics/int_camN_img/camNN_KK_int.jpg`), found by
OpenCV as Pose2Sim finds them (`findChessboardCorners`, then `cornerSubPix` in an 11x11
window): camera `cam_NN`, frame = image KK - 1, marker `C<row><column>` in OpenCV's order;
an image where the board is not found has no rows. `board.toml`: that board as a rigid
machine model (metres).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import tomllib
import zipfile
from pathlib import Path

import numpy as np

DEMO = "Pose2Sim/Demo/"
# Pose2Sim's BODY_25B skeleton (Pose2Sim/skeletons.py): marker name -> OpenPose keypoint index
BODY_25B = {
    "RHip": 12, "RKnee": 14, "RAnkle": 16, "RBigToe": 22, "RSmallToe": 23, "RHeel": 24,
    "LHip": 11, "LKnee": 13, "LAnkle": 15, "LBigToe": 19, "LSmallToe": 20, "LHeel": 21,
    "Neck": 17, "Head": 18, "Nose": 0, "RShoulder": 6, "RElbow": 8, "RWrist": 10,
    "LShoulder": 5, "LElbow": 7, "LWrist": 9,
}
NECK = BODY_25B["Neck"]
COPIED = {
    "calibration/Calib.qca.txt": "Calib.qca.txt",
    "calibration/Calib_qualisys.toml": "Calib_qualisys.toml",
    "opensim/Balancing_for_IK.trc": "Demo_0-100.trc",
}


def projections(calibration: dict) -> dict[str, np.ndarray]:
    """Pinhole P = K [R | t] per camera (no distortion, as Pose2Sim triangulates)."""
    import cv2

    out = {}
    for name, cam in calibration.items():
        if name == "metadata":
            continue
        rotation, _ = cv2.Rodrigues(np.array(cam["rotation"], dtype=float))
        out[name] = np.array(cam["matrix"]) @ np.hstack([rotation, np.reshape(cam["translation"], (3, 1))])
    return out


def dlt(p_all: list[np.ndarray], xy: np.ndarray) -> np.ndarray:
    """The 3-D point seen at xy (V, 2) by the cameras p_all (V of 3x4), linear least squares."""
    rows = np.concatenate([[x * p[2] - p[0], y * p[2] - p[1]] for p, (x, y) in zip(p_all, xy)])
    point = np.linalg.svd(rows)[2][-1]
    return point[:3] / point[3]


def keypoint_rows(wheel: zipfile.ZipFile, calibration: dict) -> list[tuple]:
    p_of = projections(calibration)
    files: dict[tuple[str, int], list[np.ndarray]] = {}
    for name in wheel.namelist():
        match = re.fullmatch(re.escape(DEMO) + r"pose/cam(\d+)_json/cam\d+\.(\d+)\.json", name)
        if match:
            people = json.loads(wheel.read(name))["people"]
            camera = f"cam_{int(match[1]):02d}"
            files[camera, int(match[2])] = [np.reshape(p["pose_keypoints_2d"], (-1, 3)) for p in people]
    cameras = sorted({c for c, _ in files})
    frames = sorted({f for _, f in files})
    rows = []
    for frame in frames:
        people = {c: files.get((c, frame), []) for c in cameras}
        single = [c for c in cameras if len(people[c]) == 1 and people[c][0][NECK, 2] > 0]
        neck = None
        if len(single) >= 2:
            neck = dlt([p_of[c] for c in single], np.array([people[c][0][NECK, :2] for c in single]))
        for camera in cameras:
            if not people[camera]:
                continue
            if len(people[camera]) == 1 or neck is None:
                person = max(people[camera], key=lambda k: k[:, 2].sum())
            else:
                seen = p_of[camera] @ np.append(neck, 1.0)
                person = min(people[camera], key=lambda k: np.hypot(*(k[NECK, :2] - seen[:2] / seen[2])))
            for marker, index in BODY_25B.items():
                x, y, score = person[index]
                if score > 0:
                    rows.append((camera, frame, marker, f"{x:g}", f"{y:g}", f"{score:g}"))
    return rows


BOARD_COLUMNS, BOARD_ROWS, SQUARE_M = 4, 7, 0.060  # Config.toml: intrinsics_corners_nb [4, 7], 60 mm


def board_rows(wheel: zipfile.ZipFile) -> list[tuple]:
    import cv2

    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    rows = []
    for name in sorted(wheel.namelist()):
        match = re.fullmatch(re.escape(DEMO) + r"calibration/intrinsics/int_cam\d+_img/cam(\d+)_(\d+)_int\.jpg", name)
        if not match:
            continue
        gray = cv2.imdecode(np.frombuffer(wheel.read(name), np.uint8), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(gray, (BOARD_COLUMNS, BOARD_ROWS),
                                                   cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            continue
        corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), criteria).reshape(-1, 2)
        for k, (x, y) in enumerate(corners):
            rows.append((f"cam_{int(match[1]):02d}", int(match[2]) - 1, f"C{k // BOARD_COLUMNS}{k % BOARD_COLUMNS}",
                         f"{x:.3f}", f"{y:.3f}"))
    return rows


def board_model() -> str:
    lines = [f'name = "chessboard {BOARD_COLUMNS} x {BOARD_ROWS}"',
             f'source = "Pose2Sim demo: {BOARD_COLUMNS} x {BOARD_ROWS} inner corners, {SQUARE_M * 1000:g} mm squares"',
             "", "[[links]]", 'name = "board"']
    for k in range(BOARD_COLUMNS * BOARD_ROWS):
        row, column = divmod(k, BOARD_COLUMNS)
        lines += ["", "[[markers]]", f'name = "C{row}{column}"', 'link = "board"',
                  f"position = [{column * SQUARE_M:.3f}, {row * SQUARE_M:.3f}, 0.0]"]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("wheel", type=Path, help="pose2sim-0.4.15-py3-none-any.whl")
    parser.add_argument("--out", type=Path, default=Path("tests/data/pose2sim"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(args.wheel) as wheel:
        for source, target in COPIED.items():
            (args.out / target).write_bytes(wheel.read(DEMO + source))
        licence = next(n for n in wheel.namelist() if n.endswith((".dist-info/LICENSE", "/licenses/LICENSE")))
        (args.out / "LICENSE").write_bytes(wheel.read(licence))
        calibration = tomllib.loads(wheel.read(DEMO + "calibration/Calib_qualisys.toml").decode())
        rows = keypoint_rows(wheel, calibration)
        corners = board_rows(wheel)
    with open(args.out / "board_corners.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["camera", "frame", "marker", "x", "y"])
        writer.writerows(corners)
    (args.out / "board.toml").write_text(board_model())
    with open(args.out / "keypoints.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["camera", "frame", "marker", "x", "y", "score"])
        writer.writerows(rows)
    print(f"{len(rows)} keypoints of {len({r[0] for r in rows})} cameras, {len(corners)} board corners "
          f"written to {args.out}")


if __name__ == "__main__":
    main()
