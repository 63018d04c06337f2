"""The disk refinement's inner loop, compiled (numba): each candidate on its own window.

For one candidate at a time, each iteration visits the pixels of the ellipse's outer ring
and inside it twice: for the ring's grey levels (a 256-bin histogram, for the 15th, 50th and
85th percentiles) and the mean of the disk's middle, then for the darkness centroid and second
moments inside the window; a last pass takes the levels around the final ellipse. The window follows the ellipse as
it moves and grows, up to `max_major` px of major semi-axis. `mocap.tracking.detect` describes the
method; this module only computes it.

Shapes: N candidates.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_MIN_EVAL = 0.25  # px², the least squared semi-axis
_UNEVEN = 0.1  # (85th percentile - median) / contrast of a ring of two levels


@njit("UniTuple(f8, 3)(f8, f8, f8)", cache=True, nogil=True)
def _eigen(sxx: float, sxy: float, syy: float):
    """Eigenvalues (minor, major) of a symmetric 2x2 matrix and the major axis's angle."""
    mean = 0.5 * (sxx + syy)
    half_gap = math.sqrt(0.25 * (sxx - syy) ** 2 + sxy * sxy)
    return mean - half_gap, mean + half_gap, 0.5 * math.atan2(2.0 * sxy, sxx - syy)


@njit("UniTuple(f8, 2)(f8)", cache=True, nogil=True)
def _ring_radii(minor: float):
    k_in = 1.0 + max(0.7 / max(minor, 0.5), 0.15)
    return k_in, max(1.6, k_in + 0.35)


@njit("UniTuple(f8, 3)(i8[::1], i8)", cache=True, nogil=True)
def _ring_levels(histogram: np.ndarray, total: int):
    """The 15th, 50th and 85th percentiles (the level at rank floor(q (n - 1))) of a 256-bin
    histogram of `total` values, in one pass up to the last of them."""
    span = max(total - 1, 0)
    low, mid, high = math.floor(0.15 * span), math.floor(0.5 * span), math.floor(0.85 * span)
    darkest = middle = bright = 255.0
    seen = 0
    for level in range(256):
        seen += histogram[level]
        if seen > low and darkest == 255.0:
            darkest = float(level)
        if seen > mid and middle == 255.0:
            middle = float(level)
        if seen > high:
            bright = float(level)
            break
    return darkest, middle, bright


@njit("UniTuple(i8, 2)(f8, f8, f8, f8, f8, f8, i8, i8)", cache=True, nogil=True)
def _row_span(ia: float, ib: float, ic: float, cx: float, dy: float, level: float, x0: int, x1: int):
    """The columns (first, last) of a row, within x0..x1, that can hold pixels with
    ``ia dx² + 2 ib dx dy + ic dy² < level`` (dx = x - cx; ia > 0): between the quadratic's
    roots for a slightly higher level, widened by a pixel each side, so that no such pixel is
    left out (each is still tested); last < first when there is none."""
    level = level * (1.0 + 1e-9) + 1e-9
    b = ib * dy
    disc = b * b - ia * (ic * dy * dy - level)
    if disc < 0.0:
        return x0, x0 - 1
    root = math.sqrt(disc)
    first = int(math.floor(cx + (-b - root) / ia)) - 1
    last = int(math.ceil(cx + (-b + root) / ia)) + 1
    return max(first, x0), min(last, x1)


@njit(
    "Tuple((f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1]))"
    "(u1[:, ::1], f8[:, ::1], f8[:, :, ::1], f8[::1], i8)",
    cache=True,
    nogil=True,
)
def refine_disks(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray, max_major: np.ndarray, iterations: int):
    """Refine N candidates: start centres xy (N, 2), semi-axis matrices shape (N, 2, 2),
    the largest major semi-axis allowed (N,) px. Returns centres (N, 2), semi-axes (N, 2)
    a >= b, angle (N,), contrast (N,), fill (N,), the ring's spread (N,) and its
    unevenness (N,) (see `mocap.tracking.detect.refine`)."""
    n = xy.shape[0]
    height, width = gray.shape
    out_xy = xy.copy()
    out_axes = np.zeros((n, 2))
    out_angle = np.zeros(n)
    out_contrast = np.zeros(n)
    out_fill = np.zeros(n)
    out_spread = np.full(n, np.inf)
    out_uneven = np.full(n, np.inf)
    histogram = np.zeros(256, dtype=np.int64)
    for i in range(n):
        cx, cy = xy[i, 0], xy[i, 1]
        minor2, major2, angle = _eigen(shape[i, 0, 0], shape[i, 0, 1], shape[i, 1, 1])
        limit = max_major[i] ** 2
        minor2 = min(max(minor2, _MIN_EVAL), limit)
        major2 = min(max(major2, _MIN_EVAL), limit)
        darkest = background = foreground = middle = math.nan
        mass = 0.0
        for iteration in range(iterations + 1):
            c, s = math.cos(angle), math.sin(angle)
            # inverse shape: R diag(1/major², 1/minor²) R^T, R's first column the major axis
            ia = c * c / major2 + s * s / minor2
            ib = c * s / major2 - c * s / minor2
            ic = s * s / major2 + c * c / minor2
            k_in, k_out = _ring_radii(math.sqrt(minor2))
            k_in2, k_out2 = k_in * k_in, k_out * k_out
            reach = k_out * math.sqrt(major2) + 1.0
            x0, x1 = max(int(math.floor(cx - reach)), 0), min(int(math.ceil(cx + reach)), width - 1)
            y0, y1 = max(int(math.floor(cy - reach)), 0), min(int(math.ceil(cy + reach)), height - 1)
            # the levels around the current ellipse (the last pass: around the final one)
            histogram[:] = 0
            ring_count = middle_count = 0
            middle_sum = 0.0
            for y in range(y0, y1 + 1):
                dy = y - cy
                first, last = _row_span(ia, ib, ic, cx, dy, k_out2, x0, x1)
                for x in range(first, last + 1):
                    dx = x - cx
                    rho2 = ia * dx * dx + 2.0 * ib * dx * dy + ic * dy * dy
                    if rho2 < 0.25:
                        middle_sum += gray[y, x]
                        middle_count += 1
                    elif k_in2 <= rho2 < k_out2:
                        histogram[gray[y, x]] += 1
                        ring_count += 1
            if ring_count == 0:
                darkest = background = middle = math.nan
            else:
                darkest, middle, background = _ring_levels(histogram, ring_count)
            foreground = middle_sum / middle_count if middle_count > 0 else math.nan
            if background - middle > _UNEVEN * (background - foreground):
                # a ring of two levels (half of it on something brighter than the disk's own
                # surround, as the sky beside a disk painted at a face's edge): the disk's
                # darkness is measured from the level of most of it, which leaves the centroid
                # where the disk is rather than leaning away from the brighter side
                background = middle
            contrast = max(background - foreground, 1.0)
            if iteration == iterations or not math.isfinite(contrast):
                break
            m0 = mx = my = mxx = mxy = myy = 0.0
            for y in range(y0, y1 + 1):
                dy = y - cy
                first, last = _row_span(ia, ib, ic, cx, dy, k_in2, x0, x1)
                for x in range(first, last + 1):
                    dx = x - cx
                    if ia * dx * dx + 2.0 * ib * dx * dy + ic * dy * dy < k_in2:
                        w = min(max((background - gray[y, x]) / contrast, 0.0), 1.0)
                        m0 += w
                        mx += w * dx
                        my += w * dy
                        mxx += w * dx * dx
                        mxy += w * dx * dy
                        myy += w * dy * dy
            mass = m0
            if m0 <= 0:
                break
            ux, uy = mx / m0, my / m0
            sxx = 4.0 * (mxx / m0 - ux * ux) + 1e-3
            sxy = 4.0 * (mxy / m0 - ux * uy)
            syy = 4.0 * (myy / m0 - uy * uy) + 1e-3
            cx, cy = cx + ux, cy + uy
            minor2, major2, angle = _eigen(sxx, sxy, syy)
            minor2 = min(max(minor2, _MIN_EVAL), limit)
            major2 = min(max(major2, _MIN_EVAL), limit)
        a, b = math.sqrt(major2), math.sqrt(minor2)
        out_xy[i, 0], out_xy[i, 1] = cx, cy
        out_axes[i, 0], out_axes[i, 1] = a, b
        out_angle[i] = angle
        out_contrast[i] = background - foreground
        out_fill[i] = mass / (math.pi * a * b)
        if math.isfinite(darkest):
            out_spread[i] = (background - darkest) / max(background - foreground, 1.0)
            out_uneven[i] = (background - middle) / max(background - foreground, 1.0)
    return out_xy, out_axes, out_angle, out_contrast, out_fill, out_spread, out_uneven


@njit(
    "Tuple((f8[:, ::1], f8[:, ::1], f8[::1], f8[::1], f8[::1], f8[::1], f8[::1], i8[::1]))"
    "(u1[:, ::1], f8[:, ::1], f8[:, :, ::1], i8)",
    cache=True,
    nogil=True,
)
def refine_disks_converged(gray: np.ndarray, xy: np.ndarray, shape: np.ndarray, iterations: int):
    """`refine_disks` from xy (N, 2) with semi-axis matrices shape (N, 2, 2), each window
    reaching twice the start's major semi-axis and 4 px; a candidate that moved more than a
    quarter of its radius (at least a pixel's) is refined once more from where it arrived,
    with the ellipse it found. Returns what `refine_disks` returns, the candidates that stayed
    first, then those refined again, each in their input order, and (N,) the input index of
    each row (each candidate's result is its own: the rows of a subset of the candidates are
    those of the whole run, in the same order)."""
    n = xy.shape[0]
    max_major = np.empty(n)
    for i in range(n):
        major2 = _eigen(shape[i, 0, 0], shape[i, 0, 1], shape[i, 1, 1])[1]
        max_major[i] = 2.0 * math.sqrt(max(major2, 0.25)) + 4.0
    first = refine_disks(gray, xy, shape, max_major, iterations)
    centre, axes, angle = first[0], first[1], first[2]
    far = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        dx, dy = centre[i, 0] - xy[i, 0], centre[i, 1] - xy[i, 1]
        moved = math.sqrt(dx * dx + dy * dy)
        far[i] = moved > 0.25 * max(math.sqrt(axes[i, 0] * axes[i, 1]), 1.0)
    again = np.flatnonzero(far)
    stayed = np.flatnonzero(~far)
    k = again.shape[0]
    start = np.empty((k, 2))
    start_shape = np.empty((k, 2, 2))
    again_major = np.empty(k)
    for j in range(k):
        i = again[j]
        start[j, 0], start[j, 1] = centre[i, 0], centre[i, 1]
        # R diag(a², b²) R^T, R's first column the major axis (`Detections.shape`)
        cos, sin = math.cos(angle[i]), math.sin(angle[i])
        a2, b2 = axes[i, 0] ** 2, axes[i, 1] ** 2
        start_shape[j, 0, 0] = cos * a2 * cos + sin * b2 * sin
        start_shape[j, 0, 1] = start_shape[j, 1, 0] = cos * a2 * sin - sin * b2 * cos
        start_shape[j, 1, 1] = sin * a2 * sin + cos * b2 * cos
        major2 = _eigen(start_shape[j, 0, 0], start_shape[j, 0, 1], start_shape[j, 1, 1])[1]
        again_major[j] = 2.0 * math.sqrt(max(major2, 0.25)) + 4.0
    second = refine_disks(gray, start, start_shape, again_major, iterations)
    results = (np.empty((n, 2)), np.empty((n, 2)), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n),
               np.empty(n, dtype=np.int64))
    for j in range(n):
        if j < stayed.shape[0]:
            i, source = stayed[j], first
            results[7][j] = stayed[j]
        else:
            i, source = j - stayed.shape[0], second
            results[7][j] = again[i]
        results[0][j, 0], results[0][j, 1] = source[0][i, 0], source[0][i, 1]
        results[1][j, 0], results[1][j, 1] = source[1][i, 0], source[1][i, 1]
        results[2][j] = source[2][i]
        results[3][j] = source[3][i]
        results[4][j] = source[4][i]
        results[5][j] = source[5][i]
        results[6][j] = source[6][i]
    return results
