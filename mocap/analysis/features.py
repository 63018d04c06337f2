"""Per-cycle parameters and the paper's dig classes (Table 1 of PAPER.md).

Class rules, for a front shovel's dig (the tip moves out and up, away from the machine):

- **Type 1**: starts at the base of the pile, initial bucket angle significantly negative;
- **Type 2**: starts at the base of the pile, initial bucket angle near zero;
- **Type 3**: starts midway up the pile, initial bucket angle near zero;
- **other**: no rule fits, or the dig is cut by the start or end of the data (a dig that pulls the bucket towards the machine, as a
  backhoe's does; a start high on the pile; a negative angle midway up).

"Base of the pile" and "midway up" compare the dig's start height with the highest point
the dig reaches, both above the ground (`start_height_ratio`): below `base_ratio` is the
base, up to `top_ratio` midway. The features behind each decision are columns of
cycles.csv, and `class_rule` says in words which rule applied.

Shapes: K cycles, F frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.analysis.segment import Segments
from mocap.analysis.series import TipSeries
from mocap.core.classes import DIG_CLASSES, OTHER

CLASSES = DIG_CLASSES


@dataclass(frozen=True)
class ClassRules:
    """Thresholds of Table 1: start height as a share of the dig's top, bucket angle (deg)."""

    base_ratio: float = 0.3
    top_ratio: float = 0.75
    negative_deg: float = -12.0
    near_zero_deg: float = 12.0

    def __post_init__(self) -> None:
        if not 0 < self.base_ratio < self.top_ratio <= 1:
            raise ValueError(f"need 0 < base_ratio < top_ratio <= 1, got {self.base_ratio}, {self.top_ratio}")
        if not self.negative_deg < 0 < self.near_zero_deg:
            raise ValueError(f"need negative_deg < 0 < near_zero_deg, got {self.negative_deg}, {self.near_zero_deg}")


def classify(ratio: float, angle_deg: float, advance: float, rise: float, rules: ClassRules) -> tuple[str, str]:
    """The class of one dig and the rule, in words, that decided it."""
    if not (np.isfinite(ratio) and np.isfinite(angle_deg)):
        return OTHER, "incomplete dig"
    if advance <= 0 or rise <= 0:
        return OTHER, f"not a front shovel's dig (advance {advance:+.2f} m, rise {rise:+.2f} m)"
    where = "base" if ratio < rules.base_ratio else ("midway" if ratio <= rules.top_ratio else "top")
    if angle_deg < rules.negative_deg:
        tilt = "negative"
    elif abs(angle_deg) <= rules.near_zero_deg:
        tilt = "near zero"
    else:
        tilt = "positive"
    text = f"start {where} of the pile (height ratio {ratio:.2f}), initial angle {tilt} ({angle_deg:+.0f} deg)"
    label = {("base", "negative"): "Type 1", ("base", "near zero"): "Type 2",
             ("midway", "near zero"): "Type 3"}.get((where, tilt), OTHER)
    return label, text


def _at(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """values[index] with NaN where index is -1."""
    out = np.full(len(index), np.nan)
    ok = index >= 0
    out[ok] = values[index[ok]]
    return out


def _next(values: np.ndarray) -> np.ndarray:
    """Each cycle's next value (K,), NaN for the last."""
    return np.append(np.asarray(values, dtype=float)[1:], np.nan)[: len(values)]


def cycle_parameters(series: TipSeries, seg: Segments, rules: ClassRules = ClassRules()) -> dict[str, np.ndarray]:
    """The per-cycle columns of cycles.csv (K rows each): frames, times, phase durations,
    swing angles, dig start position, length, depth, speeds, class features and class."""
    k = len(seg)
    t, deg = series.time, np.degrees
    cols: dict[str, np.ndarray] = {
        "cycle": np.arange(1, k + 1),
        "start_frame": series.frame[seg.start],
        "end_frame": series.frame[seg.end],
        "dig_start_frame": series.frame[seg.dig_start],
        "dig_end_frame": series.frame[seg.dig_end],
    }
    labels, rule_text = [], []
    p = {name: np.full(k, np.nan) for name in (
        "dig_length_m", "dig_depth_m", "dig_top_m", "dig_speed_mean_m_s", "dig_speed_max_m_s",
        "swing_speed_max_m_s")}
    for i in range(k):
        a, b = seg.dig_start[i], seg.dig_end[i]
        r, z = series.reach[a:b + 1], series.height[a:b + 1]
        step = np.hypot(np.diff(r), np.diff(z))
        p["dig_length_m"][i] = step.sum()
        chord = np.array([r[-1] - r[0], z[-1] - z[0]])
        normal = np.array([chord[1], -chord[0]]) / max(np.linalg.norm(chord), 1e-9)  # points below the chord
        p["dig_depth_m"][i] = float(((np.stack([r - r[0], z - z[0]], -1)) @ normal).max())
        p["dig_top_m"][i] = z.max()
        p["dig_speed_mean_m_s"][i] = series.speed[a:b + 1].mean()
        p["dig_speed_max_m_s"][i] = series.speed[a:b + 1].max()
        p["swing_speed_max_m_s"][i] = series.speed[b:seg.end[i] + 1].max()
    start_height = series.height[seg.dig_start]
    ratio = start_height / np.maximum(p["dig_top_m"], 1e-9)
    start_angle = deg(series.angle[seg.dig_start])
    advance = series.reach[seg.dig_end] - series.reach[seg.dig_start]
    rise = series.height[seg.dig_end] - series.height[seg.dig_start]
    for i in range(k):
        label, text = classify(ratio[i], start_angle[i], advance[i], rise[i], rules)
        if seg.partial[i]:
            label, text = OTHER, "dig cut by the start or end of the data"
        labels.append(label)
        rule_text.append(text)
    cols["class"] = np.array(labels, dtype=object)
    cols["dump_start_frame"] = np.where(seg.truck_arrive >= 0, series.frame[np.maximum(seg.truck_arrive, 0)], -1)
    cols["swing_back_start_frame"] = np.where(seg.truck_leave >= 0, series.frame[np.maximum(seg.truck_leave, 0)], -1)
    arrive, leave = _at(t, seg.truck_arrive), _at(t, seg.truck_leave)
    dig_start_t, dig_end_t = t[seg.dig_start], t[seg.dig_end]
    next_dig = _next(dig_start_t)
    cols |= {
        "start_time": t[seg.start], "end_time": t[seg.end],
        "dig_start_time": dig_start_t, "dig_end_time": dig_end_t,
        "cycle_time_s": next_dig - dig_start_t,
        "dig_s": dig_end_t - dig_start_t,
        "swing_loaded_s": arrive - dig_end_t,
        "dump_s": leave - arrive,
        "swing_back_s": next_dig - leave,
        "swing_out_deg": deg(np.abs(_at(series.azimuth, seg.truck_arrive) - series.azimuth[seg.dig_end])),
        "swing_back_deg": deg(np.abs(_next(series.azimuth[seg.dig_start]) - _at(series.azimuth, seg.truck_leave))),
        "start_height_m": start_height,
        "start_reach_m": series.reach[seg.dig_start],
        "start_height_ratio": ratio,
        "start_angle_deg": start_angle,
        "end_angle_deg": deg(series.angle[seg.dig_end]),
        "dig_advance_m": advance,
        "dig_rise_m": rise,
    }
    cols |= p
    cols["class_rule"] = np.array(rule_text, dtype=object)
    gap = np.array([series.gap[s:e + 1].sum() + series.filled[s:e + 1].sum() for s, e in zip(seg.start, seg.end)])
    cols["gap_frames"] = gap
    complete = (seg.truck_leave >= 0) & (np.arange(k) < k - 1) & ~seg.partial
    cols["complete"] = complete.astype(int)
    cols["start_from_toe_m"] = cols["start_reach_m"] - toe_estimate(series, seg, ratio < rules.base_ratio)
    return cols


def toe_estimate(series: TipSeries, seg: Segments, base: np.ndarray) -> float:
    """The pile's toe (m from the swing axis): the median reach where digs that start at the
    base leave the floor (rise by a tenth of their height); NaN without such digs."""
    toes = []
    for a, b in zip(seg.dig_start[base], seg.dig_end[base]):
        z = series.height[a:b + 1]
        up = np.flatnonzero(z > z[0] + 0.1 * (z.max() - z[0]))
        if up.size:
            toes.append(series.reach[a + up[0]])
    return float(np.median(toes)) if toes else float("nan")
