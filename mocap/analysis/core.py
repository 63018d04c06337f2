"""The whole analysis of one motion, pure: series -> cycles -> classes -> shapes ->
similarity -> relations. Its table is cycles.csv's content.

Shapes: K cycles, N arc-length samples.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from mocap.analysis.features import ClassRules, cycle_parameters
from mocap.analysis.segment import SegmentOptions, Segments, segment
from mocap.analysis.series import TipSeries
from mocap.analysis.shape import (DigPaths, Deviations, Template, build_templates, deviations, dig_channels,
                                  fit_lifts, general_paths, resample_digs)
from mocap.analysis.similarity import Grouping, Relation, correlations, direction_relation, dtw_matrix, group_digs

FIRST = ("cycle", "start_frame", "end_frame", "dig_start_frame", "dig_end_frame", "class")
CHANGES = ("start_height_m", "start_reach_m", "start_angle_deg", "dig_length_m", "dig_s", "scale_x", "scale_z")
LIFT_ROUNDS = 2
RELATED = ("dig_s", "dig_length_m", "dig_rise_m", "dig_advance_m", "start_height_m", "start_angle_deg",
           "end_angle_deg", "dig_speed_mean_m_s", "scale_x", "scale_z", "cycle_time_s")


@dataclass(frozen=True)
class Analysis:
    """Everything the analysis found: `table` {column: (K,)} in cycles.csv's order,
    `segments`, dig `paths`, `templates` per class, `deviations`, `distance` (K, K) DTW,
    `grouping`, `relations` per class, `correlation` (P, P) of `RELATED`."""

    series: TipSeries
    segments: Segments
    table: dict
    paths: DigPaths
    templates: dict[str, Template]
    deviations: Deviations
    distance: np.ndarray
    grouping: Grouping
    relations: tuple[Relation, ...]
    correlation: np.ndarray

    def __len__(self) -> int:
        return len(self.segments)

    def take(self, keep: np.ndarray) -> Analysis:
        """The analysis of the cycles where `keep` (K,) is true (templates and relations stay
        those of all cycles)."""
        dev = Deviations(*(np.asarray(getattr(self.deviations, f.name))[keep] for f in fields(Deviations)))
        grouping = Grouping(self.grouping.groups[keep], self.grouping.count, self.grouping.silhouette)
        return replace(self, segments=self.segments.take(keep), table={k: v[keep] for k, v in self.table.items()},
                       paths=DigPaths(self.paths.s, self.paths.path[keep]), deviations=dev,
                       distance=self.distance[np.ix_(keep, keep)], grouping=grouping,
                       correlation=correlations({k: v[keep] for k, v in self.table.items()}, RELATED))


def analyze(series: TipSeries, rules: ClassRules = ClassRules(), options: SegmentOptions = SegmentOptions()) -> Analysis:
    """Segment, measure, classify and compare the dig cycles of `series`."""
    seg = segment(series, options)
    table = cycle_parameters(series, seg, rules)
    labels = table["class"]
    paths = resample_digs(series, seg.dig_start, seg.dig_end)
    starts = np.column_stack([table["start_reach_m"], table["start_height_m"], np.radians(table["start_angle_deg"])])
    dev = deviations(series, seg.dig_start, seg.dig_end, np.ones((len(labels), 2)))
    channels = dig_channels(series, seg.dig_start, seg.dig_end, dev)
    general, after, window = general_paths(channels)
    templates, scales = build_templates(general, labels, starts, after, window)
    for _ in range(LIFT_ROUNDS):  # the redirection's lift taken out of the path, its arc length taken again
        general, after, window = general_paths(channels, fit_lifts(channels, labels, templates, scales))
        templates, scales = build_templates(general, labels, starts, after, window)
    lift = fit_lifts(channels, labels, templates, scales, whole=True)
    dev = replace(dev.with_lifts(lift), scale_x=scales[:, 0], scale_z=scales[:, 1])
    distance = dtw_matrix(paths.path)
    grouping = group_digs(distance)
    aspect = dev.scale_z / dev.scale_x
    table |= {
        "scale_x": dev.scale_x, "scale_z": dev.scale_z,
        "scaling": np.where(np.abs(np.log(aspect)) < np.log(1.07), "proportional", "non-proportional").astype(object),
        "reactive_rms_m": dev.reactive_m, "reactive_rms_deg": dev.reactive_deg,
        "redirection": dev.redirection,
        "redirection_time": dev.redirection_time,
        "redirection_frame": np.array([series.frame[series.index_at(t)] if np.isfinite(t) else -1
                                       for t in dev.redirection_time], dtype=int),
        "redirection_angle_deg": np.degrees(dev.redirection_angle),
        "redirection_lift_m": dev.redirection_lift,
        "redirection_kind": dev.redirection_kind,
        "group": grouping.groups,
        "dtw_to_previous": np.concatenate([[np.nan], np.diag(distance, 1)]) if len(labels) else np.zeros(0),
    }
    for name in CHANGES:
        values = np.asarray(table[name], dtype=float)
        table[f"change_{name}"] = np.concatenate([[np.nan], np.diff(values)]) if len(values) else values
    order = list(FIRST) + [c for c in table if c not in FIRST]
    table = {c: table[c] for c in order}
    relations = tuple(direction_relation(label, paths.path[labels == label]) for label in templates)
    return Analysis(series, seg, table, paths, templates, dev, distance, grouping, relations,
                    correlations(table, RELATED))
