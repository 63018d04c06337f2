"""The fleet summary: per session, and per machine and day, the cycles per hour, the cycle
time split into the dig and the rest (swing, dump, return) and the mix of cycle classes.

A session's machine and day come from its session.toml ``[metadata]`` (`machine_id`, else
the model's name; `date`, a TOML date or datetime, else "unknown").
"""

from __future__ import annotations

import datetime

import numpy as np

from mocap.core.cycles import Cycles
from mocap.core.session_summary import CLASSES, SessionSummary

def machine_and_day(metadata: dict, model_name: str) -> tuple[str, str]:
    machine = str(metadata.get("machine_id", model_name))
    date = metadata.get("date")
    if isinstance(date, datetime.datetime):
        day = date.date().isoformat()
    elif isinstance(date, datetime.date):
        day = date.isoformat()
    else:
        day = str(date) if date else "unknown"
    return machine, day


def cycle_figures(cycles: Cycles | None, fps: float, n_frames: int) -> dict:
    """Hours (n_frames / fps / 3600), cycle count, summed cycle and dig seconds (frames are
    inclusive: a cycle from frame a to b lasts (b - a + 1) / fps; the dig from where it
    begins to where the loaded swing does), class counts."""
    hours = n_frames / fps / 3600.0
    if cycles is None:
        return {"hours": hours}
    labels = np.array(cycles.label, dtype=object)
    counts = tuple(int(np.sum(labels == c)) for c in CLASSES[:-1])
    digs = cycles.phases if cycles.phases is not None else np.full((len(cycles), 2), -1)
    known = (digs[:, 0] >= 0) & (digs[:, 1] >= 0)
    return {
        "hours": hours,
        "cycles": len(cycles),
        "cycle_seconds": float(np.sum(cycles.end - cycles.start + 1) / fps),
        "dig_seconds": float(np.sum((digs[:, 1] - digs[:, 0] + 1)[known]) / fps),
        "classes": counts + (len(cycles) - sum(counts),),
        "analysed": True,
    }


def combine(summaries: list[SessionSummary], name: str) -> SessionSummary:
    """Sessions added up (the successful ones, and the partial ones: their results written)
    under one name."""
    ok = [s for s in summaries if s.status == "ok"]
    partial = [s for s in summaries if s.status == "partial"]
    analysed = [s for s in ok + partial if s.analysed]
    return SessionSummary(
        name, "", "", status=f"{len(ok)}/{len(summaries)} ok" + (f", {len(partial)} partial" if partial else ""),
        hours=float(sum(s.hours for s in analysed)) if analysed else float("nan"),
        cycles=sum(s.cycles for s in analysed),
        cycle_seconds=sum(s.cycle_seconds for s in analysed),
        dig_seconds=sum(s.dig_seconds for s in analysed),
        classes=tuple(int(sum(s.classes[k] for s in analysed)) for k in range(len(CLASSES))),
        analysed=bool(analysed),
        stages_run=sum(s.stages_run for s in summaries),
        stages_skipped=sum(s.stages_skipped for s in summaries),
        stage_seconds=sum(s.stage_seconds for s in summaries),
    )


def _f(value: float, digits: int = 1) -> str:
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def _mix(summary: SessionSummary) -> str:
    if not summary.cycles:
        return ""
    return ", ".join(f"{c} {100 * n / summary.cycles:.0f}%" for c, n in zip(CLASSES, summary.classes) if n)


def _table(title: str, key: str, summaries: list[SessionSummary]) -> list[str]:
    lines = [f"## By {title}", "", f"| {title} | sessions ok | hours | cycles | cycles/h | cycle s | dig s | rest s | class mix |",
             "|---|---|---|---|---|---|---|---|---|"]
    for value in sorted({getattr(s, key) for s in summaries}):
        total = combine([s for s in summaries if getattr(s, key) == value], value)
        rest = total.mean_cycle_s - total.mean_dig_s
        lines.append(f"| {value} | {total.status} | {_f(total.hours, 2)} | {total.cycles} | {_f(total.cycles_per_hour)} | "
                     f"{_f(total.mean_cycle_s)} | {_f(total.mean_dig_s)} | {_f(rest)} | {_mix(total)} |")
    return lines + [""]


def report_text(summaries: list[SessionSummary], wall_seconds: float) -> str:
    """The fleet report (Markdown): totals, then tables by session, machine and day, then the failures."""
    total = combine(summaries, "fleet")
    lines = [
        "# Fleet summary",
        "",
        f"{len(summaries)} sessions, {total.status}; {total.stages_run} stages run, {total.stages_skipped} "
        f"up to date and skipped; {wall_seconds:.1f} s wall time, {total.stage_seconds:.1f} s in stages.",
        "",
    ]
    if not any(s.analysed for s in summaries):
        lines += ["No session has a cycle analysis (results/cycles.csv): no cycle figures.", ""]
    lines += _table("session", "session", summaries)
    lines += _table("machine", "machine", summaries)
    lines += _table("day", "day", summaries)
    failed = [s for s in summaries if s.status not in ("ok", "partial")]
    if failed:
        lines += ["## Failed", ""] + [f"- {s.session}: {s.error}" for s in failed] + [""]
    partial = [s for s in summaries if s.status == "partial"]
    if partial:
        lines += ["## Partial", ""] + [f"- {s.session}: {s.error}" for s in partial] + [""]
    return "\n".join(lines)
