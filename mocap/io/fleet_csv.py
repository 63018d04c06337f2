"""The fleet summary CSV of `mocap batch`: one row per session.

Columns: `session` (folder), `machine`, `day`, `status` (ok / partial / failed), `error` (a
failed session's reason; a partial one's stages and what they could not do), `stages_run`,
`stages_skipped`, `stage_seconds`, `hours` (recorded), `cycles`, `cycles_per_hour`, `mean_cycle_s`, `mean_dig_s`, `mean_rest_s` (swing, dump and return),
then one count per cycle class (`type_1`, `type_2`, `type_3`, `other`). Cycle columns are
empty for a session without a cycle analysis.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from mocap.core.session_summary import CLASSES, SessionSummary
from mocap.io.atomic import atomic_path

COLUMNS = ("session", "machine", "day", "status", "error", "stages_run", "stages_skipped", "stage_seconds",
           "hours", "cycles", "cycles_per_hour", "mean_cycle_s", "mean_dig_s", "mean_rest_s",
           *(c.lower().replace(" ", "_") for c in CLASSES))


def _num(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if np.isfinite(value) else ""


def save_fleet(summaries: list[SessionSummary], path: str | Path) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        for s in summaries:
            cycles = [str(s.cycles), _num(s.cycles_per_hour, 3), _num(s.mean_cycle_s, 3), _num(s.mean_dig_s, 3),
                      _num(s.mean_cycle_s - s.mean_dig_s, 3), *map(str, s.classes)] if s.analysed else [""] * 9
            writer.writerow([s.session, s.machine, s.day, s.status, s.error, s.stages_run, s.stages_skipped,
                             _num(s.stage_seconds, 3), _num(s.hours, 4), *cycles])
