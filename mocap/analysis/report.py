"""The analysis report: one self-contained HTML page, figures drawn with matplotlib and
embedded as PNG, readable without the tool.

Figures follow the paper's Fig. 9-11: per class, the tip path in the vertical plane from
the dig start and the bucket angle against horizontal displacement, several cycles
overlaid with the class template, operator redirections marked; then the cycle-time
breakdown, the DTW similarity matrix, the bucket angle against the path's direction and
the parameters' correlations.
"""

from __future__ import annotations

import base64
import html
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from mocap.analysis.core import RELATED, Analysis  # noqa: E402

OVERLAID = 8
PHASES = (("dig_s", "dig"), ("swing_loaded_s", "swing loaded"), ("dump_s", "dump"), ("swing_back_s", "swing back"))


def figure_png(fig) -> str:
    """The figure as an <img>, drawn once: its margins are fixed (`page_subplots`), where
    bbox_inches="tight" would draw it twice."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def page_subplots(rows: int, cols: int, size: tuple[float, float], left: float, right: float, bottom: float,
              top: float, wgap: float = 0.0, hgap: float = 0.0):
    """plt.subplots (axes always 2-D) with margins and gaps between axes in inches, fixed
    for the figure's labels: a constrained layout measures every text once more before
    drawing, half of a figure's time."""
    width, height = size
    axes_w = (width - left - right - wgap * (cols - 1)) / cols
    axes_h = (height - bottom - top - hgap * (rows - 1)) / rows
    grid = dict(left=left / width, right=1 - right / width, bottom=bottom / height, top=1 - top / height,
                wspace=wgap / axes_w, hspace=hgap / axes_h)
    return plt.subplots(rows, cols, figsize=size, squeeze=False, gridspec_kw=grid)


def _class_figures(a: Analysis) -> str:
    labels = list(a.templates)
    width = min(4.6 * len(labels), 13.5)
    fig, axes = page_subplots(2, len(labels), (width, 7.6), left=0.75, right=0.15, bottom=0.55, top=0.35,
                          wgap=0.8, hgap=0.75)
    t, series = a.table, a.series
    for col, label in enumerate(labels):
        idx = np.flatnonzero(t["class"] == label)[:OVERLAID]
        path_ax, angle_ax = axes[0, col], axes[1, col]
        marks = []  # (dx, dz, angle) of each redirection: one artist per axes
        for k in idx:
            s0, s1 = a.segments.dig_start[k], a.segments.dig_end[k]
            dx = series.reach[s0:s1 + 1] - series.reach[s0]
            dz = series.height[s0:s1 + 1] - series.height[s0]
            angle = np.degrees(series.angle[s0:s1 + 1])
            path_ax.plot(dx, dz, lw=1, label=f"cycle {t['cycle'][k]}")
            angle_ax.plot(dx, angle, lw=1)
            if np.isfinite(t["redirection_time"][k]):
                j = series.index_at(t["redirection_time"][k]) - s0
                j = int(np.clip(j, 0, len(dx) - 1))
                marks.append((dx[j], dz[j], angle[j]))
        if marks:
            mx, mz, ma = np.array(marks).T
            path_ax.plot(mx, mz, "kx", ms=9, mew=2, label="redirection")
            angle_ax.plot(mx, ma, "kx", ms=9, mew=2)
        tpl = a.templates[label]
        path_ax.plot(tpl.path[:, 0], tpl.path[:, 1], "k--", lw=2, label="template")
        angle_ax.plot(tpl.path[:, 0], np.degrees(tpl.path[:, 2]), "k--", lw=2)
        path_ax.set(title=f"{label}: tip path ({tpl.count} dig{'s' if tpl.count != 1 else ''})",
                    xlabel="horizontal displacement (m)", ylabel="vertical displacement (m)")
        path_ax.set_aspect("equal", adjustable="datalim")
        angle_ax.set(title=f"{label}: bucket angle", xlabel="horizontal displacement (m)",
                     ylabel="bucket angle (deg)")
        path_ax.legend(fontsize=7, loc="upper left")  # a fixed place: "best" searches every line's points
        for ax in (path_ax, angle_ax):
            ax.grid(alpha=0.3)
    return figure_png(fig)


def _bars(x: np.ndarray, bottom: np.ndarray, top: np.ndarray, width: float = 0.8) -> np.ndarray:
    """Rectangles (K, 4, 2) of bars centred at x (K,) from bottom to top (K,)."""
    left, right = x - width / 2, x + width / 2
    return np.stack([np.column_stack(c) for c in ((left, bottom), (left, top), (right, top), (right, bottom))], axis=1)


PHASE_COLOURS = ("tab:orange", "tab:red", "tab:green", "tab:blue")


def _phase_spans(a: Analysis) -> list[tuple[int, int, int, int]]:
    """(cycle k, phase i, first index, last index) of every phase seen, in the series' indices:
    dig, swing loaded (to the dump), dump (the dwell at the truck), swing back (to the next dig)."""
    seg, spans = a.segments, []
    for k in range(len(a)):
        nxt = seg.dig_start[k + 1] if k + 1 < len(a) else -1
        bounds = (seg.dig_start[k], seg.dig_end[k], seg.truck_arrive[k], seg.truck_leave[k], nxt)
        for i in range(4):
            if bounds[i] >= 0 and bounds[i + 1] > bounds[i]:
                spans.append((k, i, int(bounds[i]), int(bounds[i + 1])))
    return spans


def _timeline_figure(a: Analysis) -> str:
    """The session over time: swing angle, tip height and bucket angle, phases shaded,
    cycles numbered."""
    s = a.series
    fig, axes = page_subplots(3, 1, (13, 6.4), left=0.85, right=0.2, bottom=0.55, top=0.55, hgap=0.15)
    axes = axes[:, 0]
    t = s.time - s.time[0]
    for ax, values, name in zip(axes, (np.degrees(s.azimuth), s.height, np.degrees(s.angle)),
                                ("swing (deg)", "tip height (m)", "bucket angle (deg)")):
        ax.plot(t, values, "k", lw=0.8)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax.set_xlim(t[0], t[-1])
    drawn = set()
    for k, i, first, last in _phase_spans(a):
        for ax in axes:
            ax.axvspan(t[first], t[last], color=PHASE_COLOURS[i], alpha=0.25, lw=0,
                       label=PHASES[i][1] if ax is axes[0] and i not in drawn else None)
        drawn.add(i)
    for k in range(len(a)):  # the cycle's number over its dig
        x = t[a.segments.dig_start[k]]
        axes[0].annotate(str(a.table["cycle"][k]), (x, 1.0), xycoords=("data", "axes fraction"),
                         xytext=(2, 3), textcoords="offset points", fontsize=9, weight="bold")
    for ax in axes[:-1]:
        ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel(f"time from the first frame (s); frame {int(s.frame[0])} at 0 s")
    if drawn:
        axes[0].legend(loc="lower left", bbox_to_anchor=(0.0, 1.09), ncols=len(drawn), fontsize=8, frameon=False)
    return figure_png(fig)


def _plan_figure(a: Analysis) -> str:
    """The tip seen from above (the swing axis at the origin): the whole session in grey,
    each dig in its cycle's colour, the dumps marked."""
    s = a.series
    x, y = s.reach * np.cos(s.azimuth), s.reach * np.sin(s.azimuth)
    fig, axes = page_subplots(1, 1, (8, 5.5), left=0.8, right=1.5, bottom=0.6, top=0.35)
    ax = axes[0, 0]
    ax.plot(x, y, color="0.7", lw=0.8, label="tip path")
    for k in range(len(a)):
        a0, b0 = a.segments.dig_start[k], a.segments.dig_end[k]
        ax.plot(x[a0:b0 + 1], y[a0:b0 + 1], lw=2, color=f"C{k % 10}", label=f"dig {a.table['cycle'][k]}")
    dumps = [k for k in range(len(a)) if a.segments.truck_arrive[k] >= 0]
    if dumps:
        j = a.segments.truck_arrive[dumps]
        ax.plot(x[j], y[j], "kv", ms=7, label="dump start")
    ax.plot([0], [0], "k+", ms=12, mew=2, label="swing axis")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="x (m)", ylabel="y (m)", title="Plan view of the bucket tip")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # beside the plot: it covers no path
    return figure_png(fig)


def _time_figure(a: Analysis) -> str:
    fig, axes = page_subplots(1, 1, (max(6.5, 0.3 * len(a) + 3), 3.8), left=0.7, right=0.2, bottom=0.55, top=0.65)
    ax = axes[0, 0]
    x = np.asarray(a.table["cycle"], dtype=float)
    bottom = np.zeros(len(a))
    for i, (column, name) in enumerate(PHASES):  # one collection per phase: a patch per bar costs seconds
        height = np.nan_to_num(np.asarray(a.table[column], dtype=float))
        top = bottom + height
        ax.add_collection(PolyCollection(_bars(x, bottom, top), facecolors=PHASE_COLOURS[i], edgecolors="none",
                                         label=name if (height > 0).any() else None))
        bottom = top
    ax.set_xlim(x.min() - 0.6, x.max() + 0.6)
    ax.set_ylim(0, max(float(bottom.max()), 1.0) * 1.05)
    if len(x) <= 40:
        ax.set_xticks(x, [str(int(c)) for c in x])
    ax.set(xlabel="cycle", ylabel="time (s)")
    ax.set_title("Cycle-time breakdown (a cycle ends where the next dig starts)", pad=22)
    ax.legend(fontsize=8, ncols=4, loc="lower left", bbox_to_anchor=(0.0, 1.0), frameon=False, borderaxespad=0.2)
    return figure_png(fig)


def _similarity_figure(a: Analysis) -> str:
    order = np.lexsort((a.table["cycle"], a.table["class"].astype(str)))
    fig, axes = page_subplots(1, 1, (6.2, 5.0), left=1.05, right=0.2, bottom=0.55, top=0.35)
    ax = axes[0, 0]
    image = ax.imshow(a.distance[np.ix_(order, order)], cmap="viridis", vmin=0)
    ticks = np.arange(len(order)) if len(order) <= 30 else np.arange(0, len(order), len(order) // 15)
    ax.set_xticks(ticks, [str(a.table["cycle"][order[i]]) for i in ticks], fontsize=7, rotation=90)
    ax.set_yticks(ticks, [f"{a.table['cycle'][order[i]]} {a.table['class'][order[i]]}" for i in ticks], fontsize=7)
    ax.set_xlabel("cycle")
    ax.set_title("DTW distance between digs (sorted by class)")
    fig.colorbar(image, ax=ax, label="DTW distance (dig lengths and rad, summed over the path)")
    return figure_png(fig)


def _relation_figure(a: Analysis) -> str:
    # the bottom margin holds the correlation matrix's vertical parameter names
    fig, axes = page_subplots(1, 2, (13, 5.6), left=0.75, right=0.75, bottom=1.45, top=0.35, wgap=1.6)
    axes = axes[0]
    labels = a.table["class"]
    for rel in a.relations:
        path = a.paths.path[labels == rel.label]
        direction = np.degrees(np.arctan2(np.gradient(path[:, :, 1], axis=1), np.gradient(path[:, :, 0], axis=1)))
        dots = axes[0].plot(direction[:, 2:-2].ravel(), np.degrees(path[:, 2:-2, 2]).ravel(), ".", ms=2, alpha=0.4)[0]
        if np.isfinite(rel.slope):
            x = np.linspace(-90, 90, 10)
            axes[0].plot(x, np.degrees(rel.intercept) + rel.slope * x, color=dots.get_color(),
                         label=f"{rel.label}: angle = {np.degrees(rel.intercept):.0f} + {rel.slope:.2f}·dir, r={rel.r:.2f}")
    axes[0].set(xlabel="direction of the tip's path (deg above horizontal)", ylabel="bucket angle (deg)",
                title="Bucket angle vs path direction", xlim=(-90, 100))
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7, loc="lower right")  # not "best": it would search the thousands of dots
    image = axes[1].imshow(a.correlation, cmap="coolwarm", vmin=-1, vmax=1)
    axes[1].set_xticks(range(len(RELATED)), RELATED, rotation=90, fontsize=7)
    axes[1].set_yticks(range(len(RELATED)), RELATED, fontsize=7)
    axes[1].set_title("Correlation of cycle parameters")
    fig.colorbar(image, ax=axes[1], label="Pearson r")
    return figure_png(fig)


def _spread(values) -> tuple[str, str, str, int]:
    """Median, interquartile range and min-max of the finite values, as text, and their count."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return "", "", "", 0
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return f"{med:.1f}", f"{q1:.1f}–{q3:.1f}", f"{v.min():.1f}–{v.max():.1f}", len(v)


def summary_rows(a: Analysis) -> list[list]:
    """The summary table's rows: quantity, median, IQR, range, n (cycle time and each phase, s)."""
    rows = []
    for column, name in (("cycle_time_s", "cycle time"),) + PHASES:
        med, iqr, span, n = _spread(a.table[column])
        rows.append([f"{name} (s)", med, iqr, span, n])
    return rows


def _summary(a: Analysis) -> str:
    t = a.table
    counts = {label: int((t["class"] == label).sum()) for label in dict.fromkeys(t["class"])}
    timed = int(np.isfinite(np.asarray(t["cycle_time_s"], dtype=float)).sum())
    redirected = int((t["redirection"] != "none").sum())
    facts = html_table(["cycles", "with a cycle time", "classes", "redirections"],
                   [[len(a), timed, ", ".join(f"{k}: {v}" for k, v in counts.items()), redirected]])
    spread = html_table(["", "median", "middle half (IQR)", "range", "cycles"], summary_rows(a))
    note = ("" if timed else "<p>No cycle has a time: a cycle's time runs from its dig to the next dig, "
            "and this motion holds one dig only.</p>")
    return facts + spread + note


def html_table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _f(value, digits=2) -> str:
    value = float(value)
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def _say(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


def render_report(a: Analysis, title: str) -> str:
    """The report's HTML text."""
    t = a.table
    parts = [f"<h1>{html.escape(title)}</h1>"]
    if len(a) == 0:
        parts.append("<p>No dig cycle was found in this motion.</p>")
    else:
        parts.append("<h2>Summary</h2>" + _summary(a))
        parts.append(f"<p>Unsupervised grouping of the dig paths: {a.grouping.count} group(s)"
                     + (f" and {int((a.grouping.groups == 0).sum())} outlier dig(s)" if (a.grouping.groups == 0).any() else "")
                     + (f" (silhouette {a.grouping.silhouette:.2f})" if np.isfinite(a.grouping.silhouette) else "")
                     + (": more types than the three classes." if a.grouping.count > 3 else
                        ": no more types than the three classes.") + "</p>")
        parts.append("<h2>The session over time</h2><p>Swing angle, bucket tip height and bucket angle; the "
                     "phases shaded, each cycle's number over its dig.</p>" + _timeline_figure(a))
        parts.append("<h2>Plan view of the swing</h2>" + _plan_figure(a))
        parts.append("<h2>1. Motion characteristics while digging</h2><p>Per class, the tip's path from the dig "
                     "start and the bucket angle along it, up to eight digs overlaid; dashed: the class template; "
                     "x: an operator's redirection.</p>" + _class_figures(a))
        rows = [[c, k, _f(t["start_height_m"][i]), _f(t["start_angle_deg"][i], 0), _f(t["dig_s"][i], 1),
                 _f(t["dig_length_m"][i]), _f(t["scale_x"][i]), _f(t["scale_z"][i]), t["redirection_kind"][i],
                 t["class_rule"][i]] for i, (c, k) in enumerate(zip(t["cycle"], t["class"]))]
        parts.append(html_table(["cycle", "class", "start height m", "start angle deg", "dig s", "length m",
                             "scale x", "scale z", "redirection", "rule"], rows))
        parts.append("<h2>2. How similar consecutive cycles are</h2>")
        parts.append(_similarity_figure(a) if len(a) > 1 else _say("One cycle: similarity needs two."))
        timed = np.isfinite(np.asarray(t["cycle_time_s"], dtype=float)).any()
        parts.append(_time_figure(a) if timed else _say("No cycle time: a cycle ends where the next dig starts, "
                                                         "and there is no next dig."))
        groups = [["outliers" if g == 0 else g, int((a.grouping.groups == g).sum()),
                   ", ".join(f"{k} {int(((a.grouping.groups == g) & (t['class'] == k)).sum())}" for k in a.templates)]
                  for g in np.unique(a.grouping.groups)]
        parts.append(html_table(["group", "digs", "by class"], groups))
        parts.append("<h2>3. Adjustment from one load to the next</h2>")
        if len(a) > 1:
            changes = [c for c in t if c.startswith("change_")]
            rows = [[c, _f(t["dtw_to_previous"][i])] + [_f(t[n][i]) for n in changes]
                    for i, c in enumerate(t["cycle"]) if i > 0]
            parts.append("<p>Each cycle's change from the one before it (units of the columns of cycles.csv: "
                         "m, deg, s; scales as ratios).</p>"
                         + html_table(["cycle", "DTW to previous"] + [c.removeprefix("change_") for c in changes], rows))
        else:
            parts.append(_say("One cycle: an adjustment needs two."))
        parts.append("<h2>4. Relations between motion parameters</h2>")
        if len(a) >= 3:
            parts.append(_relation_figure(a))
        else:
            parts.append(_say(f"{len(a)} cycle(s): correlations between cycle parameters need at least three."))
    style = ("body{font-family:sans-serif;max-width:1200px;margin:auto;padding:0 8px}table{border-collapse:collapse;"
             "font-size:12px;margin:6px 0}td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%;height:auto;"
             "display:block;margin:8px 0}.note{font-style:italic;color:#444}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
