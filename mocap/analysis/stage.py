"""The analyze stage: load the motion -> analyse -> write cycles.csv, report.html,
templates.toml -> a short summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocap.analysis.core import Analysis, analyze
from mocap.analysis.report import render_report
from mocap.analysis.series import tip_series
from mocap.analysis.templates import templates_table
from mocap.core.cycles import Cycles
from mocap.errors import InputError
from mocap.io.atomic import write_text
from mocap.io.cycles_csv import load_cycles, save_cycle_table
from mocap.io.machine_toml import load_machine
from mocap.io.motion_csv import load_motion
from mocap.io.templates_toml import save_templates

CYCLES, REPORT, TEMPLATES = "cycles.csv", "report.html", "templates.toml"


def check_cycles_within(path: Path, cycles_frames: np.ndarray, frames: np.ndarray) -> None:
    """InputError when given cycles lie outside the motion's frames."""
    outside = (cycles_frames < frames.min()) | (cycles_frames > frames.max())
    if outside.any():
        raise InputError(f"cycle frames {cycles_frames[outside][:3].tolist()} lie outside the motion's frames "
                         f"{int(frames.min())}..{int(frames.max())}; is it the cycles file of this motion?", path=path)


def run_analyze(machine_path: str | Path, motion_path: str | Path, out: str | Path,
                cycles_path: str | Path | None = None) -> str:
    """Analyse one motion CSV into `out`/; with `cycles_path`, only the frames inside the
    given cycles are analysed (a cycles CSV, e.g. hand-marked, with start_frame,end_frame).
    Returns the summary."""
    machine = load_machine(machine_path)
    motion = load_motion(motion_path, machine)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("is a file; --out takes a folder", path=out)
    for name in (CYCLES, REPORT, TEMPLATES):
        if (out / name).resolve() in {Path(motion_path).resolve(), Path(cycles_path or motion_path).resolve()}:
            raise InputError(f"--out would overwrite the input {name}; choose another folder", path=out)
    analysis = analyze_motion(motion, load_cycles(cycles_path) if cycles_path is not None else None, cycles_path)
    write_analysis(analysis, machine, out, f"Dig cycles of {machine.name}: {Path(motion_path).name}")
    return summary(analysis, out)


def analyze_motion(motion, cycles: Cycles | None = None, cycles_path=None) -> Analysis:
    """The dig cycles of a motion (mocap.core.motion.Motion); with `cycles`, only the digs
    inside those cycles (`cycles_path` names them in messages)."""
    series = tip_series(motion)
    analysis = analyze(series)
    if cycles is not None:
        check_cycles_within(Path(cycles_path or "cycles"), np.concatenate([cycles.start, cycles.end]), series.frame)
        dig = analysis.table["dig_start_frame"]
        analysis = analysis.take(((dig[:, None] >= cycles.start) & (dig[:, None] <= cycles.end)).any(axis=1))
    return analysis


def write_analysis(analysis: Analysis, machine, out: str | Path, title: str) -> None:
    """cycles.csv, report.html and templates.toml into the folder `out`."""
    out = Path(out)
    save_cycle_table(analysis.table, out / CYCLES)
    write_text(out / REPORT, render_report(analysis, title))
    save_templates(templates_table(analysis, machine), out / TEMPLATES)


def summary(analysis: Analysis, out: Path) -> str:
    t = analysis.table
    if len(t["cycle"]) == 0:
        return f"no dig cycle found; wrote {out / CYCLES}, {out / REPORT}, {out / TEMPLATES}"
    counts = ", ".join(f"{k} {int((t['class'] == k).sum())}" for k in dict.fromkeys(t["class"]))
    redirected = int((t["redirection"] != "none").sum())
    return (f"{len(t['cycle'])} cycles ({counts}), median cycle {np.nanmedian(t['cycle_time_s']) if len(t['cycle']) > 1 else float('nan'):.1f} s, "
            f"dig {np.median(t['dig_s']):.1f} s; {redirected} redirection(s); "
            f"{analysis.grouping.count} group(s) of dig paths\n"
            f"wrote {out / CYCLES}, {out / REPORT}, {out / TEMPLATES}")
