"""Multi-view triangulation of every marker in every frame (the APAS replacement).

For all points at once: pixels are undistorted (cv2.undistortPoints), a linear DLT on
normalised coordinates gives a start, and a few Gauss-Newton steps minimise the pixel
reprojection error with the cameras' analytic projection Jacobians. With three or more
views a point whose worst view is off by more than `max_error_px` is re-triangulated
leaving each view out in turn (all candidates in one batch); the view whose removal fits
the rest best is dropped, repeatedly while at least three views remain.

One frame cannot tell every wrong view: a wild pixel along the epipolar line of the only
other view, or of one of two others, leaves views that agree. `triangulate_tracks` also
asks each marker's 3-D track: a view far from what the point's neighbours in time predict,
where another view is near it, is dropped (the point too, where fewer than two views stay).

Shapes: C cameras, N points (any leading shape, e.g. F frames by M markers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mocap.core.camera import Camera, project_cam
from mocap.reconstruct.outliers import PREDICTORS, dense_tracks, noise_from_fits

_EPS = 1e-9
# a 3-D track's predictions: the 2-D tracks' ones; points between f-a and f+b, a != b, for a
# gap beside the frame; and lines from f+2, f+3 (f-2, f-3) for a track's end whose next frame
# is missing (each prediction's uncertainty is counted, so a long lever is fair)
TRACK_PREDICTORS = (
    *PREDICTORS,
    *({-a: b / (a + b), b: a / (a + b)} for a in (1, 2, 3) for b in (1, 2, 3) if a != b),
    {2: 3.0, 3: -2.0}, {-2: 3.0, -3: -2.0},
)
SMOOTH_SHARE = 0.5  # a marker's 3-D track is judged only where this share of its points is on it
TRACK_FRAMES = max(abs(o) for p in TRACK_PREDICTORS for o in p)  # frames either side a 3-D track predicts from


@dataclass(frozen=True)
class TriangulateOptions:
    """iterations: Gauss-Newton steps; max_error_px: a view whose reprojection error
    exceeds this is an outlier candidate (with >= 3 views), and a point seen by two views
    whose views disagree by more is dropped; None: `sigmas` times the pixel noise the data
    have (estimated robustly from every point's residuals); min_views: views needed."""

    iterations: int = 2
    max_error_px: float | None = None
    sigmas: float = 5.0
    min_views: int = 2

    def __post_init__(self) -> None:
        if self.iterations < 0 or self.min_views < 2 or not self.sigmas > 0:
            raise ValueError("iterations >= 0, min_views >= 2 and sigmas > 0 are required")
        if self.max_error_px is not None and not self.max_error_px > 0:
            raise ValueError("max_error_px must be positive")


@dataclass(frozen=True)
class Triangulation:
    """xyz (*, 3) world metres, NaN where fewer than `min_views` views; error_px (*) RMS
    reprojection error over the used views; views (*) number of used views; used (C, *)
    which views were used (False where not seen or dropped as an outlier); contradicted (*)
    how many of a point's views its marker's 3-D track contradicted (`triangulate_tracks`;
    None where the tracks were not asked)."""

    xyz: np.ndarray
    error_px: np.ndarray
    views: np.ndarray
    used: np.ndarray
    contradicted: np.ndarray | None = None

    def __post_init__(self) -> None:
        shape = np.shape(self.error_px)
        if np.shape(self.xyz) != shape + (3,) or np.shape(self.views) != shape or np.shape(self.used)[1:] != shape:
            raise ValueError("Triangulation needs xyz (*, 3), views (*) and used (C, *) for error_px (*)")
        if self.contradicted is not None and np.shape(self.contradicted) != shape:
            raise ValueError("Triangulation's contradicted must have the shape of error_px (*)")


def triangulate(cameras: list[Camera], pixels: np.ndarray, options: TriangulateOptions | None = None) -> Triangulation:
    """Triangulate points seen by several cameras.

    Parameters
    ----------
    cameras : C calibrated cameras.
    pixels : (C, *, 2) pixels, NaN where a camera did not see the point.

    Returns
    -------
    Triangulation over the leading shape ``*``.
    """
    options = options or TriangulateOptions()
    pixels = np.asarray(pixels, dtype=float)
    if pixels.ndim < 2 or pixels.shape[0] != len(cameras) or pixels.shape[-1] != 2:
        raise ValueError(f"pixels must have shape (C={len(cameras)}, *, 2), got {pixels.shape}")
    shape = pixels.shape[1:-1]
    xyz, error_px, used, *_ = _triangulate_flat(cameras, pixels.reshape(len(cameras), -1, 2), options)
    return Triangulation(
        xyz.reshape(shape + (3,)),
        error_px.reshape(shape),
        used.sum(0).reshape(shape),
        used.reshape((len(cameras),) + shape),
    )


def triangulate_tracks(cameras: list[Camera], pixels: np.ndarray,
                       options: TriangulateOptions | None = None, floor_px: float = 3.0) -> Triangulation:
    """Triangulate markers' tracks: pixels (C, F, M, 2) of consecutive frames. Each point as
    `triangulate` does; then each point is compared with what its marker's 3-D track
    predicts (the points of frames f-3 … f+3, the predictions `TRACK_PREDICTORS`, each
    with its uncertainty from its points' normal matrices). A point within `sigmas` SDs of a
    prediction is on its track; for the others each seen view is compared with the
    predictions projected into it: a used view far from every one (beyond `sigmas` SDs of
    the pixel noise plus the prediction's uncertainty, and beyond `floor_px`), where another
    seen view is near one, is dropped and the point triangulated again from the views near
    one (a view dropped before but near one is taken back); with fewer than two of them the
    point is dropped. A marker with fewer than `SMOOTH_SHARE` of its points on its track is
    not judged (frames too far apart in time), nor one whose 2-D track in some camera bends
    between frames by more than its noise and `floor_px / sigmas` (`dense_tracks`: every
    k-th frame of a video, a board moved far between stills). A point with one prediction (a track's end,
    a gap) is judged only where two views are near it; with none it is left as
    `triangulate` made it. A point judged so is judged again from predictions without the
    points so judged (a wrong neighbour spoils the predictions it is in), and changed only
    if that says so too. Returns a Triangulation over (F, M); its `contradicted` counts
    the views dropped so."""
    options = options or TriangulateOptions()
    pixels = np.asarray(pixels, dtype=float)
    if pixels.ndim != 4 or pixels.shape[0] != len(cameras) or pixels.shape[-1] != 2:
        raise ValueError(f"pixels must have shape (C={len(cameras)}, F, M, 2), got {pixels.shape}")
    n_cams, shape = len(cameras), pixels.shape[1:3]
    flat = pixels.reshape(n_cams, -1, 2)
    xyz, error_px, used, noise, normal = _triangulate_flat(cameras, flat, options)
    seen = np.isfinite(flat).all(-1)
    covariance = np.full(normal.shape, np.nan)
    solved = np.isfinite(xyz).all(-1)
    covariance[solved] = noise**2 * np.linalg.inv(normal[solved])
    points, spread = xyz.reshape(shape + (3,)), covariance.reshape(shape + (3, 3))
    on_track, predicted = _on_the_track(points, spread, options.sigmas)
    # a marker whose points are mostly off their track moves too far between frames to be judged
    smooth = on_track.reshape(shape).sum(0) >= SMOOTH_SHARE * predicted.reshape(shape).sum(0)
    # ... and so does one whose 2-D tracks bend between frames by more than their noise (sparse frames)
    smooth &= np.all([dense_tracks(pixels[c], floor_px / options.sigmas) for c in range(n_cams)], axis=0)
    redo = np.nonzero(predicted & ~on_track & np.broadcast_to(smooth, shape).reshape(-1))[0]
    for second in (False, True):  # judged again without the points judged wrong: a wrong neighbour spoils predictions
        if not len(redo):
            break
        base = points.copy()
        if second:
            base.reshape(-1, 3)[redo] = np.nan
        near, count = _near_the_track(cameras, flat[:, redo], base, spread, redo, noise, options.sigmas, floor_px)
        near_views = (seen[:, redo] & near).sum(0)
        # one prediction could be spoiled by a wrong neighbour: it judges only where two views agree with it
        judged = (count >= 2) | ((count == 1) & (near_views >= 2))
        contradicted = judged & used[:, redo] & ~near
        keep = contradicted.any(0) & (near_views >= 1)
        redo, near, contradicted = redo[keep], near[:, keep], contradicted[:, keep]
    dropped = np.zeros(flat.shape[1], int)
    if len(redo):
        dropped[redo] = contradicted.sum(0)
        again = np.where((seen[:, redo] & near)[..., None], flat[:, redo], np.nan)
        xyz[redo], error_px[redo], used[:, redo], *_ = _triangulate_flat(cameras, again, options, noise)
    return Triangulation(
        xyz.reshape(shape + (3,)), error_px.reshape(shape), used.sum(0).reshape(shape),
        used.reshape((n_cams,) + shape), dropped.reshape(shape),
    )


def _prediction(xyz: np.ndarray, covariance: np.ndarray, predictor: dict[int, float], at: np.ndarray):
    """A predictor's ({frame offset: weight}, `TRACK_PREDICTORS`) prediction (K, 3) of the
    points `at` (K,) (indices into N = F M) of xyz (F, M, 3) from their neighbours in time,
    with its covariance (K, 3, 3) from the neighbours' (F, M, 3, 3), and whether it exists
    (K,)."""
    n_frames, n_markers = xyz.shape[:2]
    points, spreads = xyz.reshape(-1, 3), covariance.reshape(-1, 3, 3)
    frame = at // n_markers
    guess, spread, valid = np.zeros((len(at), 3)), np.zeros((len(at), 3, 3)), np.ones(len(at), bool)
    for offset, weight in predictor.items():
        inside = (frame + offset >= 0) & (frame + offset < n_frames)
        valid &= inside
        other = np.where(inside, at + offset * n_markers, at)
        guess += weight * points[other]
        spread += weight**2 * spreads[other]
    return guess, spread, valid & ~np.isnan(guess[:, 0])  # a point's covariance is NaN where it is


def _on_the_track(xyz: np.ndarray, covariance: np.ndarray, sigmas: float):
    """Whether each point (N,) of xyz (F, M, 3) lies within `sigmas` SDs (its own
    covariance (F, M, 3, 3) and the prediction's) of some prediction of its track, and
    whether it has one (N,)."""
    points, own = xyz.reshape(-1, 3), covariance.reshape(-1, 3, 3)
    on, predicted = np.zeros(len(points), bool), np.zeros(len(points), bool)
    solved = ~np.isnan(points[:, 0])
    for predictor in TRACK_PREDICTORS:
        ask = np.nonzero(solved & ~on)[0]  # one prediction near is enough
        guess, spread, valid = _prediction(xyz, covariance, predictor, ask)
        predicted[ask] |= valid
        ask, gap, spread = ask[valid], points[ask[valid]] - guess[valid], spread[valid]
        d2 = np.einsum("ni,ni->n", gap, np.linalg.solve(own[ask] + spread, gap[..., None])[..., 0])
        on[ask] = d2 <= sigmas**2
    return on, predicted


def _near_the_track(cameras, flat, xyz, covariance, at, noise, sigmas, floor_px):
    """For the views (C, K) of the points `at` (K,) (indices into N = F M) of xyz (F, M, 3),
    pixels `flat` (C, K, 2): whether each seen view is near some prediction of its marker's
    3-D track (within `sigmas` SDs of the pixel noise plus the prediction's uncertainty, or
    within `floor_px`), and each point's number of predictions (K,)."""
    n_cams = len(cameras)
    seen = np.isfinite(flat).all(-1)
    near, count = np.zeros((n_cams, len(at)), bool), np.zeros(len(at), int)
    for predictor in TRACK_PREDICTORS:
        guess, spread, valid = _prediction(xyz, covariance, predictor, at)
        count += valid
        residual, jac = _residuals(cameras, flat, seen & valid, np.where(valid[:, None], guess, 0.0))
        residual, jac = residual.reshape(len(at), n_cams, 2), jac.reshape(len(at), n_cams, 2, 3)
        gap = noise**2 * np.eye(2) + jac @ np.where(valid[:, None, None], spread, 0.0)[:, None] @ np.swapaxes(jac, -1, -2)
        d2 = np.einsum("kci,kci->kc", residual, np.linalg.solve(gap, residual[..., None])[..., 0])
        close = (d2 <= sigmas**2) | ((residual**2).sum(-1) <= floor_px**2)
        near |= (seen & valid[None]) & close.T
    return near, count


def _triangulate_flat(cameras: list[Camera], flat: np.ndarray, options: TriangulateOptions, noise: float | None = None):
    """Points (N,) of pixels (C, N, 2) -> xyz (N, 3), error_px (N,), used (C, N), the pixel
    noise (`noise`, or estimated from the residuals) and each point's normal matrix (N, 3,
    3) in px²/m² (its covariance over the noise²); points seen by fewer than two views are
    left NaN."""
    seen = np.isfinite(flat).all(-1)
    solvable = np.nonzero(seen.sum(0) >= 2)[0]  # the others are left untouched: no point
    xyz = np.full((flat.shape[1], 3), np.nan)
    error_px = np.full(flat.shape[1], np.nan)
    normal = np.full((flat.shape[1], 3, 3), np.nan)
    used = seen.copy()
    if len(solvable):
        xyz[solvable], error_px[solvable], used[:, solvable], noise, normal[solvable] = _triangulate_points(
            cameras, flat[:, solvable], options, noise)
    return xyz, error_px, used, 1.0 if noise is None else noise, normal


def _triangulate_points(cameras: list[Camera], flat: np.ndarray, options: TriangulateOptions, noise: float | None = None):
    """Points (N,) each seen by two or more cameras, pixels (C, N, 2) -> xyz (N, 3) (NaN
    with fewer than `min_views` views left), error_px (N,), used (C, N), the pixel noise
    (`noise`, or estimated from the first solve's residuals) and the normal matrices (N, 3,
    3) at the solution."""
    seen = np.isfinite(flat).all(-1)
    normalised = undistort(cameras, flat)
    used = seen.copy()
    xyz, residual, jac = _solve(cameras, flat, normalised, used, options.iterations)
    noise = _noise(residual, used) if noise is None else noise
    limit = options.max_error_px or options.sigmas * noise
    for _ in range(len(cameras) - 2):
        error = np.where(used, np.linalg.norm(residual, axis=-1), 0.0)
        suspect = np.nonzero((used.sum(0) >= 3) & (error.max(0) > limit))[0]
        if not len(suspect):
            break
        drop, moved = _leave_one_out(xyz[suspect], residual[:, suspect], jac[suspect], used[:, suspect])
        index = suspect[drop >= 0]
        if not len(index):
            break
        used[drop[drop >= 0], index] = False
        xyz[index], residual[:, index], jac[index] = _solve(
            cameras, flat[:, index], normalised[:, index], used[:, index], options.iterations,
            start=moved[drop >= 0],
        )
    views = used.sum(0)
    squared = np.where(used, (residual**2).sum(-1), 0.0).sum(0)
    # two views that disagree: one of them is wrong and nothing tells which
    disagree = (views == 2) & (squared > limit**2)
    used[:, disagree] = False
    views = used.sum(0)
    enough = views >= options.min_views
    error_px = np.where(enough, np.sqrt(squared / np.maximum(views, 1)), np.nan)
    normal = np.swapaxes(jac, 1, 2) @ jac + _EPS * np.eye(3)
    return np.where(enough[:, None], xyz, np.nan), error_px, used, noise, normal


def _noise(residual: np.ndarray, used: np.ndarray) -> float:
    """Pixel noise SD per axis from the residuals (C, N, 2) of points with views `used`
    (C, N): each point's chi-square has 2 v - 3 degrees of freedom."""
    views = used.sum(0)
    squared = np.where(used, (residual**2).sum(-1), 0.0).sum(0)
    sigma = noise_from_fits(squared, 2 * views - 3)
    return sigma if np.isfinite(sigma) and sigma > 0 else 1.0


def undistort(cameras: list[Camera], pixels: np.ndarray) -> np.ndarray:
    """Normalised image coordinates (C, N, 2) of pixels (C, N, 2), NaN stays NaN."""
    out = np.full(pixels.shape, np.nan)
    for c, camera in enumerate(cameras):
        ok = np.isfinite(pixels[c]).all(-1)
        if ok.any():
            points = np.ascontiguousarray(pixels[c, ok].reshape(-1, 1, 2))
            out[c, ok] = cv2.undistortPoints(points, camera.matrix, camera.distortion).reshape(-1, 2)
    return out


def _solve(cameras, pixels, normalised, used, iterations, start=None):
    """DLT (or `start` (N, 3)) then Gauss-Newton for points (N,) with views `used` (C, N)
    -> xyz (N, 3), residuals (C, N, 2) observed minus projected and their Jacobians
    (N, 2C, 3) by xyz (zero where unused), compiled (mocap.reconstruct.triangulate_kernel;
    `_dlt` and `_residuals` are its numpy statement)."""
    from mocap.reconstruct.triangulate_kernel import solve_points

    n_cams, n = used.shape
    xyz, residual, jac = np.empty((n, 3)), np.empty((n_cams, n, 2)), np.empty((n, 2 * n_cams, 3))
    solve_points(
        np.ascontiguousarray(pixels, dtype=float), np.ascontiguousarray(normalised, dtype=float),
        np.ascontiguousarray(used, dtype=bool), np.zeros((0, 3)) if start is None else np.ascontiguousarray(start, dtype=float),
        start is not None, *_camera_arrays(cameras), int(iterations), xyz, residual, jac)
    return xyz, residual, jac


def _camera_arrays(cameras):
    """rotation (C, 3, 3), translation (C, 3), matrix (C, 3, 3) and distortion (C, 5) of the
    cameras, for the compiled solve."""
    rotation = np.array([c.cam_from_world.rotation for c in cameras], dtype=float)
    translation = np.array([c.cam_from_world.translation for c in cameras], dtype=float)
    matrix = np.array([c.matrix for c in cameras], dtype=float)
    distortion = np.array([c.distortion for c in cameras], dtype=float)
    return rotation, translation, matrix, distortion


def _solve_numpy(cameras, pixels, normalised, used, iterations, start=None):
    """`_solve` in numpy (the statement the compiled kernel follows; for tests)."""
    xyz = _dlt(cameras, normalised, used) if start is None else start
    eye = _EPS * np.eye(3)
    for _ in range(iterations):
        residual, jac = _residuals(cameras, pixels, used, xyz)  # (N, 2C), (N, 2C, 3)
        jac_t = np.swapaxes(jac, 1, 2)
        normal = jac_t @ jac
        lhs = normal + (1.0 + np.trace(normal, axis1=1, axis2=2) / 3)[:, None, None] * eye  # damped relative to its scale
        rhs = jac_t @ residual[..., None]
        bad = ~(np.isfinite(lhs).all((1, 2)) & np.isfinite(rhs).all((1, 2)))  # a point gone behind a camera
        lhs[bad], rhs[bad] = np.eye(3), 0.0
        xyz = xyz + np.linalg.solve(lhs, rhs)[..., 0]
    residual, jac = _residuals(cameras, pixels, used, xyz)
    return xyz, np.moveaxis(residual.reshape(len(xyz), len(cameras), 2), 1, 0), jac


def _dlt(cameras, normalised, used) -> np.ndarray:
    """Linear triangulation (N, 3): least squares of x P3 - P1 = 0, y P3 - P2 = 0 over the
    used views with P = [R | t] on undistorted normalised coordinates."""
    n_cams, n = used.shape
    rows = np.empty((n, n_cams, 2, 4))
    for c, camera in enumerate(cameras):
        projection = np.c_[camera.cam_from_world.rotation, camera.cam_from_world.translation]
        xy = np.where(used[c][:, None], normalised[c], 0.0)
        w = used[c].astype(float)[:, None, None]
        rows[:, c] = (xy[:, :, None] * projection[2] - projection[:2]) * w
    rows = rows.reshape(n, 2 * n_cams, 4)
    lhs = np.swapaxes(rows, 1, 2) @ rows
    return np.linalg.solve(lhs[:, :3, :3] + _EPS * np.eye(3), -lhs[:, :3, 3:])[..., 0]


def _residuals(cameras, pixels, used, xyz, with_jacobian=True):
    """Residuals (N, 2C) and d(projection)/d(xyz) (N, 2C, 3), zero where unused."""
    n = len(xyz)
    residual = np.empty((n, len(cameras), 2))
    jac = np.empty((n, len(cameras), 2, 3)) if with_jacobian else None
    for c, camera in enumerate(cameras):
        rot = camera.cam_from_world.rotation
        out = project_cam(xyz @ rot.T + camera.cam_from_world.translation, camera.matrix, camera.distortion, with_jacobian)
        uv, d_uv = out if with_jacobian else (out, None)
        ok = used[c] & np.isfinite(uv[:, 0])
        residual[:, c] = np.where(ok[:, None], pixels[c] - uv, 0.0)
        if with_jacobian:
            jac[:, c] = (d_uv.reshape(-1, 3) @ rot).reshape(n, 2, 3) * ok[:, None, None]
    residual = residual.reshape(n, -1)
    return residual, None if jac is None else jac.reshape(n, -1, 3)


def _leave_one_out(xyz: np.ndarray, residual: np.ndarray, jac: np.ndarray, used: np.ndarray):
    """For suspect points (N,): the view (N,) whose removal leaves the smallest RMS error of
    the remaining views, or -1 where no view can be removed, and the points moved by the
    step that removal implies (N, 3), a start for re-triangulating without the view.

    Each removal is ranked by one Gauss-Newton step from the all-view solution without that
    view, and the remaining residuals predicted linearly (residual (C, N, 2) and jac
    (N, 2C, 3) at the all-view solution): no new projections.
    """
    n_cams, n = used.shape
    jac = jac.reshape(n, n_cams, 2, 3)
    r = np.moveaxis(residual, 0, 1)  # (N, C, 2)
    jac_t = np.swapaxes(jac, -1, -2)  # (N, C, 3, 2)
    hessian_views = jac_t @ jac  # (N, C, 3, 3), zero for unused views
    gradient_views = (jac_t @ r[..., None])[..., 0]  # (N, C, 3)
    hessian = hessian_views.sum(1, keepdims=True) - hessian_views + _EPS * np.eye(3)
    gradient = gradient_views.sum(1, keepdims=True) - gradient_views
    step = np.linalg.solve(hessian, gradient[..., None])[..., 0]  # (N, K left out, 3)
    predicted = r[:, None] - np.einsum("nckd,njd->njck", jac, step)  # (N, K, C, 2)
    keep = used.T[:, None, :] & ~np.eye(n_cams, dtype=bool)[None]  # (N, K, C)
    squared = np.where(keep, (predicted**2).sum(-1), 0.0).sum(-1)
    views = keep.sum(-1)
    rms = np.where(used.T & (views >= 2), np.sqrt(squared / np.maximum(views, 1)), np.inf)
    best = np.argmin(rms, axis=1)
    moved = xyz + step[np.arange(n), best]
    return np.where(np.isfinite(rms[np.arange(n), best]), best, -1), moved
