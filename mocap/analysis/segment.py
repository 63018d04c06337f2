"""Dig cycles and their phases from the bucket's motion alone.

Definitions (the README states them too):

- A **swing** is a turn of the house by more than `min_swing_deg`; between swings the house
  dwells. A dwell where the tip comes down into the lower half of the session's height range
  is at the **face**; the dwell after a face dwell is at the **truck**.
- The **dig** runs from the bucket's first cutting motion after the return swing has
  stopped at the face (the tip speed's minimum at the end of the lowering, after which the
  tip moves forward, up, or back along the floor as a backhoe's drags — not mostly down,
  judged over the next `horizon_s` — by more than the base's bouncing) to its lift-out as
  the swing toward the truck begins (the last tip-speed minimum before that swing). When
  the bucket rests longer than `pause_s` before the dig, the dig starts when it leaves the
  rest. When it rests longer than `rest_s` before the lift-out, the dig ends when it comes
  to rest: where its speed reaches zero, taken as the speed's last fall below the rest's
  threshold (a fiftieth of the session's 95th percentile, brief rises of the base's
  bouncing bridged) plus the time its fall from four times that took (a smooth stop's
  speed falls as the square of the time left).
- A **cycle** runs from the start of one dig to the start of the next (the last ends with
  the data); its phases are dig, swing loaded (lift-out and swing to the truck), dump (the
  dwell at the truck) and swing back (the return swing and lowering to the next dig).

Shapes: F frames, K cycles, S swings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import find_peaks

from mocap.analysis.series import TipSeries


@dataclass(frozen=True)
class SegmentOptions:
    """Thresholds of the segmentation (degrees, seconds, shares)."""

    swing_rate_deg_s: float = 6.0
    onset_deg_s: float = 1.5
    min_swing_deg: float = 30.0
    merge_s: float = 0.5
    prominence: float = 0.05
    horizon_s: float = 3.0
    pause_s: float = 2.0
    min_dig_s: float = 1.5
    rest_s: float = 0.5

    def __post_init__(self) -> None:
        for name in ("swing_rate_deg_s", "onset_deg_s", "min_swing_deg", "prominence", "horizon_s", "pause_s", "min_dig_s",
                     "rest_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SegmentOptions.{name} must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class Segments:
    """K cycles as frame indices into the series (not motion-CSV frames), with -1 where a
    phase was not seen.

    start, end (K,) first and last index of each cycle; dig_start, dig_end (K,);
    truck_arrive, truck_leave (K,) the dump dwell; partial (K,) digs cut by the start or
    end of the data (no return swing before a moving first frame, no swing after);
    swings (S, 2) start and end index of every swing; face (S + 1,) whether each dwell is
    at the face.
    """

    start: np.ndarray
    end: np.ndarray
    dig_start: np.ndarray
    dig_end: np.ndarray
    truck_arrive: np.ndarray
    truck_leave: np.ndarray
    partial: np.ndarray
    swings: np.ndarray
    face: np.ndarray

    def __len__(self) -> int:
        return len(self.start)

    def take(self, keep: np.ndarray) -> Segments:
        """The cycles where `keep` (K,) is true."""
        return Segments(self.start[keep], self.end[keep], self.dig_start[keep], self.dig_end[keep],
                        self.truck_arrive[keep], self.truck_leave[keep], self.partial[keep], self.swings, self.face)


def find_swings(series: TipSeries, options: SegmentOptions) -> np.ndarray:
    """Swings (S, 2) as [start, end] indices: runs of swing rate above the threshold,
    merged across short stops, turning the house by more than `min_swing_deg`, widened to
    where the rate falls below `onset_deg_s`."""
    moving = np.abs(series.swing_rate) > np.radians(options.swing_rate_deg_s)
    edges = np.diff(np.concatenate([[0], moving.astype(np.int8), [0]]))
    runs = np.stack([np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1], axis=-1)
    if len(runs) == 0:
        return np.zeros((0, 2), dtype=int)
    merged = [runs[0].copy()]
    gap = int(round(options.merge_s * series.rate))
    for a, b in runs[1:]:
        same_way = np.sign(series.swing_rate[a]) == np.sign(series.swing_rate[merged[-1][1]])
        if a - merged[-1][1] <= gap and same_way:
            merged[-1][1] = b
        else:
            merged.append(np.array([a, b]))
    swings = np.array(merged)
    onset = np.abs(series.swing_rate) > np.radians(options.onset_deg_s)
    for row in swings:  # widen to where the house starts and stops turning
        while row[0] > 0 and onset[row[0] - 1]:
            row[0] -= 1
        while row[1] < len(onset) - 1 and onset[row[1] + 1]:
            row[1] += 1
    keep = np.concatenate([[True], swings[1:, 0] > swings[:-1, 1] + 1])  # widened into each other: one swing
    ends = np.maximum.reduceat(swings[:, 1], np.flatnonzero(keep))
    swings = np.stack([swings[keep, 0], ends], axis=-1)
    turn = np.abs(series.azimuth[swings[:, 1]] - series.azimuth[swings[:, 0]])
    return swings[turn > np.radians(options.min_swing_deg)]


def _dwells(swings: np.ndarray, n: int) -> np.ndarray:
    """Dwells (S + 1, 2) [start, end] indices between swings, the first from 0, the last to n - 1."""
    starts = np.minimum(np.concatenate([[0], swings[:, 1] + 1]), n - 1)
    ends = np.concatenate([swings[:, 0] - 1, [n - 1]])
    return np.stack([starts, np.maximum(ends, starts)], axis=-1)


def _rest_edge(speed: np.ndarray, k: int, low: float, forward: bool, pause: int) -> int:
    """From a speed minimum at `k`, the bucket's rest around it (speed below `low`): its
    end (forward) or start when it lasts longer than `pause` frames, else `k`."""
    rest = speed < max(low, speed[k] + 0.5 * low)
    lo, hi = k, k
    while lo > 0 and rest[lo - 1]:
        lo -= 1
    while hi < len(speed) - 1 and rest[hi + 1]:
        hi += 1
    if hi - lo + 1 < pause:
        return k
    return hi if forward else lo


def _rest(speed: np.ndarray, k: int, low: float, gap: int) -> tuple[int, int]:
    """The bucket's rest around the speed minimum at `k`: the first and last index of the
    stretch of speed below `low` that holds `k`, gaps of at most `gap` frames above it
    bridged (the base's bouncing)."""
    bounds = []
    for step in (-1, 1):
        edge = i = k
        while 0 < i < len(speed) - 1 and abs(i - edge) <= gap:
            i += step
            if speed[i] < low:
                edge = i
        bounds.append(edge)
    return bounds[0], bounds[1]


def find_dig(series: TipSeries, minima: np.ndarray, a: int, b: int, low: float,
             options: SegmentOptions, typical_reach: float | None = None) -> tuple[int, int] | None:
    """The dig inside the face dwell [a, b] (indices): (start, end) or None when no cutting
    motion is found. `typical_reach` the median reach of the whole series (m), taken once
    by the caller (a median over every frame per candidate would dominate the segmentation)."""
    if typical_reach is None:
        typical_reach = float(np.median(series.reach))
    rate = series.rate
    lead = int(round(1.0 * rate))
    candidates = minima[(minima >= a - lead) & (minima < b)]
    horizon = int(round(options.horizon_s * rate))
    pause = int(round(options.pause_s * rate))
    start = None
    for k in candidates:
        k = _rest_edge(series.speed, int(k), low, True, pause)
        e = min(k + horizon, b)
        if e <= k:
            continue
        dr = series.reach[k:e + 1] - series.reach[k]
        dz = series.height[k:e + 1] - series.height[k]
        # moved: more than the base's bouncing, and than a hundredth of the tip's distance
        # from the swing axis (a machine at rest has no speed scale of its own); not the
        # lowering: out, up, or in along the floor (a backhoe) at the horizon, or at most
        # of the frames from the move to the horizon (an operator's lower near the horizon
        # turns its displacement downwards)
        far = np.hypot(dr, dz) > max(0.25 * low * options.horizon_s, 0.01 * typical_reach)
        if not far[-1]:
            continue
        moved = far.argmax()  # the first frame beyond the bouncing
        level = dz[moved:] > -0.3 * np.abs(dr[moved:])
        if level[-1] or level.mean() > 0.5:
            start = k
            break
    if start is None:
        return None
    ends = candidates[candidates > start + options.min_dig_s * rate]
    if len(ends):
        end = int(ends[-1])
        lo, hi = _rest(series.speed, end, low, int(round(0.3 * rate)))
        top = lo
        while top > 0 and series.speed[top - 1] < 4.0 * low:
            top -= 1
        stop = lo + (lo - top)  # a smooth stop: from 4 low to low as long as from low to rest
        if hi - stop > int(round(options.rest_s * rate)):  # at rest before the lift-out
            end = stop
    else:
        end = b
    return (start, end) if end > start else None


def segment(series: TipSeries, options: SegmentOptions = SegmentOptions()) -> Segments:
    """Cycles and phases of `series` (see the module's definitions)."""
    n = len(series)
    swings = find_swings(series, options)
    dwells = _dwells(swings, n)
    lo, hi = np.percentile(series.height, [2, 98])
    floor = np.array([series.height[s:e + 1].min() for s, e in dwells])
    face = floor < 0.5 * (lo + hi)
    scale = float(np.percentile(series.speed, 95))
    minima, _ = find_peaks(-series.speed, prominence=options.prominence * scale,
                           distance=max(1, int(0.3 * series.rate)))
    low = 0.02 * scale
    typical_reach = float(np.median(series.reach))
    digs, trucks, partial = [], [], []
    for d, (a, b) in enumerate(dwells):
        if not face[d]:
            continue
        found = find_dig(series, minima, int(a), int(b), low, options, typical_reach)
        if found is None:
            continue
        digs.append(found)
        partial.append((d == 0 and series.speed[0] > low) or d == len(dwells) - 1)
        truck = (-1, -1)
        if d + 1 < len(dwells) and not face[d + 1]:
            truck = (int(dwells[d + 1][0]), int(dwells[d + 1][1]) if d + 2 < len(dwells) else -1)
        trucks.append(truck)
    if not digs:
        empty = np.zeros(0, dtype=int)
        return Segments(empty, empty, empty, empty, empty, empty, empty.astype(bool), swings, face)
    dig = np.array(digs)
    truck = np.array(trucks).reshape(-1, 2)
    end = np.concatenate([dig[1:, 0] - 1, [n - 1]])
    return Segments(dig[:, 0], end, dig[:, 0], dig[:, 1], truck[:, 0], truck[:, 1], np.array(partial), swings, face)
