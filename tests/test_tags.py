"""Tags on webcam-like video: boards of ArUco tags (drawn with cv2.aruco.generateImageMarker)
seen through a lens with k1 = -0.35, small, printed inverted, motion-blurred, read by a
rolling shutter, H.264-encoded; `mocap track` with a model whose markers are all tags (no
calibration), its refusals, and the preview video of the labels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from mocap.cli import main
from mocap.io.tracks_csv import load_tracks
from mocap.io.video import Video
from mocap.synthetic.encode import video_writer
from mocap.synthetic.tag_board import BoardLook, render_board
from mocap.tracking.detect import detect_tags, diagonal_intersection, tag_dictionary
from mocap.tracking.preview import marker_colours

LOOKS = {
    "small": BoardLook(tag_px=12),
    "inverted": BoardLook(tag_px=18, inverted=True),
    "blur": BoardLook(tag_px=28, speed=6.0, shutter=0.5),
    "rolling shutter": BoardLook(tag_px=16, speed=8.0, rolling_shutter=0.8, inverted=True),
}


def encode(path: Path, frames: np.ndarray, codec: str = "h264") -> list[np.ndarray]:
    """Write grey frames (F, H, W) as a video; return the frames as decoded (luma)."""
    h, w = frames.shape[1:]
    with video_writer(path, (w, h), 30.0, codec) as write:
        for gray in frames:
            write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    return [gray for _, gray in Video(path).frames()]


def opencv_tags(gray: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    """OpenCV's ArucoDetector with its default settings: {id: centre (diagonals' crossing)}."""
    detector = cv2.aruco.ArucoDetector(tag_dictionary(dictionary), cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(corners) == 0:  # (some OpenCV versions give an empty id array, not None)
        return {}
    corners = np.concatenate(corners).reshape(-1, 4, 2)
    return dict(zip(ids.reshape(-1).tolist(), diagonal_intersection(corners)))


@pytest.mark.parametrize("name", list(LOOKS))
def test_tags_found_at_least_as_opencv_finds_them(name, tmp_path):
    look = LOOKS[name]
    board = render_board(look, 5, np.random.default_rng(11), supersample=2, exposure_steps=5)
    frames = encode(tmp_path / "board.mp4", board.frames)
    ids = board.ids.tolist()
    ours_n = theirs_n = 0
    ours_err, theirs_err = [], []
    for f, gray in enumerate(frames):
        ours = detect_tags(gray, look.dictionary)
        theirs = opencv_tags(gray, look.dictionary)
        assert set(theirs) <= set(ours.ids.tolist())  # every tag OpenCV finds, found
        assert set(ours.ids.tolist()) <= set(ids)  # no id that is not on the board
        for tag_id, xy in zip(ours.ids, ours.xy):
            truth = board.xy[f, ids.index(tag_id)]
            if np.isfinite(truth[0]):
                ours_n += 1
                ours_err.append(np.linalg.norm(xy - truth))
        for tag_id, xy in theirs.items():
            truth = board.xy[f, ids.index(tag_id)]
            if np.isfinite(truth[0]):
                theirs_n += 1
                theirs_err.append(np.linalg.norm(xy - truth))
    visible = int(np.isfinite(board.xy[..., 0]).sum())
    assert ours_n >= 0.6 * visible and ours_n >= theirs_n
    assert max(ours_err) < 1.5  # no tag placed on another's
    # H.264 at crf 23 and noise of 2 grey levels: a tenth to a third of a pixel, no worse than OpenCV's
    assert np.median(ours_err) < 0.3
    if theirs_err:
        assert np.median(ours_err) <= np.median(theirs_err) + 0.02


@pytest.mark.parametrize("name", ["small", "inverted"])
def test_tag_centres_are_opencvs_own(name, tmp_path):
    """Where OpenCV's ArucoDetector (corners refined on the contour, the picture given black
    on white) finds a tag, ours has the same centre: the crossing of OpenCV's diagonals."""
    look = LOOKS[name]
    board = render_board(look, 3, np.random.default_rng(5), supersample=2, exposure_steps=3)
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
    detector = cv2.aruco.ArucoDetector(tag_dictionary(look.dictionary), parameters)
    differences = []
    for gray in encode(tmp_path / "board.mp4", board.frames):
        corners, ids, _ = detector.detectMarkers(255 - gray if look.inverted else gray)
        ours = detect_tags(gray, look.dictionary)
        assert ids is not None and set(ids.reshape(-1).tolist()) <= set(ours.ids.tolist())
        theirs = dict(zip(ids.reshape(-1).tolist(), diagonal_intersection(np.concatenate(corners).reshape(-1, 4, 2))))
        differences += [np.linalg.norm(xy - theirs[t]) for t, xy in zip(ours.ids.tolist(), ours.xy) if t in theirs]
    assert len(differences) >= 10
    assert np.median(differences) <= 0.1


def test_opencv_misses_inverted_prints_that_are_found():
    """The inverted print is the case a plain ArucoDetector misses entirely."""
    board = render_board(LOOKS["inverted"], 1, np.random.default_rng(2), supersample=2)
    assert opencv_tags(board.frames[0], "DICT_4X4_50") == {}
    assert len(detect_tags(board.frames[0]).ids) >= 0.8 * np.isfinite(board.xy[0, :, 0]).sum()


# --- the command line -------------------------------------------------------------------------


def board_model(path: Path, ids, dictionary: str = "DICT_4X4_50", disk: bool = False) -> Path:
    """A rigid 'machine' carrying tags `ids` (the board), optionally one painted disk too."""
    lines = [f'name = "tag board"\n\n[[links]]\nname = "board"\n\n[tags]\ndictionary = "{dictionary}"\n']
    for k, tag_id in enumerate(ids):
        lines.append(f'[[markers]]\nname = "T{tag_id}"\nlink = "board"\nposition = [{0.2 * k}, 0, 0]\ntag = {tag_id}\n')
    if disk:
        lines.append('[[markers]]\nname = "D1"\nlink = "board"\nposition = [0, 1, 0]\n')
    path.write_text("\n".join(lines))
    return path


@pytest.fixture(scope="module")
def board_video(tmp_path_factory):
    root = tmp_path_factory.mktemp("tags")
    board = render_board(BoardLook(tag_px=20, inverted=True, speed=3.0, shutter=0.3), 6, np.random.default_rng(5),
                         supersample=2, exposure_steps=3)
    encode(root / "webcam1.mp4", board.frames)
    return root, board


def test_cli_tracks_tags_without_a_calibration_and_draws_a_preview(board_video, capsys):
    root, board = board_video
    model = board_model(root / "board.toml", board.ids)
    assert main(["track", str(root / "webcam1.mp4"), "--machine", str(model), "--out", str(root / "t.csv"),
                 "--preview", str(root / "check.mp4")]) == 0
    out = capsys.readouterr().out
    assert "webcam1: 6 frames, " in out and "model fit" not in out  # tags alone need no model fit
    tracks = load_tracks(root / "t.csv")
    assert f"{len(tracks)} marker positions written" in out
    assert set(tracks.camera) == {"webcam1"} and np.all(tracks.score == 1.0)
    ids = board.ids.tolist()
    truth = board.xy[tracks.frame, [ids.index(int(m[1:])) for m in tracks.marker]]
    seen = np.isfinite(truth[:, 0])
    error = np.linalg.norm(tracks.xy[seen] - truth[seen], axis=1)
    assert seen.sum() >= 0.9 * np.isfinite(board.xy[..., 0]).sum() and error.max() < 1.5
    assert np.median(error) < 0.3
    # the preview: every frame, each label's dot in its marker's colour at the tracked pixel
    preview = Video(root / "check.mp4")
    assert preview.info.frame_count == 6 and preview.info.size == (640, 480)
    colours = marker_colours(tracks.marker)
    hits = []
    for index, image in preview.frames(gray=False):
        rows = tracks.select(tracks.frame == index)
        for (x, y), name in zip(rows.xy, rows.marker):
            pixel = image[int(round(y)), int(round(x))].astype(float)
            hits.append(np.linalg.norm(pixel - colours[name]))
    assert len(hits) == len(tracks) and np.mean(np.array(hits) < 70) >= 0.95  # H.264 keeps colour at half resolution


def test_cli_refuses_a_video_without_the_models_tags(board_video, capsys):
    root, board = board_video
    model = board_model(root / "april.toml", [0, 1, 2], dictionary="DICT_APRILTAG_36h11")
    out = root / "none.csv"
    assert main(["track", str(root / "webcam1.mp4"), "--machine", str(model), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "6 frames read: no tag of the machine model found; check the tag dictionary (DICT_APRILTAG_36h11" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


def test_cli_says_when_a_calibration_is_required(board_video, capsys):
    root, board = board_video
    model = board_model(root / "mixed.toml", board.ids[:3], disk=True)
    assert main(["track", str(root / "webcam1.mp4"), "--machine", str(model), "--out", str(root / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert "--calibration is required: 1 of the model's markers (D1) are painted disks" in err
    assert main(["track", str(root / "webcam1.mp4"), "--machine", str(model), "--out", str(root / "x.csv"),
                 "--preview", str(root / "webcam1.mp4")]) == 2
    assert "is the video input; writing it would destroy the input" in capsys.readouterr().err
