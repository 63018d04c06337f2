"""How close an analysis came to a synthetic session's truth (truth/cycles.csv).

Found digs are matched to true ones by the nearest dig start within `tolerance_s`. Scale
factors are relative to a class template whose size is the class's typical size, while
the truth's are relative to the class's general shape at its drawn sizes' middle
(`mocap.synthetic.paths.stretch`): they are compared after dividing out one factor per
class (the median of estimated / true, in logarithms: one dig far off does not move its
classmates' errors). The redirection's lift (m) and turn (deg) are compared where the
truth has them, for the redirections found with the right kind. Scale errors are also given for the digs
without an operator's redirection alone: a kept lift and a taller dig look alike in the
path, and their split is only as good as the event's fit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocap.io.cycles_csv import load_cycle_table


@dataclass(frozen=True)
class AnalysisScore:
    """Counts and errors against the truth; errors in seconds, scale errors as shares."""

    true: int
    found: int
    missed: int
    extra: int
    start_errors: np.ndarray
    end_errors: np.ndarray
    class_correct: int
    redirect_tp: int
    redirect_fp: int
    redirect_fn: int
    redirect_kind_correct: int
    scale_errors: np.ndarray
    scale_redirected: np.ndarray | None = None
    lift_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))
    turn_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def matched(self) -> int:
        return len(self.start_errors)

    def row(self) -> dict[str, float]:
        """The figures of a benchmark row."""
        def q(v, p):
            return float(np.percentile(np.abs(v), p)) if len(v) else float("nan")

        def within(v):
            return float(np.mean(np.abs(v) <= 0.05)) if len(v) else float("nan")
        tp = self.redirect_tp
        return {
            "true": self.true, "found": self.found, "missed": self.missed, "extra": self.extra,
            "start_med_s": q(self.start_errors, 50), "start_p95_s": q(self.start_errors, 95),
            "end_med_s": q(self.end_errors, 50), "end_p95_s": q(self.end_errors, 95),
            "class_acc": self.class_correct / max(self.matched, 1),
            "redir_precision": tp / max(tp + self.redirect_fp, 1) if tp + self.redirect_fp else float("nan"),
            "redir_recall": tp / max(tp + self.redirect_fn, 1) if tp + self.redirect_fn else float("nan"),
            "redir_kind_acc": self.redirect_kind_correct / max(tp, 1) if tp else float("nan"),
            "scale_med": q(self.scale_errors, 50), "scale_p95": q(self.scale_errors, 95),
            "scale_within_5pct": within(self.scale_errors),
            "scale_within_5pct_plain": within(self.scale_errors[~self.scale_redirected])
            if self.scale_redirected is not None else float("nan"),
        }


def _numbers(values: np.ndarray) -> np.ndarray:
    return np.array([np.nan if isinstance(v, str) and not v.strip() else float(v) for v in values])


def score_analysis(found: dict, truth: dict, tolerance_s: float = 3.0) -> AnalysisScore:
    """Compare an analysis table (cycles.csv columns) with a truth cycles table (text or numbers)."""
    t_start, t_end = _numbers(truth["dig_start_time"]), _numbers(truth["dig_end_time"])
    f_start, f_end = _numbers(found["dig_start_time"]), _numbers(found["dig_end_time"])
    used = np.zeros(len(f_start), bool)
    pairs = []
    for i, t in enumerate(t_start):
        if not len(f_start):
            break
        gap = np.where(used, np.inf, np.abs(f_start - t))
        j = int(np.argmin(gap))
        if gap[j] <= tolerance_s:
            used[j] = True
            pairs.append((i, j))
    ti = np.array([p[0] for p in pairs], dtype=int)
    fj = np.array([p[1] for p in pairs], dtype=int)
    t_class, f_class = np.asarray(truth["class"]).astype(str), np.asarray(found["class"]).astype(str)
    t_red, f_red = np.asarray(truth["redirection"]).astype(str), np.asarray(found["redirection"]).astype(str)
    t_has, f_has = t_red[ti] != "none", f_red[fj] != "none"
    both = t_has & f_has & (t_red[ti] == f_red[fj])  # found, and of the right kind
    lift_errors, turn_errors = (
        _numbers(found[c])[fj][both] - _numbers(truth[c])[ti][both] if c in truth and c in found else np.zeros(0)
        for c in ("redirection_lift_m", "redirection_angle_deg"))
    scale_errors, scale_redirected = [], []
    for axis in ("scale_x", "scale_z"):
        ratio = _numbers(found[axis])[fj] / _numbers(truth[axis])[ti]
        for label in np.unique(f_class[fj]):
            pick = (f_class[fj] == label) & np.isfinite(ratio)
            if pick.sum() >= 2:
                r = ratio[pick]
                scale_errors.append(r / np.exp(np.median(np.log(r))) - 1.0)
                scale_redirected.append(t_red[ti][pick] != "none")
    return AnalysisScore(
        true=len(t_start), found=len(f_start), missed=len(t_start) - len(pairs), extra=int((~used).sum()),
        start_errors=f_start[fj] - t_start[ti], end_errors=f_end[fj] - t_end[ti],
        class_correct=int((t_class[ti] == f_class[fj]).sum()),
        redirect_tp=int((t_has & f_has).sum()), redirect_fp=int((~t_has & f_has).sum()),
        redirect_fn=int((t_has & ~f_has).sum()),
        redirect_kind_correct=int(both.sum()),
        scale_errors=np.concatenate(scale_errors) if scale_errors else np.zeros(0),
        scale_redirected=np.concatenate(scale_redirected) if scale_redirected else np.zeros(0, bool),
        lift_errors=lift_errors, turn_errors=turn_errors,
    )


def score_files(found_csv, truth_csv) -> AnalysisScore:
    """`score_analysis` of two cycles CSVs."""
    return score_analysis(load_cycle_table(found_csv), load_cycle_table(truth_csv))


def format_analysis_score(score: AnalysisScore) -> str:
    r = score.row()
    return (f"dig cycles: {r['found']} found of {r['true']} ({r['missed']} missed, {r['extra']} extra); "
            f"dig start error median {r['start_med_s']:.2f} s (95th {r['start_p95_s']:.2f}), end {r['end_med_s']:.2f} s "
            f"(95th {r['end_p95_s']:.2f}); class accuracy {r['class_acc']:.0%}; redirections precision "
            f"{r['redir_precision']:.0%} recall {r['redir_recall']:.0%}; " + (
                f"scale error median {r['scale_med']:.1%}" if np.isfinite(r["scale_med"])
                else "scale error not scored (fewer than two digs of any one class)"))


def planned_truth(machine, plan, fps: float = 30.0):
    """The truth motion (Motion at `fps`, base bouncing included) and truth cycles table of
    a planned synthetic session (`mocap.synthetic.motion.plan_session`), without cameras."""
    from mocap.core.motion import Motion

    times = np.arange(0.0, plan.duration, 1.0 / fps)
    joints = plan.joints(times)
    world_from_base = plan.world_from_base(times)
    motion = Motion(machine.joint_names, machine.point_names, np.arange(len(times)), times, joints,
                    machine.points(joints, world_from_base), machine.bucket_angles(joints, world_from_base))
    cycles = plan.cycles
    truth = {
        "class": np.array([c.label for c in cycles], dtype=object),
        "redirection": np.array([c.redirection for c in cycles], dtype=object),
        "scale_x": np.array([c.stretch[0] for c in cycles]), "scale_z": np.array([c.stretch[1] for c in cycles]),
        "dig_start_time": np.array([c.dig_start for c in cycles]), "dig_end_time": np.array([c.dig_end for c in cycles]),
        "redirection_lift_m": np.array([c.lift for c in cycles]),
        "redirection_angle_deg": np.degrees([c.turn for c in cycles]),
    }
    return motion, truth
