"""General shape and deviations: per-class templates over normalised arc length, each dig
as template × scaling plus deviations (PAPER.md).

A dig's path is taken in the house's vertical plane from its start: horizontal
displacement ``dx`` (m, away from the machine), vertical ``dz`` (m, up) and bucket angle,
resampled at N points of normalised arc length ``s`` in [0, 1]. A class's template is the
median of its digs divided by their scales; a dig's scale (sx, sz) is the least-squares
stretch of the template onto it, normalised so that each class's scales have a geometric
mean of 1 (the template's size is the class's typical size). Both are taken from the path
low-passed at `PATH_CUTOFF_HZ` (`dig_channels`, `general_paths`), without the samples
within an operator's redirection (nor, for the template, after it), and less the
redirection's own lift: its event's shape in time (a step or a pulse) times the height
that lets the class template fit the dig best (`fit_lifts`), taken out before the arc
length is taken (a kept lift along a steep rise would otherwise read as a taller dig).
Deviations:

- **reactive**: the RMS of the path and angle about their own low-pass (``cutoff_hz``);
- **operator redirection**: a sudden turn of the bucket its smooth profile cannot explain,
  found by fitting the bucket angle with a quintic in time (the classes' angle profiles are
  smooth in it; the height's are not, the floor push bending into the rise within a
  second) plus an event in time — a pulse (temporary) or a step (kept) — at every place
  and width of a grid, and keeping the event that explains most of it; a slow kept step,
  partly taken up by the quintic, also counts where the same event explains the angle
  about a cubic in arc length and the height about a quintic in time together. Its kind
  says lift or lower (the same event in the height), the angle change, temporary or kept,
  and reversal when the tip moved back.

Shapes: K digs, N arc-length samples, T frames of one dig, G event candidates.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.signal import butter, sosfiltfilt

from mocap.analysis.features import OTHER
from mocap.analysis.series import TipSeries

N_SAMPLES = 64
MIN_EVENT_FRAMES = 30
PATH_CUTOFF_HZ = 0.5  # low-pass of the path a dig's general shape and scale are taken from


@dataclass(frozen=True)
class DigPaths:
    """K digs resampled over arc length: s (N,), path (K, N, 3) dx, dz (m), angle (rad)."""

    s: np.ndarray
    path: np.ndarray


@dataclass(frozen=True)
class Template:
    """A class's general shape: `label`, `count` digs; path (N, 3) dx, dz (m), angle (rad)
    over arc length `s` (N,); `start` (3,) median start reach, height (m), angle (rad)."""

    label: str
    count: int
    s: np.ndarray
    path: np.ndarray
    start: np.ndarray


@dataclass(frozen=True)
class Deviations:
    """Per dig (K,): scale_x, scale_z; reactive_m, reactive_deg (RMS); redirection
    ('none', 'temporary', 'kept'), its time (s, NaN without), angle change (rad), lift (m),
    kind in words, and its centre and half-width as shares of the dig's time (NaN without);
    whether the tip moved back within it; the dig's path length (m)."""

    scale_x: np.ndarray
    scale_z: np.ndarray
    reactive_m: np.ndarray
    reactive_deg: np.ndarray
    redirection: np.ndarray
    redirection_time: np.ndarray
    redirection_angle: np.ndarray
    redirection_lift: np.ndarray
    redirection_kind: np.ndarray
    redirection_centre: np.ndarray
    redirection_width: np.ndarray
    redirection_reversal: np.ndarray
    length: np.ndarray

    def with_lifts(self, lift: np.ndarray) -> Deviations:
        """The same with each redirection's lift (K,) m (as `fit_lifts` finds it against the
        class template), its kind's words said again."""
        lift = np.where(self.redirection != "none", lift, np.nan)
        words = np.array([_kind_words(*v) if v[0] != "none" else "" for v in zip(
            self.redirection, self.redirection_angle, lift, self.length, self.redirection_reversal)], dtype=object)
        return replace(self, redirection_lift=lift, redirection_kind=words)


def _kind_words(kind: str, angle: float, lift: float, length: float, reversal: bool) -> str:
    """A redirection in words: lift or lower (beyond 1.5 % of the dig's length), the angle
    change, reversal, temporary or kept."""
    words = ["lift" if lift > 0 else "lower"] if abs(lift) > 0.015 * length else []
    words.append(f"bucket angle {np.degrees(angle):+.0f} deg")
    return ", ".join(words + (["reversal"] if reversal else []) + [kind])


def _arc(r: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Normalised arc length (T,) of a path."""
    step = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(z)))])
    return step / max(step[-1], 1e-12)


def resample_digs(series: TipSeries, starts: np.ndarray, ends: np.ndarray, n: int = N_SAMPLES) -> DigPaths:
    """Each dig [start, end] (indices) resampled at `n` points of normalised arc length."""
    s = np.linspace(0.0, 1.0, n)
    out = np.empty((len(starts), n, 3))
    for k, (a, b) in enumerate(zip(starts, ends)):
        r, z, angle = series.reach[a:b + 1], series.height[a:b + 1], series.angle[a:b + 1]
        u = _arc(r, z)
        u, keep = np.unique(u, return_index=True)
        out[k, :, 0] = np.interp(s, u, r[keep] - r[0])
        out[k, :, 1] = np.interp(s, u, z[keep] - z[0])
        out[k, :, 2] = np.interp(s, u, angle[keep])
    return DigPaths(s, out)


def fit_scales(path: np.ndarray, template: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares stretch (K, 2) of a template path (N, 2) onto digs (K, N, 2).
    `weights` (K, N) in [0, 1], default 1 (0 leaves a sample out: the redirection's window)."""
    w = np.ones(path.shape[:2]) if weights is None else weights
    num = np.einsum("kn,knd,nd->kd", w, path, template)
    return num / np.maximum(w @ template**2, 1e-12)


def _descaled(xy: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Digs' paths (K, N, C) resampled at even arc length of their first two channels
    divided by their scales (K, 2), so that a stretched dig's points meet the template's
    at the same place; further channels (events) follow their points."""
    n = xy.shape[1]
    q = xy[:, :, :2] / scale[:, None, :]
    step = np.hypot(*np.diff(q, axis=1).transpose(2, 0, 1))
    arc = np.concatenate([np.zeros((len(xy), 1)), np.cumsum(step, axis=1)], axis=1)
    arc /= np.maximum(arc[:, -1:], 1e-12)
    even = np.linspace(0.0, 1.0, n)
    return np.stack([_interp_rows(even, arc, xy[:, :, d]) for d in range(xy.shape[2])], axis=-1)


def build_templates(paths: DigPaths, labels: np.ndarray, starts: np.ndarray, after: np.ndarray | None = None,
                    window: np.ndarray | None = None, iterations: int = 4) -> tuple[dict[str, Template], np.ndarray]:
    """Per-label templates and every dig's scale (K, 2) against its label's template.

    `starts` (K, 3) start reach, height, angle of each dig. `window` (K, N) in [0, 1], the
    samples within a redirection (1): they are left out of the scale fit and of the
    template (each sample the median of the digs outside a window there), so that a
    temporary lift or lower neither stretches its dig nor bends its class's shape. `after`
    (K, N) 1 at the samples after a redirection: left out of the template too (a kept
    lift the path still holds would bend it; `fit_lifts` takes it out of the dig's path).
    """
    scales = np.ones((len(labels), 2))
    after = np.zeros(paths.path.shape[:2]) if after is None else after
    window = np.zeros(paths.path.shape[:2]) if window is None else window
    templates: dict[str, Template] = {}
    for label in dict.fromkeys(labels):
        pick = labels == label
        xy = np.concatenate([paths.path[pick, :, :2], after[pick, :, None], window[pick, :, None]], axis=-1)
        template = _template(xy[..., :2], xy[..., 3] + xy[..., 2])
        sc = np.ones((len(xy), 2))
        for _ in range(iterations):
            even = _descaled(xy, sc)
            sc = _normalised(fit_scales(even[..., :2], template, 1.0 - np.clip(even[..., 3], 0, 1)))
            general = _descaled(xy, sc)
            template = _template(general[..., :2] / sc[:, None, :], general[..., 3] + general[..., 2])
        scales[pick] = sc
        angle = np.median(paths.path[pick, :, 2], axis=0)
        templates[label] = Template(label, int(pick.sum()), paths.s, np.column_stack([template, angle]),
                                    np.median(starts[pick], axis=0))
    return templates, scales


def _normalised(scale: np.ndarray) -> np.ndarray:
    """Scales (K, 2) clipped to a sane range and divided by their geometric mean."""
    scale = np.clip(scale, 0.05, 20.0)
    return scale / np.exp(np.log(scale).mean(axis=0))


def _template(xy: np.ndarray, window: np.ndarray) -> np.ndarray:
    """The median path (N, 2) of digs (K, N, 2), each sample over the digs outside a
    redirection's `window` (K, N) there (all of them where none is)."""
    out = np.where(window[..., None] > 0.5, np.nan, xy)
    none = np.all(np.isnan(out[..., 0]), axis=0)
    out[:, none] = xy[:, none]
    return np.nanmedian(out, axis=0)


def event_shape(tau: np.ndarray, centre: np.ndarray, width: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Event shapes (G, T) over time fraction `tau` (T,): a raised-cosine pulse (temporary)
    or a minimum-jerk step (kept) at `centre` (G,) of half-width `width` (G,)."""
    x = (tau[None] - centre[:, None]) / width[:, None]
    kept = np.asarray(kept, dtype=bool)[:, None]
    inside = np.abs(x) < 1
    # flat outside the event (0, or 1 after a step): the cosine and the polynomial are
    # taken only within it, a fifth of the samples, and only each row's own one
    out = np.where(kept & (x >= 1), 1.0, 0.0)
    pulse, step = inside & ~kept, inside & kept
    out[pulse] = 0.5 * (1 + np.cos(np.pi * x[pulse]))
    y = (x[step] + 1) / 2
    out[step] = y**3 * (10 + y * (-15 + 6 * y))
    return out


def _events(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Event shapes (G, T) over time fraction `tau` (T,): pulses and steps at a grid of
    centres and half-widths; their kept flag (G,), centre (G,), half-width (G,)."""
    centre = np.arange(0.15, 0.851, 0.025)
    width = np.array([0.06, 0.1, 0.14])
    c, w = (np.tile(v.ravel(), 2) for v in np.meshgrid(centre, width, indexing="ij"))
    kept = np.repeat([False, True], len(c) // 2)
    return event_shape(tau, c, w, kept), kept, c, w


@dataclass(frozen=True)
class DigChannels:
    """One dig's frames (T,) as its general shape and scale are taken from: the tip's reach
    `r` and height `z` (m) low-passed (the reactive variations' wiggles would lengthen the
    arc and shift every sample along it), bucket angle (rad); its redirection's shape in
    time `event` (0 to 1, a step when kept, a pulse when temporary, low-passed like the
    path; zeros without one), `late` 1 after it and `inside` 1 within it, widened by the
    margin either side (the low-pass spreads it); `kept` whether the event is a step."""

    r: np.ndarray
    z: np.ndarray
    angle: np.ndarray
    event: np.ndarray
    late: np.ndarray
    inside: np.ndarray
    kept: bool = False


def dig_channels(series: TipSeries, starts: np.ndarray, ends: np.ndarray, dev: Deviations | None = None,
                 cutoff_hz: float = PATH_CUTOFF_HZ, margin_s: float = 0.5) -> list[DigChannels]:
    """`DigChannels` of every dig [start, end] (indices): the path low-passed at `cutoff_hz`,
    each redirection of `dev` (if given) at the place and width its event fit found, its
    window widened by `margin_s`."""
    sos = butter(2, cutoff_hz, fs=series.rate, output="sos")
    reach, height = (sosfiltfilt(sos, v) for v in (series.raw_reach, series.raw_height))
    pad = int(round(3.0 * series.rate))
    out = []
    for k, (a, b) in enumerate(zip(starts, ends)):
        m = b - a + 1
        event, late, inside = np.zeros(m), np.zeros(m), np.zeros(m)
        kept = dev is not None and dev.redirection[k] == "kept"
        if dev is not None and dev.redirection[k] != "none":
            tau = np.arange(-pad, m + pad) / max(b - a, 1)
            centre, width = dev.redirection_centre[k], dev.redirection_width[k]
            shape = event_shape(tau, np.array([centre]), np.array([width]),
                                np.array([kept]))[0]
            event = sosfiltfilt(sos, np.where(tau < 0, 0.0, shape))[pad:pad + m]
            wide = width + margin_s / max(series.time[b] - series.time[a], 1e-9)
            tau = tau[pad:pad + m]
            late, inside = (tau >= centre + wide).astype(float), (np.abs(tau - centre) < wide).astype(float)
        out.append(DigChannels(reach[a:b + 1], height[a:b + 1], series.angle[a:b + 1], event, late, inside, kept))
    return out


def general_paths(channels: list[DigChannels], lift: np.ndarray | None = None,
                  n: int = N_SAMPLES) -> tuple[DigPaths, np.ndarray, np.ndarray]:
    """Each dig's `channels` resampled at `n` points of normalised arc length, less its
    redirection's `lift` (K,) m times its event's shape in time, so that the arc is that of
    the dig without it; also (K, N) `after`, 1 at the samples after the redirection, and
    (K, N) `window`, 1 within it (both zero for the digs without one)."""
    s = np.linspace(0.0, 1.0, n)
    lift = np.zeros(len(channels)) if lift is None else lift
    out = np.empty((len(channels), n, 3))
    after, window = np.zeros((len(channels), n)), np.zeros((len(channels), n))
    for k, dig in enumerate(channels):
        z = dig.z - lift[k] * dig.event
        u = _arc(dig.r, z)
        for d, v in enumerate((dig.r - dig.r[0], z - z[0], dig.angle)):
            out[k, :, d] = np.interp(s, u, v)
        after[k], window[k] = np.interp(s, u, dig.late), np.interp(s, u, dig.inside)
    return DigPaths(s, out), after, window


def fit_lifts(channels: list[DigChannels], labels: np.ndarray, templates: dict[str, Template], scales: np.ndarray,
              n: int = N_SAMPLES, span: float = 0.15, steps: int = 31, iterations: int = 3,
              whole: bool = False) -> np.ndarray:
    """The lift (K,) m of each dig's redirection (0 without one): the height of its event's
    own shape in time (a step when kept, a pulse when temporary) that, taken out of the
    tip's height before the arc length is taken, lets its class template (N, 2), scaled by
    a least-squares stretch, fit the dig best outside the event's window. In arc length a
    kept lift and a taller dig are nearly alike (a lift along a steep rise lies almost along
    the path), so the lift is not fitted there as a column: the whole path is taken again
    for each of `steps` heights over +-`span` of the dig's length, and a parabola through
    the best three gives the minimum. `scales` (K, 2) the digs' current stretch. With
    `whole`, a temporary event's lift is judged over the whole path, its window included: a
    pulse leaves no trace outside its window but the arc's lengthening, so that is where it
    is measured (the height reported); the scales, which leave the window out, are taken
    without it. A dig of no shovel class (`other`: a backhoe's) has its lift judged over
    the whole path always: the window is left out for a shovel dig's floor push, which
    bends into the rise there and differs from dig to dig more than a stretch follows; a
    backhoe dig has none, and its window is most of what tells a lift from a taller dig."""
    s = np.linspace(0.0, 1.0, n)
    lift = np.zeros(len(channels))
    grid = np.linspace(-span, span, steps)
    for k, dig in enumerate(channels):
        if not dig.event.any() or labels[k] not in templates:
            continue
        template = templates[labels[k]].path[:, :2]
        length = np.hypot(np.diff(dig.r), np.diff(dig.z)).sum()
        heights = grid * length
        z = dig.z[None] - heights[:, None] * dig.event[None]  # (G, T)
        stretch = np.tile(scales[k], (len(z), 1))
        r, inside = np.broadcast_to(dig.r, z.shape), np.broadcast_to(dig.inside, z.shape)
        for _ in range(iterations):  # the arc of the path divided by its own stretch, as build_templates takes it
            step = np.hypot(np.diff(dig.r)[None] / stretch[:, :1], np.diff(z, axis=1) / stretch[:, 1:])
            arc = np.concatenate([np.zeros((len(z), 1)), np.cumsum(step, axis=1)], axis=1)
            arc /= np.maximum(arc[:, -1:], 1e-12)
            path = np.stack([_interp_rows(s, arc, r) - dig.r[0], _interp_rows(s, arc, z) - z[:, :1]], axis=-1)
            everywhere = (whole and not dig.kept) or labels[k] == OTHER
            weight = np.ones_like(path[..., 0]) if everywhere else 1.0 - _interp_rows(s, arc, inside)
            stretch = np.clip(fit_scales(path, template, weight), 0.05, 20.0)
        sse = (weight[..., None] * (path - stretch[:, None, :] * template[None]) ** 2).sum(axis=(1, 2))
        g = int(np.clip(np.argmin(sse), 1, len(grid) - 2))
        y0, y1, y2 = sse[g - 1:g + 2]
        curve = y0 - 2 * y1 + y2
        shift = 0.5 * (y0 - y2) / curve if curve > 0 else 0.0
        lift[k] = heights[g] + np.clip(shift, -1.0, 1.0) * (heights[1] - heights[0])
    return lift


def _interp_rows(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """`np.interp` of every row (G, N) at `x` (N,) in [0, 1], the rows' sample places `xp`
    (G, T) increasing from 0 to 1 and values `fp` (G, T): one call, each row shifted by
    twice its index so that the rows follow one another."""
    shift = 2.0 * np.arange(len(xp))[:, None]
    return np.interp((x[None] + shift).ravel(), (xp + shift).ravel(), fp.ravel()).reshape(len(xp), len(x))


def _fit_events(ys: tuple[np.ndarray, ...], base: np.ndarray,
                shapes: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Least squares of each y (T,) of `ys` on base columns (T, B) plus each event (G, T):
    per y the SSE (G,) and event amplitudes (G,), and the SSE with the base alone. The base
    is projected out of y and of every event first (Frisch-Waugh), so each event is a
    one-column fit; the events' projection, the costly part, is shared by all of `ys`."""
    q, _ = np.linalg.qr(base)
    rs = shapes - (shapes @ q) @ q.T
    norm = np.maximum(np.einsum("gt,gt->g", rs, rs), 1e-12)
    fits = []
    for y in ys:
        ry = y - q @ (q.T @ y)
        sy = rs @ ry
        amp = sy / norm
        sse0 = float(ry @ ry)
        fits.append((sse0 - sy * amp, amp, sse0))
    return fits


def deviations(series: TipSeries, starts: np.ndarray, ends: np.ndarray,
               scales: np.ndarray, min_angle_deg: float = 4.0, max_unexplained: float = 0.4,
               slow_angle_deg: float = 6.0, slow_unexplained: float = 1.0, cutoff_hz: float = 0.6) -> Deviations:
    """Reactive RMS and operator redirections of every dig [start, end] (indices).

    A redirection is an event (a pulse or a step of the grid of `_events`) that turns the
    bucket by at least `min_angle_deg` and leaves at most `max_unexplained` of the squared
    residual of the bucket angle about a quintic in time: the classes' angle profiles are
    smooth in time, while the height's are not (the floor push bends into the rise within
    a second, as fast as an event), so the angle alone says whether there is one. A slow
    kept step is partly absorbed by the quintic; it is also a redirection when it turns the
    bucket by at least `slow_angle_deg` and the same event explains the angle about a cubic
    in arc length and the height about a quintic in time together, leaving at most
    `slow_unexplained` of their squared residuals (the two shares added, of 2). Its lift is
    the same event fitted to the tip's height about a quintic in time.
    """
    k = len(starts)
    sos = butter(2, cutoff_hz, fs=series.rate, output="sos")
    reactive_m, reactive_deg = np.full(k, np.nan), np.full(k, np.nan)
    kind = np.full(k, "none", dtype=object)
    what = np.full(k, "", dtype=object)
    when, d_angle, lift = np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.nan)
    at, half = np.full(k, np.nan), np.full(k, np.nan)
    back, lengths = np.zeros(k, bool), np.zeros(k)
    for i, (a, b) in enumerate(zip(starts, ends)):
        r, z, angle = series.raw_reach[a:b + 1], series.raw_height[a:b + 1], series.raw_angle[a:b + 1]
        lengths[i] = np.hypot(np.diff(series.reach[a:b + 1]), np.diff(series.height[a:b + 1])).sum()
        if len(r) > 15:  # the three channels low-passed in one call (a call's set-up costs more than its filtering)
            low = sosfiltfilt(sos, np.stack([r, z, angle]), padlen=min(len(r) - 1, 3 * 6))
            reactive_m[i] = np.sqrt(((r - low[0]) ** 2 + (z - low[1]) ** 2).mean())
            reactive_deg[i] = np.degrees(np.sqrt(((angle - low[2]) ** 2).mean()))
        if b - a < MIN_EVENT_FRAMES:  # too short to tell an event from the smooth profile
            continue
        tau = np.linspace(0.0, 1.0, b - a + 1)
        shapes, kept, centre, width = _events(tau)
        base = np.vander(tau, 6, increasing=True)
        (sse_a, amp, sse0_a), (sse_z, amp_z, sse0_z) = _fit_events((series.angle[a:b + 1], series.height[a:b + 1]),
                                                                    base, shapes)
        g = int(np.argmin(sse_a))
        if sse_a[g] > max_unexplained * sse0_a or abs(np.degrees(amp[g])) < min_angle_deg:
            u = _arc(series.reach[a:b + 1], series.height[a:b + 1])
            [(sse_u, amp, sse0_u)] = _fit_events((series.angle[a:b + 1],), np.vander(u, 4, increasing=True), shapes)
            unexplained = sse_u / max(sse0_u, 1e-12) + sse_z / max(sse0_z, 1e-12)
            g = int(np.argmin(unexplained))
            if unexplained[g] > slow_unexplained or abs(np.degrees(amp[g])) < slow_angle_deg:
                continue
        kind[i] = "kept" if kept[g] else "temporary"
        when[i] = series.time[a] + centre[g] * (series.time[b] - series.time[a])
        d_angle[i], lift[i], at[i], half[i] = amp[g], amp_z[g], centre[g], width[g]
        window = (tau > centre[g] - width[g]) & (tau < centre[g] + width[g])
        chord = np.array([series.reach[b] - series.reach[a], series.height[b] - series.height[a]])
        forward = np.diff(series.reach[a:b + 1]) * chord[0] + np.diff(series.height[a:b + 1]) * chord[1]
        back[i] = np.any(forward[window[1:]] < -1e-3 * np.linalg.norm(chord) / max(len(tau), 1))
        what[i] = _kind_words(kind[i], d_angle[i], lift[i], lengths[i], back[i])
    return Deviations(scales[:, 0], scales[:, 1], reactive_m, reactive_deg, kind, when, d_angle, lift, what, at, half,
                      back, lengths)
