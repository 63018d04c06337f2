"""Wild pixels: observations their own track contradicts, and the pixel noise the data
actually have.

A marker's track is smooth at the frame rate (a machine's links do not jump), so a pixel
far from what its neighbours in time predict is a wrong detection, whatever the number of
cameras that see the marker. A pixel is compared with what its neighbours predict
(midpoints of f-k and f+k, k = 1, 2, 3, and straight-line extrapolations from either side)
and kept if it is near any of them (a wild neighbour spoils only the predictions it is
in); the threshold follows the deviations the track
actually has (`factor` times their robust scale), never less than `floor_px`.

Shapes: F frames, M markers.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtri

RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median length of a 2-D Gaussian of unit SD per axis


_CHUNK_FRAMES = 20_000  # frames judged together (memory)
_REACH = 3  # the predictors' farthest neighbour
# Predictions of a pixel from its neighbours, exact for a steady motion: {frame offset:
# weight}. Midpoints of f-k and f+k, then one-sided extrapolations for the ends of a track.
_PREDICTORS = (
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
    time to judge). A flagged pixel is judged again without the flagged ones: a good pixel
    whose neighbours were all wild is kept when its other neighbours agree with it."""
    pixels = np.asarray(pixels, dtype=float)
    judged, scaled, raw = _deviations(pixels)
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
        again = _deviations(np.where(flagged[..., None], np.nan, pixels))
        flagged &= ~(again[0] & ((again[1] <= limit) | (again[2] <= floor_px)))
    return flagged


def _deviations(pixels: np.ndarray, chunk: int = _CHUNK_FRAMES):
    """Per pixel (F, M): whether two or more predictions exist, and the deviation from the
    nearest one divided by its noise gain, and in pixels; computed `chunk` frames at a time
    (each with its 3 neighbours either side), so that memory does not grow with the
    session."""
    n_frames, n_markers = pixels.shape[:2]
    judged, scaled, raw = np.empty((n_frames, n_markers), bool), np.empty((n_frames, n_markers)), np.empty((n_frames, n_markers))
    for start in range(0, n_frames, chunk):
        end = min(n_frames, start + chunk)
        low, high = max(0, start - _REACH), min(n_frames, end + _REACH)
        part = _chunk_deviations(pixels[low:high])
        for out, values in zip((judged, scaled, raw), part):
            out[start:end] = values[start - low : end - low]
    return judged, scaled, raw


def _chunk_deviations(pixels: np.ndarray):
    n_frames = pixels.shape[0]
    padded = np.pad(pixels, ((3, 3), (0, 0), (0, 0)), constant_values=np.nan)
    raw, scaled = [], []
    for weights in _PREDICTORS:
        predicted = sum(w * padded[3 + k : 3 + k + n_frames] for k, w in weights.items())
        gain = np.sqrt(1.0 + sum(w * w for w in weights.values()))  # noise of pixel minus prediction
        raw.append(np.linalg.norm(pixels - predicted, axis=-1))
        scaled.append(raw[-1] / gain)
    raw, scaled = np.stack(raw), np.stack(scaled)  # (K, F, M), NaN where not available
    judged = np.isfinite(scaled).sum(0) >= 2
    best = np.argmin(np.where(np.isfinite(scaled), scaled, np.inf), axis=0)[None]
    return judged, np.take_along_axis(scaled, best, 0)[0], np.take_along_axis(raw, best, 0)[0]


def noise_from_fits(sum_squares: np.ndarray, dof: np.ndarray) -> float:
    """Pixel noise SD per axis from many small fits' sums of squared residuals (N,) with
    their degrees of freedom (N,): the median of each fit's sqrt(chi-square / dof), divided
    by that statistic's median under pure noise, so that wild fits do not move it."""
    ok = (dof > 0) & np.isfinite(sum_squares)
    if not ok.any():
        return float("nan")
    statistic = np.sqrt(sum_squares[ok] / dof[ok])
    expected = np.sqrt(chdtri(dof[ok], 0.5) / dof[ok])  # median of sqrt(chi2_k / k)
    return float(np.median(statistic / expected))
