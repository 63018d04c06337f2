"""The bucket's motion as the analysis sees it: one smoothed, gap-free series per quantity.

The tip is described in the house's vertical plane: ``reach`` the horizontal distance from
the swing axis, ``height`` above the ground (the world frame's z = 0, the ground under the
machine at the calibration frame), ``azimuth`` the swing direction of the tip (rad, from
the world's x towards y, unwrapped). Where the base moves (``base_x``, ``base_y`` columns of
the motion CSV) the swing axis moves with it. Frames with no value (NaN) are interpolated
for the analysis and remembered in ``gap``, as are glitches — frames whose bucket angle
jumps more than `GLITCH_DEG` from its running median over 1.5 s (a fit that flipped the
bucket for a few frames); frames the reconstruction filled are in ``filled``.

Shapes: F frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.ndimage import median_filter
from scipy.signal import savgol_filter

from mocap.core.motion import Motion
from mocap.errors import InputError

TIP = "bucket_tip"
GLITCH_DEG = 20.0  # a bucket angle this far from its 1.5 s running median is a fitting glitch


@dataclass(frozen=True)
class TipSeries:
    """F frames of the bucket's motion, smoothed.

    frame (F,) motion-CSV frames; time (F,) s; reach, height (F,) m; azimuth (F,) rad;
    angle (F,) bucket angle, rad; speed (F,) tip speed, m/s; swing_rate (F,) rad/s;
    gap (F,) bool, no value in the motion; filled (F,) bool, filled by the reconstruction;
    raw_reach, raw_height, raw_angle (F,) before smoothing (gaps interpolated).
    """

    frame: np.ndarray
    time: np.ndarray
    reach: np.ndarray
    height: np.ndarray
    azimuth: np.ndarray
    angle: np.ndarray
    speed: np.ndarray
    swing_rate: np.ndarray
    gap: np.ndarray
    filled: np.ndarray
    raw_reach: np.ndarray
    raw_height: np.ndarray
    raw_angle: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    @cached_property
    def rate(self) -> float:
        """Frames per second (kept once taken: the median over every frame is asked for per dig)."""
        return 1.0 / float(np.median(np.diff(self.time)))

    def index_at(self, t: float) -> int:
        """The frame index nearest to time `t` (s)."""
        return int(np.clip(np.searchsorted(self.time, t), 0, len(self.time) - 1))


def _interpolate(time: np.ndarray, values: np.ndarray) -> np.ndarray:
    ok = np.isfinite(values)
    return np.interp(time, time[ok], values[ok])


def _glitches(time: np.ndarray, angle: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """(F,) frames whose bucket angle leaves its running median (1.5 s) by more than
    `GLITCH_DEG`; gaps are bridged first."""
    if gap.all():
        return np.zeros(len(time), bool)
    rate = 1.0 / float(np.median(np.diff(time)))
    bridged = _interpolate(time, np.where(gap, np.nan, angle))
    return np.abs(bridged - median_filter(bridged, _window(rate, 1.5), mode="nearest")) > np.radians(GLITCH_DEG)


def _window(rate: float, seconds: float) -> int:
    return max(5, int(round(seconds * rate)) // 2 * 2 + 1)


def tip_series(motion: Motion, smooth_s: float = 0.4, speed_s: float = 0.8) -> TipSeries:
    """The tip's series from a motion; InputError if it has no bucket tip or too few frames.

    `smooth_s` the Savitzky-Golay window (s) for positions and angles; `speed_s` the wider
    one for the tip's velocity, whose minima bound the digs: a machine's moves last seconds,
    while the base's bouncing (1-4 Hz, centimetres at the tip of a large shovel) and the
    reconstruction's noise would put false minima into a narrower one.
    """
    if TIP not in motion.point_names:
        raise InputError(f"the motion has no '{TIP}' point; the analysis follows the bucket tip")
    if len(motion) < 30:
        raise InputError(f"the motion has {len(motion)} frames; the analysis needs at least 30")
    time = np.asarray(motion.time, dtype=float)
    if not np.all(np.diff(time) > 0):
        k = int(np.flatnonzero(np.diff(time) <= 0)[0])
        raise InputError(f"time does not increase at frame {int(motion.frame[k + 1])}; sort the motion by time")
    tip = motion.point(TIP)
    gap = ~(np.isfinite(tip).all(axis=1) & np.isfinite(motion.bucket_angle))
    gap |= _glitches(time, motion.bucket_angle, gap)
    tip = np.where(gap[:, None], np.nan, tip)
    if gap.mean() > 0.5:
        raise InputError(f"the bucket tip is missing in {gap.mean():.0%} of the frames; nothing to analyse")
    xy = tip[:, :2].copy()
    for k, name in enumerate(("base_x", "base_y")):
        if name in motion.extra:
            base = np.asarray(motion.extra[name], dtype=float)
            xy[:, k] -= np.where(np.isfinite(base), base, 0.0)
    x, y = (_interpolate(time, xy[:, k]) for k in range(2))
    z = _interpolate(time, tip[:, 2])
    angle = _interpolate(time, np.where(gap, np.nan, motion.bucket_angle))
    rate = 1.0 / float(np.median(np.diff(time)))
    w = min(_window(rate, smooth_s), len(time) // 2 * 2 - 1)
    sx, sy, sz, sa = (savgol_filter(v, w, 2) for v in (x, y, z, angle))
    wv = min(_window(rate, speed_s), len(time) // 2 * 2 - 1)
    vx, vy, vz = (savgol_filter(v, wv, 2, deriv=1) * rate for v in (x, y, z))
    azimuth = np.unwrap(np.arctan2(sy, sx))
    wide = min(_window(rate, 2.5 * smooth_s), len(time) // 2 * 2 - 1)
    swing_rate = savgol_filter(azimuth, wide, 2, deriv=1) * rate
    filled = np.asarray(motion.extra.get("filled", np.zeros(len(time))), dtype=float)
    return TipSeries(
        frame=np.asarray(motion.frame),
        time=time,
        reach=np.hypot(sx, sy),
        height=sz,
        azimuth=azimuth,
        angle=sa,
        speed=np.sqrt(vx**2 + vy**2 + vz**2),
        swing_rate=swing_rate,
        gap=gap,
        filled=np.nan_to_num(filled) > 0,
        raw_reach=np.hypot(x, y),
        raw_height=z,
        raw_angle=angle,
    )
