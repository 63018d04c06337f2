"""A mirror solution at the session's first frame: the frames after it all agree, the
first frame's pixels are explained as well by their solution, and there is no frame before
it to come back to. The fit takes the continuous solution there as it does inside."""

import numpy as np

from mocap.reconstruct.kinfit import FitOptions, fit_joints
from mocap.reconstruct.timing import tracks_on_reference_clock
from mocap.reconstruct.uncertainty import point_quantities
from mocap.synthetic.machines import SceneOptions, random_scene

FIRST_FRAME_MIRROR = 21  # a field scene: two cameras; frame 0 shows a link's mirror as well as its own pose


def test_a_first_frame_on_a_mirror_solution_takes_the_continuous_one():
    scene = random_scene(np.random.default_rng(FIRST_FRAME_MIRROR), SceneOptions.field(), n_frames=40)
    names = [c.name for c in scene.cameras]
    ones = np.ones(len(names))
    pixels = tracks_on_reference_clock(scene.tracks, names, scene.machine.marker_names, 30.0 * ones, 0 * ones).pixels
    fit = fit_joints(scene.machine, list(scene.cameras), pixels, options=FitOptions())
    tip = point_quantities(scene.machine, np.nan_to_num(fit.joints), fit.covariance)
    error = np.linalg.norm(tip.points[:, 0] - scene.machine.points(scene.joints)[:, 0], axis=1)
    z = error / tip.points_sd[:, 0]
    assert fit.valid.all() and fit.explained.all()
    assert z.max() < 5.0, f"frame {z.argmax()}: the tip {z.max():.1f} SDs from the truth"
    assert np.sqrt(np.mean(z**2)) < 1.5  # 40 frames of an honest SD: RMS 1 ± 0.12
