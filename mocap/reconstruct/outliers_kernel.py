"""The track-outlier deviations, compiled (numba): for every pixel of one camera's tracks,
its distance from the nearest of the predictions its neighbouring frames make
(mocap.reconstruct.outliers). Shapes: F frames, M markers, K predictors, T terms."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def deviations(pixels, values, todo, offsets, weights, gains, judged, scaled, raw):
    """Fill judged (F, M) (two or more predictions), scaled (F, M) (the nearest
    prediction's distance over its noise gain) and raw (F, M) (that distance in px) for
    the pixels values (F, M, 2) that todo (F, M) names, predicted from pixels (F, M, 2)
    (NaN where not seen); the others are left unjudged (NaN). Predictor k is sum_t
    weights[k, t] * pixels[f + offsets[k, t]] (terms with weight 0 unused), its noise gain
    gains[k]."""
    n_frames, n_markers = pixels.shape[0], pixels.shape[1]
    n_predictors, n_terms = offsets.shape
    inverse_gain2 = 1.0 / gains**2
    for f in range(n_frames):
        for m in range(n_markers):
            if not todo[f, m]:
                judged[f, m], scaled[f, m], raw[f, m] = False, np.nan, np.nan
                continue
            u, v = values[f, m, 0], values[f, m, 1]
            count, best_scaled2, best_raw2 = 0, np.inf, np.nan
            first_scaled2, first_raw2 = np.nan, np.nan
            for k in range(n_predictors):
                px, py, ok = 0.0, 0.0, True
                for t in range(n_terms):
                    if weights[k, t] == 0.0:
                        continue
                    g = f + offsets[k, t]
                    if g < 0 or g >= n_frames:
                        ok = False
                        break
                    px += weights[k, t] * pixels[g, m, 0]
                    py += weights[k, t] * pixels[g, m, 1]
                r2 = (u - px) ** 2 + (v - py) ** 2 if ok else np.nan
                s2 = r2 * inverse_gain2[k]
                if k == 0:
                    first_scaled2, first_raw2 = s2, r2
                if s2 < np.inf:  # finite (NaN compares false)
                    count += 1
                    if s2 < best_scaled2:
                        best_scaled2, best_raw2 = s2, r2
            judged[f, m] = count >= 2
            if count:
                scaled[f, m], raw[f, m] = np.sqrt(best_scaled2), np.sqrt(best_raw2)
            else:
                scaled[f, m], raw[f, m] = np.sqrt(first_scaled2), np.sqrt(first_raw2)
