"""The session report: the quality of one session's measurement on one self-contained HTML
page — per camera its calibration residual, parameter SDs, place in a plan of the site and
the share of each marker tracked over time; the sync offsets; the fit's residuals and SDs
over time with its unexplained and filled frames; and, first, what to fix first in words.

Pure in its parts (`SessionQuality` from the files, `advice` from that, the page from both);
`write_session_report` reads a session folder and writes the page atomically.
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocap.analysis.report import figure_png, page_subplots, html_table, plt
from mocap.core.calibration import Calibration
from mocap.core.motion import Motion
from mocap.core.tracks import Tracks
from mocap.errors import InputError
from mocap.io.atomic import write_text
from mocap.io.cameras_toml import load_calibration
from mocap.io.motion_csv import load_motion
from mocap.io.session import Session
from mocap.io.tracks_csv import load_tracks

REPORT = "session_report.html"
BIN_S = 2.0  # the heat map's time bins (s)
WORST_RESIDUAL = 2.0  # a camera's calibration residual this many times the noise is worth a look
LOW_SHARE = 0.5  # a marker a camera sees in less than this share of the frames
FAR_SD_M = 0.5  # a camera placed less certainly than this (m) from the one frame
MANY_FILLED = 0.05  # share of frames filled or unexplained worth a word


@dataclass(frozen=True)
class CameraQuality:
    """One camera: `rms_px` of the one-frame calibration (and of the refined one, NaN if
    none), `position` (3,) m and `position_sd` (3,) m, angle SDs (deg) and focal SD (px),
    the sync `offset_s` and `fps`; `markers` the markers its tracks name, `bins` (B,) time bin
    starts (s), `share` (M, B) of the camera's frames in each bin where each marker was tracked."""

    name: str
    rms_px: float
    refined_rms_px: float
    position: np.ndarray
    position_sd: np.ndarray
    angle_sd_deg: np.ndarray
    focal_sd_px: float
    offset_s: float
    fps: float
    markers: tuple[str, ...]
    bins: np.ndarray
    share: np.ndarray


@dataclass(frozen=True)
class SessionQuality:
    """The session's cameras, its calibration noise estimate `sigma_px` (NaN if unknown),
    and the fitted `motion` (None before the fit)."""

    cameras: tuple[CameraQuality, ...]
    sigma_px: float
    motion: Motion | None


def _vector(table: dict, key: str, n: int) -> np.ndarray:
    value = table.get(key)
    return np.full(n, np.nan) if value is None else np.asarray(value, dtype=float).reshape(n)


def marker_shares(tracks: Tracks, camera: str, fps: float, offset: float, bin_s: float = BIN_S):
    """(markers, bin starts (B,) s, share (M, B)) of one camera's frames in each time bin
    where each marker was tracked; time on the reference clock."""
    own = tracks.select(np.asarray(tracks.camera) == camera)
    frames = np.asarray(own.frame, dtype=int)
    if len(frames) == 0:
        return (), np.zeros(0), np.zeros((0, 0))
    markers = tuple(sorted(set(own.marker)))
    times = frames / fps + offset
    edges = np.arange(times.min(), times.max() + bin_s, bin_s)
    all_frames = np.arange(frames.min(), frames.max() + 1)
    per_bin = np.maximum(np.histogram(all_frames / fps + offset, edges)[0], 1)
    index = {m: i for i, m in enumerate(markers)}
    rows = np.array([index[m] for m in own.marker])
    share = np.zeros((len(markers), len(edges) - 1))
    bins = np.clip(np.searchsorted(edges, times, side="right") - 1, 0, len(edges) - 2)
    np.add.at(share, (rows, bins), 1.0)
    return markers, edges[:-1], np.minimum(share / per_bin, 1.0)


def session_quality(root: str | Path) -> SessionQuality:
    """Read a session folder's calibration, tracks and motion; InputError without a calibration."""
    session = Session.open(root)
    if not session.calibration_path.is_file():
        raise InputError("no calibration in this session yet: run `mocap run` (or calibrate) first",
                         path=session.calibration_path)
    first = load_calibration(session.calibration_path)
    refined = load_calibration(session.refined_calibration_path) if session.refined_calibration_path.is_file() else None
    cameras = []
    for k, name in enumerate(first.names):
        extras = first.extras[k]
        paper_sd = extras.get("paper", {}).get("sd", {})
        position = np.asarray(first.cameras[k].center, dtype=float)
        best: Calibration = refined if refined is not None and name in refined.names else first
        j = best.names.index(name)
        offset, fps = float(best.extras[j].get("time_offset", 0.0)), float(best.extras[j].get("fps", 30.0))
        path = session.tracks_path(name)
        shares = marker_shares(load_tracks(path), name, fps, offset) if path.is_file() else ((), np.zeros(0), np.zeros((0, 0)))
        cameras.append(CameraQuality(
            name, float(extras.get("error", np.nan)),
            float(refined.extras[j].get("error", np.nan)) if best is refined else np.nan,
            np.asarray(best.cameras[j].center, dtype=float) if best is refined else position,
            _vector(paper_sd, "position", 3),
            np.array([paper_sd.get(a, np.nan) for a in ("azimuth_deg", "elevation_deg", "tilt_deg")], dtype=float),
            float(paper_sd.get("focal_px", np.nan)), offset, fps, *shares))
    motion = load_motion(session.motion_path, session.machine()) if session.motion_path.is_file() else None
    return SessionQuality(tuple(cameras), float(first.metadata.get("sigma_px", np.nan)), motion)


__all__ = ["REPORT", "SessionQuality", "advice", "marker_shares", "session_quality", "write_session_report"]


def _column(motion: Motion, name: str) -> np.ndarray | None:
    value = motion.extra.get(name)
    return None if value is None else np.nan_to_num(np.asarray(value, dtype=float))


def advice(q: SessionQuality) -> list[str]:
    """What to fix first, most important first, in words; one line saying so when nothing stands out."""
    out = []
    for c in q.cameras:
        if np.isfinite(q.sigma_px) and c.rms_px > WORST_RESIDUAL * q.sigma_px:
            out.append(f"{c.name}: its calibration residual is {c.rms_px:.2f} px, over {WORST_RESIDUAL:g} times the "
                       f"noise ({q.sigma_px:.2f} px): check its clicked labels (calibration/labels.csv) for a "
                       f"swapped or misplaced marker.")
    for c in q.cameras:
        sd = float(np.linalg.norm(c.position_sd))
        if sd > FAR_SD_M and not np.isfinite(c.refined_rms_px):  # a refined camera is placed by the session
            out.append(f"{c.name}: the one frame places it only to ±{sd:.1f} m; refine it over the session "
                       "(`mocap run` does, or `mocap refine`).")
    for c in q.cameras:
        if c.share.size:
            mean = c.share.mean(axis=1)
            low = [f"{m} ({s:.0%})" for m, s in zip(c.markers, mean) if s < LOW_SHARE]
            if low:
                out.append(f"{c.name}: markers tracked in under {LOW_SHARE:.0%} of its frames: {', '.join(low[:8])}"
                           + (" and more" if len(low) > 8 else "") + ". A marker behind the machine for part of "
                           "each cycle is expected (see the heat map); one missing all along is too small or "
                           "lost: a closer camera or a longer lens sees it better.")
    if q.motion is not None and len(q.motion):
        for name, what in (("unexplained", "unexplained (pixels the model does not fit)"),
                           ("filled", "filled (too few pixels to fit; bridged)")):
            col = _column(q.motion, name)
            if col is not None and (col > 0).mean() > MANY_FILLED:
                out.append(f"{(col > 0).mean():.0%} of the fitted frames are {what}: see the fit over time below.")
    return out or ["Nothing stands out: every camera's residual is near the noise, every marker is tracked in most "
                   "frames and the fit explains its frames."]


def _plan_figure(q: SessionQuality) -> str:
    fig, axes = page_subplots(1, 1, (7.5, 6), left=0.8, right=0.2, bottom=0.6, top=0.35)
    ax = axes[0, 0]
    if q.motion is not None and "bucket_tip" in q.motion.point_names:
        tip = q.motion.point("bucket_tip")
        ax.plot(tip[:, 0], tip[:, 1], color="0.6", lw=0.8, label="bucket tip")
    ax.plot([0], [0], "k+", ms=12, mew=2, label="machine (swing axis)")
    for k, c in enumerate(q.cameras):
        ax.plot(*c.position[:2], "o", color=f"C{k}", ms=8, label=f"{c.name}")
        sd = c.position_sd[:2]
        if np.all(np.isfinite(sd)):
            ax.errorbar(*c.position[:2], xerr=2 * sd[0], yerr=2 * sd[1], color=f"C{k}", capsize=3)
        ax.annotate(c.name, c.position[:2], xytext=(6, 6), textcoords="offset points")
        ax.plot([c.position[0], 0], [c.position[1], 0], ":", color=f"C{k}", lw=1)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Where the cameras stand (bars: ±2 SD from the one frame)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")  # not "best": it would search the tip's every point
    return figure_png(fig)


def _heat_figure(q: SessionQuality) -> str:
    shown = [c for c in q.cameras if c.share.size]
    rows = max(len(c.markers) for c in shown)
    fig, axes = page_subplots(len(shown), 1, (12, len(shown) * (0.16 * rows + 0.9) + 0.8), left=0.8, right=1.3,
                          bottom=0.55, top=0.3, hgap=0.6)
    image = None
    for ax, c in zip(axes[:, 0], shown):
        extent = (c.bins[0], c.bins[-1] + BIN_S, len(c.markers) - 0.5, -0.5)
        image = ax.imshow(c.share, aspect="auto", cmap="viridis", vmin=0, vmax=1, extent=extent,
                          interpolation="nearest")
        ax.set_yticks(range(len(c.markers)), c.markers, fontsize=6)
        ax.set_title(f"{c.name}: share of frames each marker was tracked ({BIN_S:g} s bins)", fontsize=9)
    axes[-1, 0].set_xlabel("time (s, reference clock)")
    fig.colorbar(image, ax=axes[:, 0].tolist(), label="share of frames tracked", fraction=0.03, pad=0.01)
    return figure_png(fig)


def _fit_figure(motion: Motion) -> str:
    t = motion.time
    fig, axes = page_subplots(2, 1, (12, 5.2), left=0.8, right=0.2, bottom=0.55, top=0.55, hgap=0.2)
    rms = _column(motion, "rms_px")
    top, bottom = axes[0, 0], axes[1, 0]
    if rms is not None:
        top.plot(t, rms, "k", lw=0.7, label="fit residual (rms px)")
    top.set_ylabel("residual (px)")
    if motion.joints_sd is not None:
        for j, name in enumerate(motion.joint_names):
            bottom.plot(t, np.degrees(motion.joints_sd[:, j]), lw=0.8, label=f"{name} SD")
    bottom.set(ylabel="joint SD (deg)", xlabel="time (s)")
    for name, colour in (("unexplained", "tab:red"), ("filled", "tab:orange")):
        col = _column(motion, name)
        if col is not None and (col > 0).any():
            for ax in (top, bottom):
                ax.fill_between(t, 0, 1, where=col > 0, color=colour, alpha=0.3, transform=ax.get_xaxis_transform(),
                                lw=0, label=f"{name} frames" if ax is top else None)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
        ax.set_xlim(t[0], t[-1])
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, loc="upper right", ncols=4)
    top.tick_params(labelbottom=False)
    top.set_title("The fit over time")
    return figure_png(fig)


def render_session_report(q: SessionQuality, title: str) -> str:
    parts = [f"<h1>{html.escape(title)}</h1>", "<h2>What to fix first</h2><ol>"
             + "".join(f"<li>{html.escape(a)}</li>" for a in advice(q)) + "</ol>"]
    sigma = f"{q.sigma_px:.2f} px" if np.isfinite(q.sigma_px) else "unknown"
    rows = [[c.name, f"{c.rms_px:.2f}", "yes" if np.isfinite(c.refined_rms_px) else "no",
             " / ".join(f"{v:.2f}" for v in c.position_sd), " / ".join(f"{v:.2f}" for v in c.angle_sd_deg),
             f"{c.focal_sd_px:.1f}", f"{np.linalg.norm(c.position):.0f}"] for c in q.cameras]
    parts.append(f"<h2>Cameras</h2><p>Calibration from one frame (noise estimate {sigma}): its residual and "
                 "the SDs of its parameters; the plan shows the refined position where there is one.</p>"
                 + html_table(["camera", "residual px", "refined over the session", "position SD x / y / z m",
                           "azimuth / elevation / tilt SD deg", "focal SD px", "distance m"], rows))
    parts.append(_plan_figure(q))
    parts.append("<h2>Markers tracked over time</h2>")
    parts.append(_heat_figure(q) if any(c.share.size for c in q.cameras) else
                 '<p class="note">No tracks yet: run `mocap track` (or `mocap run`).</p>')
    rows = [[c.name, f"{c.fps:g}", f"{c.offset_s:+.4f}", f"{c.offset_s * q.cameras[0].fps:+.2f}"] for c in q.cameras]
    parts.append("<h2>Sync</h2><p>Each camera's clock against the first camera's. The sync stage records no "
                 "uncertainty of its offsets; the session's refinement and fit residuals below show what an "
                 "offset error would leave.</p>"
                 + html_table(["camera", "fps", "time offset s", "offset (first camera's frames)"], rows))
    parts.append("<h2>The fit</h2>")
    if q.motion is None or len(q.motion) == 0:
        parts.append('<p class="note">No fitted motion yet: run `mocap fit` (or `mocap run`).</p>')
    else:
        m = q.motion
        counts = {name: int((_column(m, name) > 0).sum()) for name in ("unexplained", "filled")
                  if _column(m, name) is not None}
        rms = _column(m, "rms_px")
        median = f", median residual {np.median(rms[rms > 0]):.2f} px" if rms is not None and (rms > 0).any() else ""
        parts.append(f"<p>{len(m)} frames{median}; " + ", ".join(f"{v} {k}" for k, v in counts.items()) + ".</p>"
                     + _fit_figure(m))
    style = ("body{font-family:sans-serif;max-width:1200px;margin:auto;padding:0 8px}table{border-collapse:collapse;"
             "font-size:12px;margin:6px 0}td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%;height:auto;"
             "display:block;margin:8px 0}.note{font-style:italic;color:#444}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")


def write_session_report(root: str | Path, out: str | Path | None = None) -> Path:
    """Write the session report of the folder `root` (default results/session_report.html); returns its path."""
    session = Session.open(root)
    if not session.config_path.is_file():
        raise InputError("not a session folder (no session.toml); give the session folder", path=root)
    quality = session_quality(root)
    path = Path(out) if out is not None else session.results_dir / REPORT
    write_text(path, render_session_report(quality, f"Session report: {session.root.resolve().name}"))
    plt.close("all")
    return path
