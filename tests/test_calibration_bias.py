"""The calibration's second-order bias correction (`mocap.calibration.bias`): a far
camera's distance, fixed only by a perspective that falls as its inverse, is estimated
too far by about rho^2 of itself (rho its SD over its distance: the estimate is the
inverse of a nearly Gaussian one); the correction brings it in by that much, leaves the
well-fixed cameras where they are, and stays out where the expansion cannot hold."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from mocap.calibration import template_camera
from mocap.calibration.bias import bias_corrected
from mocap.calibration.identify import inverse_information
from mocap.calibration.problem import Layout, Problem
from mocap.core.machine import Tolerance
from mocap.reconstruct.offsets import tape_sd
from mocap.synthetic.bounds import numeric_jacobian
from mocap.synthetic.machines import SceneOptions, random_scene

NOISE_PX = 0.8


def _field_fit(seed: int):
    """A field scene's frame fitted by least squares within the tape's tolerance from the
    truth: the problem, its layout and templates, the solution."""
    scene = random_scene(np.random.default_rng(seed), SceneOptions.field(), n_frames=1)
    cameras = list(scene.cameras)
    layout = Layout(len(cameras), scene.machine.n_joints, n_markers=len(scene.machine.marker_names))
    templates = [template_camera(c.name, c.size) for c in cameras]
    problem = Problem(scene.model, scene.observations(inliers_only=True), layout, templates,
                      marker_sd=tape_sd(Tolerance(0.05), scene.model.marker_positions), prior_px=NOISE_PX)
    x = least_squares(problem.residuals, layout.pack(cameras, scene.joints[0]), jac=problem.jacobian,
                      x_scale="jac").x
    return problem, layout, templates, x


def _distances(layout, templates, problem, x, target) -> np.ndarray:
    return np.array([np.linalg.norm(c.center - target) for c in layout.unpack(x, templates)[0]])


@pytest.mark.parametrize("seed", [1000014, 1000005])
def test_a_far_camera_is_brought_in_by_its_distance_skew(seed):
    problem, layout, templates, x = _field_fit(seed)
    corrected = bias_corrected(problem, x, np.ones(len(x), dtype=bool), NOISE_PX)
    jacobian = problem.jacobian(x)
    covariance = NOISE_PX**2 * inverse_information(jacobian.T @ jacobian)
    target = problem.machine_at(x).markers(x[layout.joint_slice(0)][None])[0].mean(axis=0)
    before = _distances(layout, templates, problem, x, target)
    after = _distances(layout, templates, problem, corrected, target)
    rho = np.empty(len(before))
    for c in range(len(before)):
        s = layout.camera_slice(c)

        def centre(block, s=s, c=c):
            y = x.copy()
            y[s] = block
            return layout.unpack(y, templates)[0][c].center

        gradient = numeric_jacobian(centre, x[s])
        direction = (centre(x[s]) - target) / before[c]
        rho[c] = np.sqrt(direction @ gradient @ covariance[s, s] @ gradient.T @ direction) / before[c]
    assert rho.max() > 0.15  # the scene has a camera its markers hardly fix
    np.testing.assert_allclose((after - before) / before, -rho**2, rtol=0.25, atol=2e-3)


def test_left_alone_where_the_expansion_cannot_hold():
    problem, _, _, x = _field_fit(1000031)  # cameras whose SD is near their distance
    assert bias_corrected(problem, x, np.ones(len(x), dtype=bool), NOISE_PX) is x
