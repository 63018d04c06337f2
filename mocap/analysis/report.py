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


def _png(fig) -> str:
    """The figure as an <img>, drawn once: its margins are fixed (`_subplots`), where
    bbox_inches="tight" would draw it twice."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return f'<img src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _subplots(rows: int, cols: int, size: tuple[float, float], left: float, right: float, bottom: float,
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
    fig, axes = _subplots(2, len(labels), (4.6 * len(labels), 8), left=0.75, right=0.15, bottom=0.55, top=0.6,
                          wgap=0.8, hgap=0.85)
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
            path_ax.plot(mx, mz, "kx", ms=9, mew=2)
            angle_ax.plot(mx, ma, "kx", ms=9, mew=2)
        tpl = a.templates[label]
        path_ax.plot(tpl.path[:, 0], tpl.path[:, 1], "k--", lw=2, label="template")
        angle_ax.plot(tpl.path[:, 0], np.degrees(tpl.path[:, 2]), "k--", lw=2)
        path_ax.set(title=f"{label}: tip path ({tpl.count} digs)",
                    xlabel="horizontal displacement (m)", ylabel="vertical displacement (m)")
        path_ax.set_aspect("equal", adjustable="datalim")
        angle_ax.set(title=f"{label}: bucket angle", xlabel="horizontal displacement (m)",
                     ylabel="bucket angle (deg)")
        path_ax.legend(fontsize=7, loc="upper left")  # a fixed place: "best" searches every line's points
        for ax in (path_ax, angle_ax):
            ax.grid(alpha=0.3)
    fig.suptitle("Dig paths from the dig start, per class (x: operator redirection; dashed: template)")
    return _png(fig)


def _bars(x: np.ndarray, bottom: np.ndarray, top: np.ndarray, width: float = 0.8) -> np.ndarray:
    """Rectangles (K, 4, 2) of bars centred at x (K,) from bottom to top (K,)."""
    left, right = x - width / 2, x + width / 2
    return np.stack([np.column_stack(c) for c in ((left, bottom), (left, top), (right, top), (right, bottom))], axis=1)


def _time_figure(a: Analysis) -> str:
    fig, axes = _subplots(1, 1, (max(6, 0.25 * len(a) + 3), 3.5), left=0.6, right=0.15, bottom=0.5, top=0.35)
    ax = axes[0, 0]
    x = np.asarray(a.table["cycle"], dtype=float)
    bottom = np.zeros(len(a))
    for i, (column, name) in enumerate(PHASES):  # one collection per phase: a patch per bar costs seconds
        top = bottom + np.nan_to_num(np.asarray(a.table[column], dtype=float))
        ax.add_collection(PolyCollection(_bars(x, bottom, top), facecolors=f"C{i}", edgecolors="none", label=name))
        bottom = top
    ax.autoscale_view()
    ax.set_ylim(bottom=0)
    ax.set(xlabel="cycle", ylabel="time (s)", title="Cycle-time breakdown")
    ax.legend(fontsize=8, ncols=4, loc="upper right")
    return _png(fig)


def _similarity_figure(a: Analysis) -> str:
    order = np.lexsort((a.table["cycle"], a.table["class"].astype(str)))
    fig, axes = _subplots(1, 1, (5.5, 4.8), left=0.75, right=0.1, bottom=0.35, top=0.3)
    ax = axes[0, 0]
    image = ax.imshow(a.distance[np.ix_(order, order)], cmap="viridis")
    ticks = np.arange(len(order)) if len(order) <= 30 else np.arange(0, len(order), len(order) // 15)
    ax.set_xticks(ticks, [str(a.table["cycle"][order[i]]) for i in ticks], fontsize=6, rotation=90)
    ax.set_yticks(ticks, [f"{a.table['cycle'][order[i]]} {a.table['class'][order[i]]}" for i in ticks], fontsize=6)
    ax.set_title("DTW distance between digs (sorted by class)")
    fig.colorbar(image, ax=ax, label="DTW distance (dig lengths)")
    return _png(fig)


def _relation_figure(a: Analysis) -> str:
    # the bottom margin holds the correlation matrix's vertical parameter names
    fig, axes = _subplots(1, 2, (11, 5.2), left=0.75, right=0.75, bottom=1.25, top=0.3, wgap=1.35)
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
    axes[0].legend(fontsize=7, loc="lower right")  # not "best": it would search the thousands of dots
    image = axes[1].imshow(a.correlation, cmap="coolwarm", vmin=-1, vmax=1)
    axes[1].set_xticks(range(len(RELATED)), RELATED, rotation=90, fontsize=7)
    axes[1].set_yticks(range(len(RELATED)), RELATED, fontsize=7)
    axes[1].set_title("Correlation of cycle parameters")
    fig.colorbar(image, ax=axes[1], label="Pearson r")
    return _png(fig)


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(v))}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _f(value, digits=2) -> str:
    value = float(value)
    return "" if not np.isfinite(value) else f"{value:.{digits}f}"


def render_report(a: Analysis, title: str) -> str:
    """The report's HTML text."""
    t = a.table
    parts = [f"<h1>{html.escape(title)}</h1>"]
    if len(a) == 0:
        parts.append("<p>No dig cycle was found in this motion.</p>")
    else:
        counts = {label: int((t["class"] == label).sum()) for label in dict.fromkeys(t["class"])}
        parts.append(f"<p>{len(a)} cycles; classes: " + ", ".join(f"{k} {v}" for k, v in counts.items()) + ". "
                     f"Unsupervised grouping of the dig paths: {a.grouping.count} group(s)"
                     + (f" and {int((a.grouping.groups == 0).sum())} outlier dig(s)" if (a.grouping.groups == 0).any() else "")
                     + (f" (silhouette {a.grouping.silhouette:.2f})" if np.isfinite(a.grouping.silhouette) else "")
                     + (": more types than the three classes." if a.grouping.count > 3 else
                        ": no more types than the three classes.") + "</p>")
        parts.append("<h2>1. Motion characteristics while digging</h2>" + _class_figures(a))
        rows = [[c, k, _f(t["start_height_m"][i]), _f(t["start_angle_deg"][i], 0), _f(t["dig_s"][i], 1),
                 _f(t["dig_length_m"][i]), _f(t["scale_x"][i]), _f(t["scale_z"][i]), t["redirection_kind"][i],
                 t["class_rule"][i]] for i, (c, k) in enumerate(zip(t["cycle"], t["class"]))]
        parts.append(_table(["cycle", "class", "start height m", "start angle deg", "dig s", "length m",
                             "scale x", "scale z", "redirection", "rule"], rows))
        parts.append("<h2>2. How similar consecutive cycles are</h2>" + _similarity_figure(a) + _time_figure(a))
        groups = [["outliers" if g == 0 else g, int((a.grouping.groups == g).sum()),
                   ", ".join(f"{k} {int(((a.grouping.groups == g) & (t['class'] == k)).sum())}" for k in a.templates)]
                  for g in np.unique(a.grouping.groups)]
        parts.append(_table(["group", "digs", "by class"], groups))
        changes = [c for c in t if c.startswith("change_")]
        rows = [[c, _f(t["dtw_to_previous"][i])] + [_f(t[n][i]) for n in changes] for i, c in enumerate(t["cycle"])]
        parts.append("<h2>3. Adjustment from one load to the next</h2>"
                     + _table(["cycle", "DTW to previous"] + [c.removeprefix("change_") for c in changes], rows))
        parts.append("<h2>4. Relations between motion parameters</h2>" + _relation_figure(a))
    style = ("body{font-family:sans-serif;max-width:1400px;margin:auto}table{border-collapse:collapse;"
             "font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
