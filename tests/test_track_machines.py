"""Tracking machines nobody designed: random diggers (`random_digger`: random proportions,
link frames, joint senses and limits, two markers on each moving link), rendered and tracked
from the true calibration without a labels file."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocap.synthetic.machines import random_digger
from mocap.synthetic.render import CameraRenderer, RenderOptions
from mocap.synthetic.session import make_session
from mocap.tracking import CameraModel, track_frames
from mocap.tracking.run import TooFewMarkersError


@pytest.mark.parametrize("seed", [6, 11])
def test_random_diggers_are_tracked_against_their_truth(seed):
    """Every wholly visible marker labelled in 40 frames, none wrong, centres within
    hundredths of a pixel (uncompressed 960x540 frames, the default look). Seed 11's
    generator once painted the bucket's two markers 6 cm apart, their squares overlapping:
    each centre was dragged 2 px by the other's disk (no painter would; they are now kept a
    square and a half apart)."""
    machine = random_digger(np.random.default_rng(seed))
    session = make_session(machine, "random", n_cameras=1, n_cycles=1, seed=seed, size=(960, 540))
    field = session.cameras[0]
    renderer = CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(seed))
    frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)) for f, image in renderer.frames(np.arange(40))]
    model = CameraModel(machine, field.camera)
    tracks, _ = track_frames(model, iter(frames), session.plan.joints(field.times(np.array([0])))[0], None, field.fps)

    truth = session.tracks.of_camera(field.name)
    truth = truth.select(truth.frame < 40)
    true_xy = {(int(f), m): xy for f, m, xy in zip(truth.frame, truth.marker, truth.xy)}
    error = np.array([np.linalg.norm(xy - true_xy.get((int(f), m), np.inf))
                      for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy)])
    whole = truth.select(truth.score >= 1.0)
    assert len(whole) >= 5 * 40
    labelled = set(zip(tracks.frame.tolist(), tracks.marker.tolist()))
    assert all((int(f), m) in labelled for f, m in zip(whole.frame, whole.marker))
    assert np.all(error < 1.0)  # no wrong label, no centre dragged by a neighbour's disk
    assert np.median(error) < 0.05 and np.percentile(error, 95) < 0.1


def test_a_camera_that_sees_too_few_markers_is_told_so():
    """Seed 2's camera sees one of the digger's eleven disks at the start joints (the rest face
    away): no labelling of the first frame could fix four joints from it, and the error says
    how many it sees and how many a fit needs, not that the detections went unexplained."""
    machine = random_digger(np.random.default_rng(2))
    session = make_session(machine, "random", n_cameras=1, n_cycles=1, seed=2, size=(960, 540))
    field = session.cameras[0]
    renderer = CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(2))
    frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)) for f, image in renderer.frames(np.arange(1))]
    with pytest.raises(TooFewMarkersError, match="the camera sees 1 of the model's 11 disk markers, and a fit needs 5"):
        track_frames(CameraModel(machine, field.camera), iter(frames),
                     session.plan.joints(field.times(np.array([0])))[0], None, field.fps)


def test_four_markers_that_fix_the_joints_they_show_are_enough_and_two_on_the_arm_are_not():
    """Seed 7's first camera sees four of the digger's ten disks at the start (a base marker,
    one on the boom, one on the arm, one on the bucket): their eight coordinates fix the four
    joints and the image's shift with two to spare, so the camera is tracked (it was refused
    for want of a fifth marker) and every marker it shows wholly is labelled in 30 frames, none
    wrong. Two base markers with one on the arm and one on the bucket are not enough (the arm's
    and bucket's four coordinates fix their four joints with nothing to spare: a wrong pair of
    blobs fits as well as the right one), nor four markers on moving links alone (nothing holds
    the image's shift apart from the swing)."""
    machine = random_digger(np.random.default_rng(7))
    session = make_session(machine, "random digger", n_cameras=3, n_cycles=1, seed=7, size=(960, 540))
    field = session.cameras[0]
    model = CameraModel(machine, field.camera)
    index = {name: k for k, name in enumerate(machine.marker_names)}
    moved_by = machine.marker_moves.sum(axis=0)
    base, boom, arm, bucket = ([k for k in range(len(index)) if moved_by[k] == n] for n in (0, 2, 3, 4))
    assert model.determined(np.array(base[:1] + boom[:1] + arm[:1] + bucket[:1]), 5)
    assert not model.determined(np.array(base[:2] + arm[:1] + bucket[:1]), 5)
    assert not model.determined(np.array(boom[:1] + arm[:2] + bucket[:1]), 5)
    assert model.determined(np.array(base[:3] + arm[:1] + bucket[:1]), 5)  # five: the count is enough

    truth = session.tracks.of_camera(field.name)
    truth = truth.select(truth.frame < 30)
    first = truth.select((truth.frame == 0) & (truth.score >= 1.0))
    assert len(first) == 4 and model.determined(np.array([index[m] for m in first.marker]), 5)
    renderer = CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(7))
    frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)) for f, image in renderer.frames(np.arange(30))]
    tracks, _ = track_frames(model, iter(frames), session.plan.joints(field.times(np.array([0])))[0], None, field.fps)
    true_xy = {(int(f), m): xy for f, m, xy in zip(truth.frame, truth.marker, truth.xy)}
    error = np.array([np.linalg.norm(xy - true_xy.get((int(f), m), np.inf))
                      for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy)])
    assert np.all(error < 1.0)  # no wrong label
    labelled = set(zip(tracks.frame.tolist(), tracks.marker.tolist()))
    whole = truth.select(truth.score >= 1.0)
    assert sum((int(f), m) in labelled for f, m in zip(whole.frame, whole.marker)) >= 0.99 * len(whole)


def test_a_fit_refused_after_the_shake_is_measured_leaves_the_last_shake(monkeypatch):
    """The image's shift from the model (the camera's shake) is measured from a frame's first
    fit; if the frame's fit is then refused (too few markers kept), the tracker coasts on the
    last kept shift. A shift measured on labels the fit then refused once stuck (172 px on a
    random digger's camera), and the coasting tracker lost the base markers it still had for
    seconds. Here the picture moves 2 px: kept, the shift moves; refused, it stays."""
    from mocap.tracking.run import label_first_frame
    from mocap.tracking.tracker import Tracker, TrackOptions

    machine = random_digger(np.random.default_rng(6))
    session = make_session(machine, "random", n_cameras=1, n_cycles=1, seed=6, size=(960, 540))
    field = session.cameras[0]
    renderer = CameraRenderer(session, 0, RenderOptions(), np.random.default_rng(6))
    grays = [cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) for _, image in renderer.frames(np.arange(2))]
    moved = cv2.warpAffine(grays[1], np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 0.0]]), (960, 540),
                           borderMode=cv2.BORDER_REPLICATE)
    model, options = CameraModel(machine, field.camera), TrackOptions()
    first = label_first_frame(model, grays[0], session.plan.joints(field.times(np.array([0])))[0], None, options)

    kept = Tracker(model, first, options)
    assert kept.step(moved).fitted
    assert np.abs(kept.state.shift).max() > 0.05  # (the joints' fit takes up part of the move)

    refused = Tracker(model, first, options)
    calls = []
    determined = CameraModel.determined

    def refuse_the_kept(self, markers, enough):  # the third test of a step: the markers kept after the first fit
        calls.append(len(markers))
        return determined(self, markers, enough) and len(calls) != 3
    monkeypatch.setattr(CameraModel, "determined", refuse_the_kept)
    assert not refused.step(moved).fitted and len(calls) == 3
    assert np.array_equal(refused.state.shift, np.zeros(2))
