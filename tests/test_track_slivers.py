"""An oblique disk whose image is a sliver about 2 px wide, on its foreshortened square beside
dark paint (look 4 of the benchmark's seed-7 looks, links drawn as solids the tracker does not
assume): its faint ends lost to blur and the pixel grid, its ellipse reads well under the
disk's face-on radius, and the ring around the blurred ellipse reaches the paint."""

from __future__ import annotations

import cv2
import numpy as np

from mocap.io.machine_toml import load_machine
from mocap.synthetic.effects import EffectOptions
from mocap.synthetic.looks import random_look
from mocap.synthetic.render import RenderOptions
from mocap.synthetic.session import make_session
from mocap.synthetic.videos import renderer_for
from mocap.tracking import CameraModel, track_frames

N_FRAMES = 8


def test_a_sliver_where_the_fit_puts_its_marker_is_labelled():
    """U11 is wholly in view in every frame, 1.95 px across its narrowest way (a disk of about
    4.5 px radius turned 78 degrees from the camera). Labelled in at least half of the 8 frames (5 now),
    within 0.5 px of its true centre (the fit of the other markers puts it there to a few
    tenths), and no label anywhere 0.5 px or more off. Before: U11 in none of them (the ring
    test refused its disk, and where a refinement took it, the size test against the face-on
    radius did)."""
    machine = load_machine("hitachi_ex3500")
    look = random_look(np.random.default_rng([7, 4]), name="look 4")
    size = (round(960 * look.scale / 2) * 2, round(540 * look.scale / 2) * 2)
    session = make_session(machine, "hitachi_ex3500", n_cameras=3, n_cycles=1, seed=11, size=size,
                           distortion=look.distortion, shake_deg=look.shake_deg, readout=look.readout, shapes="meshes")
    field = session.cameras[0]
    options = RenderOptions(effects=EffectOptions(look.noise, look.blur, look.exposure, look.dust), look=look)
    renderer = renderer_for(session, 0, options, np.random.default_rng([7, 4, 1]))
    frames = [(f, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)) for f, image in renderer.frames(np.arange(N_FRAMES))]
    model = CameraModel(machine, field.camera)
    tracks, _ = track_frames(model, iter(frames), session.plan.joints(field.times(np.array([0])))[0], None, field.fps)

    truth = session.tracks.of_camera(field.name)
    truth = truth.select(truth.frame < N_FRAMES)
    true_xy = {(int(f), m): xy for f, m, xy in zip(truth.frame, truth.marker, truth.xy)}
    whole = truth.select((truth.marker == "U11") & (truth.score >= 1.0))
    assert len(whole) == N_FRAMES
    error = np.array([np.linalg.norm(xy - true_xy.get((int(f), m), np.inf))
                      for f, m, xy in zip(tracks.frame, tracks.marker, tracks.xy)])
    assert np.all(error < 0.5)
    sliver = tracks.marker == "U11"
    assert np.sum(sliver) >= N_FRAMES // 2
