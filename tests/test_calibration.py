"""The paper's calibration tests on generated data, and the guards around them."""

import numpy as np
import pytest
from conftest import reasonable_guess, scene

from mocap.calibration import CalibrationOptions, Guess, Observations, calibrate, template_camera
from mocap.calibration.dlt import decompose_projection, dlt_camera
from mocap.calibration.problem import Layout, Problem
from mocap.core.camera import Camera
from mocap.core.geometry import rotation_angle_between
from mocap.errors import ConvergenceError, DegenerateError
from mocap.io.machine_toml import machine_from_dict, machine_to_dict
from mocap.synthetic.scenes import look_at_camera, observe


def templates(cameras):
    return [template_camera(c.name, c.size) for c in cameras]


def camera_errors(fitted, truth):
    centre = max(np.linalg.norm(a.center - b.center) for a, b in zip(fitted, truth))
    angle = max(
        rotation_angle_between(a.cam_from_world.rotation, b.cam_from_world.rotation)
        for a, b in zip(fitted, truth)
    )
    focal = max(abs(a.focal - b.focal) / b.focal for a, b in zip(fitted, truth))
    return centre, angle, focal


def cube_scene(cube_pair, seed=0, noise_px=0.0):
    cameras, _, obs, _ = scene(cube_pair, 1, seed, noise_px=noise_px, distance=(2.5, 4.0))
    return cameras[0], obs


# --- test 1 of the paper: the cube pair -----------------------------------------------------
def test_cube_pair_exact_model_is_recovered_exactly(cube_pair):
    camera, obs = cube_scene(cube_pair)
    result = calibrate(cube_pair, obs, templates([camera]))
    fitted = result.cameras[0]
    assert np.allclose(fitted.to_paper().as_vector(), camera.to_paper().as_vector(), rtol=1e-6, atol=1e-6)
    assert result.rms_px < 1e-6


def test_cube_pair_with_5_percent_model_error_fits_closely(cube_pair):
    """Every marker coordinate off by -5 % .. +5 %. Least squares can do no worse than the
    true camera, whose residual is the model error's own image (e px). The fitted camera
    then projects the true markers within 2 e (the residual plus the model error as the
    fitted camera sees it) and the approximate ones within e."""
    rng = np.random.default_rng(11)
    for seed in range(10):
        camera, obs = cube_scene(cube_pair, seed)
        data = machine_to_dict(cube_pair)
        for marker in data["markers"]:
            marker["position"] = (np.array(marker["position"]) * rng.uniform(0.95, 1.05, 3)).tolist()
        approximate = machine_from_dict(data)
        result = calibrate(approximate, obs, templates([camera]))
        model_error_px = np.sqrt(np.mean(np.sum((camera.project(approximate.marker_positions[obs.marker]) - obs.xy) ** 2, axis=1)))
        assert result.rms_px <= model_error_px + 1e-9
        true_points = cube_pair.marker_positions[obs.marker]
        fitted = result.cameras[0].project(true_points)
        rms_true = np.sqrt(np.mean(np.sum((fitted - camera.project(true_points)) ** 2, axis=1)))
        assert rms_true <= 2 * model_error_px


def test_cube_pair_converges_from_reasonable_guesses(cube_pair):
    """Angles off by up to 30 deg, position by 30 %, focal length by a factor of 2: 50 seeded
    starts (benchmarks/bench_calibration.py --only starts holds 500 of them to the same bound)."""
    camera, obs = cube_scene(cube_pair, 3, noise_px=0.3)
    reference = calibrate(cube_pair, obs, templates([camera])).cameras[0].to_paper()
    truth = camera.to_paper()
    rng = np.random.default_rng(5)
    worst = 0.0
    for _ in range(50):
        guess = reasonable_guess(truth, rng)
        result = calibrate(cube_pair, obs, templates([camera]), guess=Guess({camera.name: guess}))
        paper = result.cameras[0].to_paper()
        worst = max(worst, np.linalg.norm(paper.position - reference.position))
    assert worst < 1e-4  # every start reached the same (right) solution


# --- test 2 and 3 of the paper: excavator and shovel with unknown joints -------------------
@pytest.mark.parametrize("machine_name", ["bobcat", "ex3500"])
@pytest.mark.parametrize("n_cameras", [1, 2, 3])
def test_machine_with_unknown_joints_no_guess(request, machine_name, n_cameras):
    machine = request.getfixturevalue(machine_name)
    for seed in range(3):
        cameras, q, obs, _ = scene(machine, n_cameras, seed=100 * n_cameras + seed)
        result = calibrate(machine, obs, templates(cameras))
        # the errors are within 5 standard deviations of the fit's own covariance
        truth = Layout(n_cameras, machine.n_joints).pack(cameras, q)
        z = np.abs(result.parameters - truth) / result.std
        assert np.max(z) < 5.0, dict(zip(result.parameter_names, z.round(1)))
        assert np.max(np.abs(np.degrees(result.joints - q))) < 3.0
        assert 0.3 < result.rms_px < 0.8  # 0.5 px per axis noise: ~0.5-0.7 px rms
        assert not result.outliers


def test_per_camera_joints(ex3500):
    cameras, q, obs, _ = scene(ex3500, 2, seed=7)
    result = calibrate(ex3500, obs, templates(cameras), CalibrationOptions(per_camera=True))
    assert result.joints.shape == (2, 4)
    assert np.max(np.abs(np.degrees(result.joints - q))) < 2.0
    assert np.all(result.joints_sd > 0) and result.joints_sd.shape == (2, 4)


def test_wrong_observation_is_named_and_dropped(ex3500):
    cameras, q, obs, tracks = scene(ex3500, 2, seed=21, outliers=2)
    clean = scene(ex3500, 2, seed=21)[2]
    moved = np.linalg.norm(obs.xy - clean.xy, axis=1) > 10
    result = calibrate(ex3500, obs, templates(cameras))
    named = {(r.camera, r.marker) for r in result.outliers}
    truth = {(tracks.camera[k], tracks.marker[k]) for k in np.nonzero(moved)[0]}
    assert named == truth
    assert np.max(np.abs(np.degrees(result.joints - q))) < 2.0


def test_fitting_distortion_and_principal_point(ex3500):
    rng = np.random.default_rng(3)
    camera = look_at_camera("c", (1920, 1080), 1400.0, [25.0, -28.0, 9.0], [5.0, 0.0, 5.0],
                            distortion=np.array([-0.08, 0.0, 0.0, 0.0, 0.0]))
    joints = np.radians([[-20.0, 35.0, -70.0, 20.0], [40.0, 50.0, -90.0, 60.0]])
    # two poses of the machine seen at once stand in for a richer frame: stack as markers
    tracks = observe([camera], ex3500, joints[:1], rng, noise_px=0.2)
    obs = Observations(np.zeros(len(tracks), int), ex3500.marker_index(tracks.marker), tracks.xy)
    plain = calibrate(ex3500, obs, templates([camera]))
    fitted = calibrate(ex3500, obs, templates([camera]), CalibrationOptions(distortion="k1"))
    assert fitted.rms_px < plain.rms_px
    assert abs(fitted.cameras[0].distortion[0] - (-0.08)) < 4 * fitted.std[7]


@pytest.mark.parametrize("offsets", [False, True])
def test_analytic_jacobian_matches_finite_differences(ex3500, offsets):
    cameras, q, obs, _ = scene(ex3500, 2, seed=4)
    n_markers = len(ex3500.marker_names) if offsets else 0
    layout = Layout(2, 4, per_camera=True, fit_principal_point=True, distortion="full", n_markers=n_markers)
    cams = [Camera(c.name, c.size, c.matrix, np.array([-0.05, 0.01, 0.001, -0.002, 0.003]), c.cam_from_world) for c in cameras]
    marker_sd = np.full(n_markers, 0.1) if offsets else None
    problem = Problem(ex3500, obs, layout, cams, marker_sd, prior_px=0.7)
    x = layout.pack(cams, np.stack([q, q + 0.01]))
    x[layout.offset_slice] = np.random.default_rng(1).normal(0, 0.05, 3 * n_markers)
    analytic = problem.jacobian(x)
    numeric = np.empty_like(analytic)
    for i in range(len(x)):
        h = 1e-6 * max(1.0, abs(x[i]))
        step = np.zeros_like(x)
        step[i] = h
        numeric[:, i] = (problem.residuals(x + step) - problem.residuals(x - step)) / (2 * h)
    assert np.allclose(analytic, numeric, rtol=1e-4, atol=1e-3)


def _reference_jacobian(problem, x):
    """The Jacobian (2N, P) of the pixel rows by the formula camera by camera (numpy), as
    `Problem` computed it before its compiled pass."""
    import cv2

    from mocap.core.camera import project_cam

    layout, obs = problem.layout, problem.obs
    machine = problem.machine_at(x)
    jac = np.zeros((len(obs), 2, layout.size))
    for c, template in enumerate(problem.templates):
        rows = np.nonzero(obs.camera == c)[0]
        q = x[layout.joint_slice(c if layout.per_camera else 0)]
        world, d_world_d_q = (a[0] for a in machine.markers_with_jacobian(q[None]))
        world_from_link = machine.link_poses(q[None])[0, :, :3, :3][machine.marker_links]
        start = layout.camera_slice(c).start
        block = x[layout.camera_slice(c)]
        matrix, distortion = layout.intrinsics(block, template)
        rotation, d_rotation = cv2.Rodrigues(block[:3])
        points = world[obs.marker[rows]]
        points_cam = points @ rotation.T + block[3:6]
        uv, d_uv_d_cam = project_cam(points_cam, matrix, distortion, True)
        behind = ~np.isfinite(uv[:, 0])
        uv, d_uv_d_cam = np.nan_to_num(uv), np.nan_to_num(d_uv_d_cam)
        d_cam_d_rvec = np.einsum("kij,nj->nik", d_rotation.reshape(3, 3, 3), points)
        jac[rows, :, start : start + 3] = d_uv_d_cam @ d_cam_d_rvec
        jac[rows, :, start + 3 : start + 6] = d_uv_d_cam
        jac[rows, :, start + 6] = (uv - matrix[:2, 2]) / matrix[0, 0]
        k = start + 7
        if layout.fit_principal_point:
            jac[rows, 0, k], jac[rows, 1, k + 1] = 1.0, 1.0
            k += 2
        u, v = points_cam[:, 0] / points_cam[:, 2], points_cam[:, 1] / points_cam[:, 2]
        r2 = u * u + v * v
        terms = {0: (u * r2, v * r2), 1: (u * r2**2, v * r2**2), 2: (2 * u * v, r2 + 2 * v * v),
                 3: (r2 + 2 * u * u, 2 * u * v), 4: (u * r2**3, v * r2**3)}
        for term in layout.distortion_terms:
            jac[rows, :, k] = matrix[0, 0] * np.stack(terms[term], axis=-1)
            k += 1
        jac[rows[behind]] = 0.0
        d_uv_d_world = d_uv_d_cam @ rotation
        jac[rows, :, layout.joint_slice(c if layout.per_camera else 0)] = d_uv_d_world @ d_world_d_q[obs.marker[rows]]
        d_offset = d_uv_d_world @ world_from_link[obs.marker[rows]]
        for a in range(3):
            jac[rows, :, layout.offset_slice.start + 3 * obs.marker[rows] + a] = d_offset[:, :, a]
    return jac.reshape(2 * len(obs), layout.size)


def test_problem_evaluation_is_the_cameras_pixels_and_the_formula_camera_by_camera(ex3500):
    """Per-camera joints, principal points, full distortion, marker offsets, a camera with
    known intrinsics and a marker behind its camera: the residuals are each camera's own
    projection of the moved markers minus the pixels (BEHIND_PX behind), the prior rows the
    offsets over their SD, and the Jacobian the formula camera by camera to 1e-12."""
    from mocap.calibration.problem import BEHIND_PX

    cameras, q, obs, _ = scene(ex3500, 3, seed=7)
    rng = np.random.default_rng(2)
    m = len(ex3500.marker_names)
    layout = Layout(3, 4, per_camera=True, fit_principal_point=True, distortion="full", n_markers=m,
                    fixed_intrinsics=frozenset([cameras[2].name]))
    cams = [Camera(c.name, c.size, c.matrix, rng.normal(0, 0.02, 5), c.cam_from_world) for c in cameras]
    marker_sd = rng.uniform(0.05, 0.2, (m, 3))
    problem = Problem(ex3500, obs, layout, cams, marker_sd, prior_px=0.7)
    joints = q + rng.normal(0, 0.05, (3, 4))
    x = layout.pack(cams, joints)
    x[layout.offset_slice] = rng.normal(0, 0.05, 3 * m)
    # camera 1 moved forward to just behind its farthest-but-one marker
    points_cam = cams[1].cam_from_world.apply(problem.machine_at(x).markers(joints[1][None])[0])
    x[layout.camera_slice(1).start + 5] -= np.sort(points_cam[obs.marker[obs.camera == 1], 2])[-2] + 0.01
    residuals, jacobian = problem.residuals(x), problem.jacobian(x)

    fitted, _ = layout.unpack(x, cams)
    moved = problem.machine_at(x)
    expected = np.empty((len(obs), 2))
    for c, camera in enumerate(fitted):
        rows = obs.camera == c
        expected[rows] = camera.project(moved.markers(joints[c][None])[0][obs.marker[rows]]) - obs.xy[rows]
    behind = ~np.isfinite(expected[:, 0])
    assert behind.sum() >= 1 and np.all(obs.camera[behind] == 1)
    expected[behind] = BEHIND_PX
    offsets_over_sd = 0.7 * x[layout.offset_slice] / marker_sd.ravel()
    assert np.allclose(residuals, np.r_[expected.ravel(), offsets_over_sd], rtol=1e-12, atol=1e-9)
    reference = _reference_jacobian(problem, x)
    assert np.all(reference[np.repeat(behind, 2)] == 0.0)
    assert np.max(np.abs(jacobian[: 2 * len(obs)] - reference)) <= 1e-12 * np.max(np.abs(reference))
    assert np.array_equal(jacobian[2 * len(obs) :, layout.offset_slice], np.diag(0.7 / marker_sd.ravel()))
    assert not np.any(jacobian[2 * len(obs) :, : layout.offset_slice.start])
    jacobian[:] = 0.0  # the caller's to change: the next call at the same x does not see it
    assert np.max(np.abs(problem.jacobian(x)[: 2 * len(obs)] - reference)) <= 1e-12 * np.max(np.abs(reference))


def test_the_compiled_rodrigues_is_opencvs():
    """The rotation and its derivative by the rotation vector as cv2.Rodrigues gives them,
    at the identity, below and above DBL_EPSILON, near a half turn and at random."""
    import cv2

    from mocap.calibration.problem_kernel import rodrigues

    rng = np.random.default_rng(3)
    vectors = [np.zeros(3), np.array([1e-17, 0.0, 0.0]), np.array([3e-16, -1e-16, 2e-16]),
               np.array([0.0, 0.0, np.pi - 1e-9]), *rng.normal(0.0, 1.5, (20, 3))]
    for r in vectors:
        rotation, jacobian = np.empty((3, 3)), np.empty((3, 9))
        rodrigues(r, rotation, jacobian)
        expected_rotation, expected_jacobian = cv2.Rodrigues(r)
        assert np.allclose(rotation, expected_rotation, rtol=0, atol=1e-15)
        assert np.allclose(jacobian, expected_jacobian, rtol=0, atol=1e-14)


# --- guards ----------------------------------------------------------------------------------
def test_three_markers_are_under_determined(cube_pair):
    camera, obs = cube_scene(cube_pair)
    with pytest.raises(DegenerateError, match="sees 3 marker\\(s\\): its 7 parameters need at least 4"):
        calibrate(cube_pair, obs.select(np.arange(len(obs)) < 3), templates([camera]))


def test_collinear_markers_are_refused(cube_pair):
    data = machine_to_dict(cube_pair)
    for k, marker in enumerate(data["markers"]):
        marker["position"] = [float(k), 0.5 * k, 0.0]
    line = machine_from_dict(data)
    camera = look_at_camera("c", (1920, 1080), 2000.0, [20.0, -15.0, 6.0], [3.0, 1.5, 0.0])
    tracks = observe([camera], line, np.zeros((1, 0)), np.random.default_rng(0), noise_px=0.0)
    obs = Observations(np.zeros(len(tracks), int), line.marker_index(tracks.marker), tracks.xy)
    with pytest.raises(DegenerateError, match="lie on a line"):
        calibrate(line, obs, templates([camera]))


def test_a_plane_seen_face_on_is_refused(cube_pair):
    data = machine_to_dict(cube_pair)
    grid = [[x, y, 0.0] for x in (0.0, 1.0, 2.0) for y in (0.0, 1.0, 2.0)][:8]
    for marker, position in zip(data["markers"], grid):
        marker["position"] = position
    plane = machine_from_dict(data)
    camera = look_at_camera("c", (1920, 1080), 2000.0, [1.0, 1.0, 60.0], [1.0, 1.0, 0.0])
    tracks = observe([camera], plane, np.zeros((1, 0)), np.random.default_rng(0), noise_px=0.0)
    obs = Observations(np.zeros(len(tracks), int), plane.marker_index(tracks.marker), tracks.xy)
    with pytest.raises(DegenerateError, match="focal length and distance of camera\\(s\\) c cannot be told apart"):
        calibrate(plane, obs, templates([camera]))


def test_a_joint_its_markers_cannot_fix_is_refused(bobcat):
    data = machine_to_dict(bobcat)
    # the house keeps one marker, on the swing axis; nothing beyond the house is seen
    data["markers"] = [m for m in data["markers"] if m["link"] in ("undercarriage",)] + [
        {"name": "H0", "link": "house", "position": [0.0, 0.0, 0.2]}
    ]
    data["links"] = data["links"][:2]
    data.pop("points"), data.pop("bucket_angle")
    machine = machine_from_dict(data)
    cameras, q, obs, _ = scene(machine, 1, seed=2, noise_px=0.0)
    with pytest.raises(DegenerateError, match="cannot fix joint\\(s\\) swing"):
        calibrate(machine, obs, templates(cameras))


def test_a_link_without_seen_markers_is_refused(ex3500):
    cameras, q, obs, _ = scene(ex3500, 1, seed=1)
    bucket = ex3500.marker_links[obs.marker] == 4
    with pytest.raises(DegenerateError, match="joint 'bucket' is unknown but no marker on link 'bucket'"):
        calibrate(ex3500, obs.select(~bucket), templates(cameras))


def test_per_camera_needs_base_markers_in_every_camera(ex3500):
    cameras, q, obs, _ = scene(ex3500, 2, seed=1)
    base_in_second = (obs.camera == 1) & (ex3500.marker_links[obs.marker] == 0)
    reduced = obs.select(~base_in_second)
    with pytest.raises(DegenerateError, match="with --per-camera each camera must be placed by the base"):
        calibrate(ex3500, reduced, templates(cameras), CalibrationOptions(per_camera=True))
    # shared pose: the second camera is placed from the other links once the pose is known
    result = calibrate(ex3500, reduced, templates(cameras))
    assert np.linalg.norm(result.cameras[1].center - cameras[1].center) < 3.0


# --- the DLT baseline ------------------------------------------------------------------------
def test_dlt_recovers_a_camera_from_control_points(cube_pair):
    camera, obs = cube_scene(cube_pair, 4)
    result = dlt_camera("c", camera.size, cube_pair.marker_positions[obs.marker], obs.xy)
    assert result.rms_px < 1e-6
    assert np.linalg.norm(result.camera.center - camera.center) < 1e-6
    assert np.allclose(result.camera.matrix, camera.matrix, atol=1e-5)


@pytest.mark.parametrize("scale", [-3.0, 1e-4])
def test_decompose_projection_gives_positive_focal_lengths_and_a_proper_rotation(scale):
    rng = np.random.default_rng(4)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rotation *= np.linalg.det(rotation)  # det +1
    matrix = np.array([[2500.0, 3.0, 960.0], [0.0, 2400.0, 540.0], [0.0, 0.0, 1.0]])
    center = rng.normal(size=3) * 30
    projection = scale * matrix @ np.c_[rotation, -rotation @ center]
    got_matrix, got_rotation, got_center = decompose_projection(projection)
    np.testing.assert_allclose(got_matrix, matrix, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(got_rotation, rotation, atol=1e-12)
    np.testing.assert_allclose(got_center, center, atol=1e-9)


def test_dlt_guards(cube_pair):
    camera, obs = cube_scene(cube_pair, 4)
    with pytest.raises(DegenerateError, match="at least 6 reference points"):
        dlt_camera("c", camera.size, cube_pair.marker_positions[obs.marker[:5]], obs.xy[:5])
    flat = cube_pair.marker_positions[obs.marker] * [1, 1, 0]
    with pytest.raises(DegenerateError, match="coplanar"):
        dlt_camera("c", camera.size, flat, obs.xy)


def test_scrambled_labels_do_not_give_a_silent_answer(ex3500):
    cameras, q, obs, _ = scene(ex3500, 1, seed=8)
    rng = np.random.default_rng(0)
    scrambled = Observations(obs.camera, rng.permutation(obs.marker), obs.xy)
    with pytest.raises(ConvergenceError, match="did not converge: .* check the marker labels"):
        calibrate(ex3500, scrambled, templates(cameras))
