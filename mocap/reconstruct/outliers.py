"""Wild pixels: observations their own track contradicts, and the pixel noise the data
actually have.

A marker's track is smooth at the frame rate (a machine's links do not jump), so a pixel
far from what its neighbours in time predict is a wrong detection, whatever the number of
cameras that see the marker. A pixel is compared with what its neighbours predict
(midpoints of f-k and f+k, k = 1, 2, 3, and straight-line extrapolations from either side)
and kept if it is near any of them (a wild neighbour spoils only the predictions it is
in); the threshold follows the deviations the track
actually has (`factor` times their robust scale), never less than `floor_px`.

Frames need not be a dense video: every k-th frame of one, or a board moved far between
stills, bends a track between its frames by more than the noise. The bend is read from the
data (`track_bends`): a track whose midpoint predictions err from its motion by more than
`floor_px / factor` (and than noise alone makes that estimate), at its turns and at the
median of its frames alike, is not judged, whatever its frame numbers say.

Shapes: F frames, M markers.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mocap.reconstruct.chi2 import upper_quantile

RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median length of a 2-D Gaussian of unit SD per axis
NOISE_BEND = 2.5  # pure noise gives n points' bend estimate up to this / sqrt(n) of their noise
BEND_PERCENTILE = 90  # a track's bend and noise read at this percentile: a motion bends it at its turns
DENSE_PERCENTILE = 50  # whether a track is dense, read at the median of its frames: a wild pixel bends it at three


# Predictions of a pixel from its neighbours, exact for a steady motion: {frame offset:
# weight}. Midpoints of f-k and f+k, then one-sided extrapolations for the ends of a track.
PREDICTORS = (
    {-1: 0.5, 1: 0.5}, {-2: 0.5, 2: 0.5}, {-3: 0.5, 3: 0.5},
    {1: 2.0, 2: -1.0}, {-1: 2.0, -2: -1.0}, {1: 1.5, 3: -0.5}, {-1: 1.5, -3: -0.5},
)


def track_outliers(pixels: np.ndarray, factor: float = 6.0, floor_px: float = 3.0, rough_px: float = 3.0) -> np.ndarray:
    """(F, M) True where a pixel of pixels (F, M, 2) (one camera, consecutive frames, NaN
    where not seen) is far from every prediction its neighbours make: beyond `factor` times
    the deviations' robust scale (each prediction's deviation divided by its own noise
    gain; the larger of the scale of each marker's own track and of all smooth tracks) and
    beyond `floor_px`. A pixel with fewer than two predictions is never flagged, nor any
    pixel of a track whose typical deviation exceeds `rough_px` (frames too far apart in
    time to judge), nor of a track that bends between its frames by more than its noise
    (`dense_tracks`: sparse frames of a video). A flagged pixel is judged again without the flagged ones: a good pixel
    whose neighbours were all wild is kept when its other neighbours agree with it."""
    pixels = np.asarray(pixels, dtype=float)
    judged, scaled, raw = _deviations(pixels, pixels, np.ones(pixels.shape[:2], bool))
    judged &= dense_tracks(pixels, floor_px / factor)[None]
    if not judged.any():
        return np.zeros(pixels.shape[:2], bool)
    tracked = judged.any(0)
    scale = np.full(judged.shape[1], np.inf)  # (M,) each track's own scale
    scale[tracked] = np.nanmedian(np.where(judged, scaled, np.nan)[:, tracked], axis=0) / RAYLEIGH_MEDIAN
    smooth = scale <= rough_px  # a rough track (frames too far apart in time) cannot tell a wild pixel
    calm = judged & smooth[None]
    limit = factor * np.maximum(scale, np.median(scaled[calm]) / RAYLEIGH_MEDIAN if calm.any() else 0.0)
    flagged = calm & (scaled > limit) & (raw > floor_px)
    if flagged.any():
        again = _deviations(np.where(flagged[..., None], np.nan, pixels), pixels, flagged)
        flagged &= ~(again[0] & ((again[1] <= limit) | (again[2] <= floor_px)))
    return flagged


def track_bends(points: np.ndarray, percentile: float = BEND_PERCENTILE) -> tuple[np.ndarray, np.ndarray]:
    """Per track of points (F, M, D) (consecutive frames, NaN where not seen): how far its
    motion bends it between frames and its noise, both as the error they give the midpoint
    of the frames either side (M,), read from the second differences over one and two
    frames (their `BEND_PERCENTILE` percentile: a motion bends a track most at its turns):
    noise gives both alike, a bend (acceleration a per frame squared) a / 2 and 2 a.
    NaN where a track has no five consecutive points."""
    points = np.asarray(points, dtype=float)
    one, two = np.full(points.shape[:2], np.nan), np.full(points.shape[:2], np.nan)
    if len(points) >= 5:
        middle = points[2:-2]
        one[2:-2] = np.sum((middle - 0.5 * (points[1:-3] + points[3:-1])) ** 2, -1)
        two[2:-2] = np.sum((middle - 0.5 * (points[:-4] + points[4:])) ** 2, -1)
        two[np.isnan(one)], one[np.isnan(two)] = np.nan, np.nan
    counted = np.isfinite(one).any(0)
    m1, m2 = np.full(points.shape[1], np.nan), np.full(points.shape[1], np.nan)
    m1[counted], m2[counted] = (np.nanpercentile(d[:, counted], percentile, 0) for d in (one, two))
    bend2 = np.maximum(m2 - m1, 0.0) / 15.0  # (2 a)^2 - (a / 2)^2 = 15 (a / 2)^2
    return np.sqrt(bend2), np.sqrt(np.maximum(m1 - bend2, 0.0))


def dense_tracks(points: np.ndarray, least: float) -> np.ndarray:
    """(M,) whether each track of points (F, M, D) is sampled densely enough for its
    neighbours in time to predict it: its bend between frames (`track_bends`) is within
    `least` / 4 (the midpoint of f-2 and f+2 errs by four times it), or within what noise
    alone gives the estimate from n points (`NOISE_BEND` / sqrt(n) of the noise: beyond it
    once in a thousand noise tracks). It is sparse only where it bends so at the median of
    its frames as well as at `BEND_PERCENTILE`: sparse frames bend a track at every frame,
    a wild pixel at the three around it (which would excuse itself from being judged).
    A track too short to tell counts as dense."""
    points = np.asarray(points, dtype=float)
    counted = np.isfinite(points[2:-2, ..., 0] + points[1:-3, ..., 0] + points[3:-1, ..., 0] + points[:-4, ..., 0]
                          + points[4:, ..., 0]).sum(0) if len(points) >= 5 else np.zeros(points.shape[1])
    sparse = np.ones(points.shape[1], bool)
    for percentile in (BEND_PERCENTILE, DENSE_PERCENTILE):  # sparse frames bend a track at both, a wild pixel at the first
        bend, noise = track_bends(points, percentile)
        sparse &= bend > np.maximum(NOISE_BEND / np.sqrt(np.maximum(counted, 1)) * noise, least / 4)
    return ~sparse


def _deviations(pixels: np.ndarray, values: np.ndarray, todo: np.ndarray):
    """Per pixel of values (F, M, 2) that todo (F, M) names: whether two or more
    predictions from pixels (F, M, 2) exist, and the deviation from the nearest one divided
    by its noise gain, and in pixels (compiled: mocap.reconstruct.outliers_kernel)."""
    from mocap.reconstruct.outliers_kernel import deviations

    n_terms = max(len(w) for w in PREDICTORS)
    offsets = np.zeros((len(PREDICTORS), n_terms), np.int64)
    weights = np.zeros((len(PREDICTORS), n_terms))
    for k, predictor in enumerate(PREDICTORS):
        offsets[k, : len(predictor)] = list(predictor)
        weights[k, : len(predictor)] = list(predictor.values())
    gains = np.sqrt(1.0 + (weights**2).sum(1))  # noise of pixel minus prediction
    shape = pixels.shape[:2]
    out = np.empty(shape, bool), np.empty(shape), np.empty(shape)
    deviations(np.ascontiguousarray(pixels, dtype=float), np.ascontiguousarray(values, dtype=float),
               np.ascontiguousarray(todo, dtype=bool), offsets, weights, gains, *out)
    return out


def noise_from_fits(sum_squares: np.ndarray, dof: np.ndarray) -> float:
    """Pixel noise SD per axis from many small fits' sums of squared residuals (N,) with
    their degrees of freedom (N,): the median of each fit's sqrt(chi-square / dof), divided
    by that statistic's median under pure noise, so that wild fits do not move it."""
    ok = (dof > 0) & np.isfinite(sum_squares)
    if not ok.any():
        return float("nan")
    statistic = np.sqrt(sum_squares[ok] / dof[ok])
    distinct, inverse = np.unique(dof[ok], return_inverse=True)
    medians = _chi2_medians(distinct.dtype.str, distinct.tobytes())  # the few distinct dof once
    expected = np.sqrt(medians / distinct)[inverse]  # median of sqrt(chi2_k / k)
    return float(np.median(statistic / expected))


@lru_cache(maxsize=64)
def _chi2_medians(dtype: str, distinct: bytes) -> np.ndarray:
    """Chi-square medians of the distinct dof (given as their bytes, so that a repeat is
    looked up, not computed again)."""
    medians = upper_quantile(np.frombuffer(distinct, dtype=dtype), 0.5)
    medians.flags.writeable = False
    return medians
