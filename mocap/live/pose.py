"""The pose of each reference frame as it comes: every camera's labelled pixels placed on
the reference clock, the machine model fitted from the frame before (the batched kernel of
`mocap fit`), and a fixed-lag smoother that gives the row of the frame `lag` frames back.

No file or thread here: arrays in, arrays out (`mocap.live.run` wires them to the sources).
Shapes: C cameras, M markers, J joints, P parameters (the joints, then with base motion the
base's rotation vector and translation), W frames in the smoother's window.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass, replace
from time import thread_time

import numpy as np

from mocap.core.camera import Camera
from mocap.core.geometry import matrix_to_rotvec
from mocap.core.machine import Machine
from mocap.io.motion_csv import base_columns
from mocap.reconstruct.base_check import SAMPLE_FRAMES, compare_bases
from mocap.reconstruct.kinfit import FitOptions, FrameFitter, fit_joints
from mocap.reconstruct.kinmodel import base_matrices
from mocap.reconstruct.smooth import SmoothOptions, chi2_quantile, fit_sds, frame_correlation, smooth
from mocap.reconstruct.uncertainty import point_quantities

log = logging.getLogger(__name__)

_RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2))  # median of a 2-D residual's length over its per-axis SD
_NOISE_FRAMES = 90  # frames whose residuals give the pixel noise
_LONE_SHARE = 0.1  # a camera's frame this share of an interval from a time gives the markers seen in it alone
_RESTART_RATIO = 4.0  # a frame whose cost per observation is this much above the typical one is fitted from the grid
_LEAVE_OUT_SHARE = 0.25  # a frame no pose explains: at most this share of its observations left out ...
_LEAVE_OUT_CANDIDATES = 6  # ... one at a time, each the one of its worst residuals whose leaving out explains the most
_WORST_RATIO = 5.0  # ... until its worst residual left is within this many times the usual frame's worst
_PROCESS_NOISE_EVERY = 30  # frames between estimates of the smoother's process noise
_PROCESS_NOISE_FRAMES = 900  # ... from this many frames (30 s at 30 fps)
_GAP_FRAMES = 3  # frames without a fit after which the pose before them no longer starts the next fit
_FIRST_PROCESS_NOISE = 10.0  # (rad or m)^2 / s^3 until the window holds enough to estimate it: little smoothing
# the rows' covariance scale until the fits' scatter about the smoothed values is measured (the smallest the five
# random looks of bench_live measured at their end: 5.0-15.0), and the rows of measurement it counts for: the
# scale is their geometric mean weighed by the prior's rows and the rows measured (the data overrule it as they come)
PRIOR_SCALE = 4.0
_PRIOR_ROWS = 30
_PACE_FRAMES = 6  # the newest frames whose fits judge whether the process noise suits the motion's pace now
_PACE_PROBABILITY = 0.999  # their fits beyond this chi-square quantile of the smoothed values: the noise is raised
_PACE_FACTOR = 4.0  # ... by this factor at a time
_PACE_STEPS = 3  # ... at most this many times (64 times the estimate over the last 30 s)
_PACE_RUN = 3  # beyond every raise: the newest fits that must all contradict the smoothing for a faster motion
_BASE_FIRST = 60  # frames fitted before the first test of whether the base moves (2 s at 30 fps)
_BASE_EVERY = 150  # without a window: frames between the tests, each of up to `SAMPLE_FRAMES` spread over all so far
_BASE_MARGIN = 0.05  # a test changes the choice when the criterion's gain is this share past its penalty
BASE_WINDOW = 90  # the last frames each test fits (3 s at 30 fps) ...
_WINDOW_EVERY = 30  # ... and the frames between its tests


class CameraHistory:
    """A camera's last labelled frames: (time on the reference clock, pixels (M, 2)), at most
    `depth` (None: every frame not yet forgotten, for files read as fast as they are tracked,
    where a camera's tracker may run any way ahead of the rows)."""

    def __init__(self, fps: float, depth: int | None = 256):
        self.fps = fps
        self.frames: deque[tuple[float, np.ndarray]] = deque(maxlen=depth)

    def add(self, time: float, pixels: np.ndarray) -> None:
        self.frames.append((time, pixels))

    def forget(self, before: float) -> None:
        """Drop the frames older than `before` but the last of them (the one before a time asked)."""
        while len(self.frames) > 1 and self.frames[1][0] <= before:
            self.frames.popleft()

    @property
    def latest(self) -> float:
        return self.frames[-1][0] if self.frames else -np.inf

    def pixels_at(self, time: float) -> np.ndarray | None:
        """(M, 2) the markers at `time`: interpolated between the frames either side, or (the
        later frame not in yet, or a frame missed between them) extrapolated from the last two
        frames before at their velocity, up to one interval ahead; a marker in only one of the
        two, or every marker of the one frame near, taken from its frame only if that frame is
        within `_LONE_SHARE` of an interval of `time` (a marker's pixel half a frame old is
        half a frame's motion off: a marker going out of sight as the base bounced was 2-5 px
        off, the fit 3-7 cm at the tip); None if no frame is near."""
        if not self.frames:
            return None
        interval = 1.0 / self.fps
        times = np.array([t for t, _ in self.frames])
        before = np.flatnonzero(times <= time)
        after = np.flatnonzero(times >= time)
        if len(before) and len(after) and times[after[0]] - times[before[-1]] <= 1.5 * interval:
            a, b = self.frames[before[-1]], self.frames[after[0]]
        elif (len(before) >= 2 and time - times[before[-1]] <= interval
              and times[before[-1]] - times[before[-2]] <= 1.5 * interval):
            a, b = self.frames[before[-2]], self.frames[before[-1]]
        else:  # no two frames near: the nearest alone
            a = b = min((self.frames[k] for k in (*before[-1:], *after[:1])), key=lambda f: abs(f[0] - time))
        share = 0.0 if b[0] == a[0] else (time - a[0]) / (b[0] - a[0])
        both = a[1] + share * (b[1] - a[1])
        near = min((a, b), key=lambda f: abs(f[0] - time))
        alone = near[1] if abs(near[0] - time) <= _LONE_SHARE * interval else np.full_like(near[1], np.nan)
        pixels = np.where(np.isfinite(both), both, alone) if a is not b else alone
        return pixels if np.isfinite(pixels).any() else None


@dataclass(frozen=True)
class FrameFit:
    """One frame's fit: values (P,), information (P, P) (the normal matrix over the pixel
    noise²), valid, rms_px, observations; `base_moves` when the base's pose was fitted (a
    fit with a fixed base, its values' base part zero and unobserved, when it was not)."""

    values: np.ndarray
    information: np.ndarray
    valid: bool
    rms_px: float
    observations: int
    base_moves: bool = False


class _BaseTest(threading.Thread):
    """`compare_bases` on a sample of frames; `check` (frames fitted when it began, its answer
    or None, its CPU seconds) once run."""

    def __init__(self, machine, cameras, pixels, start, options, frames: int):
        super().__init__(name="base test", daemon=True)
        self.args, self.frames, self.check = (machine, cameras, pixels, start, options), frames, None

    def run(self) -> None:
        began = thread_time()
        try:
            answer = compare_bases(*self.args)
        except (ValueError, np.linalg.LinAlgError) as exc:  # the sample's fits failed: no answer this time
            log.warning("the test of whether the base moves failed after %d frames: %s", self.frames, exc)
            answer = None
        self.check = (self.frames, answer, thread_time() - began)


class WarmFit:
    """The machine fitted frame after frame, each from the frame before's parameters moved on
    at their last velocity (with the base moving, the base's pose too); the first frame, and
    one that ends far worse than is typical, from the whole fit's grid and restarts
    (`fit_joints`). The pixel noise behind the information
    is estimated from the last frames' residuals (or `options.noise_px`).

    With `choose_base` (and a fixed base in `options`) the base is held where the calibration
    saw it or fitted per frame as the data say, with `mocap fit`'s test
    (`mocap.reconstruct.base_check.compare_bases`): the first after `_BASE_FIRST` frames, then
    every `_WINDOW_EVERY`, on the last `base_window` frames (the base fitted per frame while
    the recent frames show it moving, as while the bucket digs, and held while they do not);
    with `base_window` None, every `_BASE_EVERY` on up to `SAMPLE_FRAMES` frames spread over
    all the frames so far (as `mocap fit` spreads them over the session);
    each test decides until the next; until the first the base is fitted per frame (a base
    that moves is followed from the first frame; one that holds still costs the first frames
    only the base's noise), and the first test decides on the criterion alone (the start was
    no answer of the data); a change after needs the criterion's gain `_BASE_MARGIN` past its
    penalty (tests near the line do not flap); with
    `background` the tests run on their own thread and their answer is taken at the first
    frame after. The values then always carry the base's six parameters (zero and unobserved
    while it is held). A frame with fewer markers seen than the moving base's parameters is
    fitted with the base held, chosen or with `options.base_motion` (its pose and the joints
    would not be told apart)."""

    def __init__(self, machine: Machine, cameras: list[Camera], options: FitOptions | None = None,
                 choose_base: bool = False, background: bool = True,
                 base_window: int | None = BASE_WINDOW):
        self.machine, self.cameras = machine, list(cameras)
        self.window = base_window
        self.options = options or FitOptions()
        self.choose_base = choose_base and not self.options.base_motion and machine.n_joints > 0
        self.base_moves = self.options.base_motion or self.choose_base  # chosen: fitted per frame until a test holds it
        both = self.choose_base or (self.base_moves and machine.n_joints > 0)  # a frame may hold the base
        self.fitters = {moves: FrameFitter(machine, self.cameras, replace(self.options, base_motion=moves))
                        for moves in ((False, True) if both else (self.base_moves,))}
        self.n_params = machine.n_joints + 6 * (self.choose_base or self.base_moves)
        self.last: deque[np.ndarray] = deque(maxlen=2)
        self.gap: tuple[np.ndarray, int] | None = None  # the last fit before frames without one, and those frames
        self.lengths: deque[np.ndarray] = deque(maxlen=_NOISE_FRAMES)
        self.per_obs: deque[float] = deque(maxlen=_NOISE_FRAMES)
        self.recent: list[tuple[np.ndarray, np.ndarray]] = []  # (pixels, joints) of every `stride`-th frame
        self.stride = 1
        self.kept = 0
        self.base_tests: list[tuple[int, bool]] = []  # (frames fitted then, the base moves)
        self.base_test_s = 0.0  # the tests' CPU time
        self.base_evidence: list[float] = []  # each test's gain in the information criterion over its penalty
        self.background = background
        self.testing: _BaseTest | None = None  # the test running
        self.left_out = 0  # frames fitted with observations left out (`_leave_out`)

    @property
    def fitter(self) -> FrameFitter:
        return self.fitters[self.base_moves]

    @property
    def warm(self) -> bool:
        """A frame before was fitted: the next starts from it."""
        return bool(self.last)

    @property
    def noise_px(self) -> float:
        if self.options.noise_px:
            return self.options.noise_px
        if not self.lengths:
            return 1.0
        return max(float(np.median(np.concatenate(self.lengths))) / _RAYLEIGH_MEDIAN, 0.05)

    def __call__(self, pixels: np.ndarray, keep: bool = True) -> FrameFit:
        """pixels (C, M, 2), NaN where not seen. `keep` False: a provisional fit (a camera's
        pixels extrapolated) that neither starts the next frame nor counts in the noise."""
        n_joints, n_params, moves = self.machine.n_joints, self.n_params, self.base_moves
        seen = np.isfinite(pixels[..., 0])
        n_obs = int(seen.sum())
        if moves and len(self.fitters) == 2 and n_obs < self.fitters[True].n_params:
            moves = False  # too few markers to tell the base's pose from the joints: the base held for this frame
        fitter = self.fitters[moves]
        if 2 * n_obs < fitter.n_params:
            if keep:
                if self.last:
                    self.gap = (self.last[-1], 0)
                self.last.clear()
                if self.gap is not None:
                    self.gap = (self.gap[0], self.gap[1] + 1)
            return FrameFit(np.full(n_params, np.nan), np.zeros((n_params, n_params)), False, np.nan, n_obs, moves)
        frame = pixels[:, None]
        usual = float(np.median(self.per_obs)) if self.per_obs else np.inf  # the cost per observation so far
        beyond = _RESTART_RATIO * usual + self.options.scale_px**2  # ... that no pose explaining the frame reaches
        if not self.last:
            state = self._from_grid(frame, moves)
            if self.gap is not None and self.gap[1] <= _GAP_FRAMES:
                # up to _GAP_FRAMES frames without a fit: the pose before them, as good a fit within the
                # noise, is the pose the machine was in; the grid's may be a mirror that explains
                # the pixels as well, metres off (a random digger's bucket, 11 m)
                held = self.gap[0]
                near = fitter.fit(frame, held[None, :n_joints], held[None, n_joints:] if moves else None)
                if near.cost[0] <= state.cost[0] + fitter.n_params * self.noise_px**2:
                    state = near
        else:
            start = self.last[-1] if len(self.last) < 2 else 2 * self.last[-1] - self.last[-2]
            state = fitter.fit(frame, start[None, :n_joints], start[None, n_joints:] if moves else None)
            if state.cost[0] / n_obs > beyond:
                again = self._from_grid(frame, moves)
                if again.cost[0] < state.cost[0]:
                    state = again
        if state.cost[0] / n_obs > beyond:
            # no pose explains the frame as the frames before were explained: an observation or a
            # few that are wrong (a marker labelled where another, or nothing of the machine, is)
            # are left out, if that explains the rest; else the frame is weighed as it is, below
            explained = self._leave_out(fitter, frame, seen, state, beyond, start if self.last else None)
            if explained is not None:
                state, seen = explained
                n_obs = int(seen.sum())
                if keep:
                    self.left_out += 1
                log.debug("%d observation(s) left out of a frame no pose explained with them",
                          int(np.isfinite(pixels[..., 0]).sum()) - n_obs)
        residual = state.residual[0].reshape(-1, 2)[seen.reshape(-1)]
        length = np.hypot(residual[:, 0], residual[:, 1])
        weight = state.weight[0].reshape(-1, 2)[seen.reshape(-1), 0]
        values = np.zeros(n_params)
        values[:n_joints] = state.joints[0]
        if state.rotation is not None:
            values[n_joints:] = np.r_[matrix_to_rotvec(state.rotation[:1])[0], state.translation[0]]
        information = np.zeros((n_params, n_params))
        fitted = state.hessian[0].shape[0]
        information[:fitted, :fitted] = state.hessian[0] / self.noise_px**2
        per_obs = float(state.cost[0] / n_obs)
        if per_obs > beyond:
            # even from the grid no pose explains this frame's pixels as the frames before were
            # explained (markers mislabelled in it): its residuals say its noise is that much
            # larger, and its information is that much less (the smoother weighs it as such)
            information /= per_obs / usual
        if keep:
            self.gap = None
            self.lengths.append(length)
            self.per_obs.append(per_obs)
            self.last.append(values)
            if self.choose_base:  # the test of the base without the observations left out
                self._test_base(np.where(seen[..., None], pixels, np.nan), values[:n_joints])
        rms = float(np.sqrt(np.sum(weight * length**2) / max(np.sum(weight), 1e-12)))
        return FrameFit(values, information, True, rms, n_obs, moves)

    def _test_base(self, pixels: np.ndarray, joints: np.ndarray) -> None:
        """Keep the frame for the test of the base, take a finished test's answer, and start
        the next test when it is time (with `background`, on its own thread: the rows do not
        wait for it)."""
        if self.window:
            self.recent.append((pixels, joints))
            del self.recent[:-self.window]
        elif self.kept % self.stride == 0:
            self.recent.append((pixels, joints))
            if len(self.recent) > 2 * SAMPLE_FRAMES:  # every other one kept: spread over all the frames so far
                self.recent = self.recent[::2]
                self.stride *= 2
        self.kept += 1
        if self.testing is not None and not self.testing.is_alive():
            self.testing.join()
            self._take(self.testing.check)
            self.testing = None
        every = _WINDOW_EVERY if self.window else _BASE_EVERY
        if self.kept < _BASE_FIRST or (self.kept - _BASE_FIRST) % every or self.testing is not None:
            return
        pick = np.unique(np.linspace(0, len(self.recent) - 1, min(SAMPLE_FRAMES, len(self.recent))).round().astype(int))
        test = _BaseTest(self.machine, self.cameras, np.stack([self.recent[k][0] for k in pick], axis=1),
                         np.stack([self.recent[k][1] for k in pick]), replace(self.options, base_motion=False),
                         self.kept)
        if self.background:
            self.testing = test
            test.start()
        else:
            test.run()
            self._take(test.check)

    def _take(self, check) -> None:
        """A test's answer (None: no answer): the base moves or is held from now on."""
        if check is None:
            return
        frames, check, cpu_s = check
        self.base_test_s += cpu_s
        if check is None:
            return
        evidence = check.evidence  # the information criterion's gain over its penalty (> 1: it moves)
        margin = _BASE_MARGIN if self.base_tests else 0.0  # the first test: no answer before it to hold to
        moves = evidence > (1.0 - margin if self.base_moves else 1.0 + margin)
        self.base_evidence.append(float(evidence))
        self.base_tests.append((frames, moves))
        if moves != self.base_moves:
            log.info("after %d frames the base %s (a base pose per frame leaves %.2f px of noise, the fixed base "
                     "%.2f px, over %d frames)", frames, "moves" if moves else "holds still",
                     check.moving_noise_px, check.fixed_noise_px, check.frames)
            self.base_moves = moves
            self.lengths.clear()  # the residuals and costs of the other model
            self.per_obs.clear()

    def _leave_out(self, fitter: FrameFitter, frame: np.ndarray, seen: np.ndarray, state, beyond: float,
                   start: np.ndarray | None):
        """The frame (C, 1, M, 2) whose fit `state` ends beyond `beyond` per observation, fitted
        again without its wrong observations: one at a time, of the `_LEAVE_OUT_CANDIDATES` worst
        residuals the one whose leaving out lowers the cost most (all of them fitted at once,
        from the fit so far and from `start`, the frame's prediction, values (P,)), until the
        cost per observation left is within `beyond` and the worst residual left within
        `_WORST_RATIO` times the usual frame's worst (the median over the last frames: a
        marker labelled far off is not hidden in the average of many); at most
        `_LEAVE_OUT_SHARE` of the observations, and the fit kept overdetermined twice over
        (twice as many coordinates as parameters). The new fit and the observations it used
        (C, M), or None if no such subset explains the frame."""
        n_joints, n_obs = self.machine.n_joints, int(seen.sum())
        worst = [float(length.max()) for length in self.lengths if len(length)]
        gate = _WORST_RATIO * float(np.median(worst)) if worst else np.inf
        most = min(int(_LEAVE_OUT_SHARE * n_obs), n_obs - fitter.n_params)
        used = seen.reshape(-1).copy()
        for left in range(1, most + 1):
            residual = state.residual[0].reshape(-1, 2)
            length = np.where(used, np.hypot(residual[:, 0], residual[:, 1]), -np.inf)
            candidates = np.argsort(-length)[:min(_LEAVE_OUT_CANDIDATES, n_obs - left + 1)]
            variants = np.repeat(np.where(used.reshape(seen.shape)[:, None, :, None], frame, np.nan),
                                 len(candidates), axis=1)  # (C, K, M, 2)
            camera, marker = np.unravel_index(candidates, seen.shape)
            variants[camera, np.arange(len(candidates)), marker] = np.nan
            values = np.r_[state.joints[0], matrix_to_rotvec(state.rotation[:1])[0], state.translation[0]] \
                if state.rotation is not None else state.joints[0]
            starts = np.stack([values] if start is None else [start[:len(values)], values])  # ties: the prediction
            starts = np.repeat(starts, len(candidates), axis=0)  # (S K, P): each start with every candidate
            trial = fitter.fit(np.tile(variants, (1, len(starts) // len(candidates), 1, 1)), starts[:, :n_joints],
                               starts[:, n_joints:] if state.rotation is not None else None)
            best = int(np.argmin(trial.cost))
            if not trial.cost[best] < state.cost[0]:
                return None
            state = trial.take(np.array([best]))
            used[candidates[best % len(candidates)]] = False
            residual = state.residual[0].reshape(-1, 2)[used]
            if state.cost[0] / (n_obs - left) <= beyond and np.hypot(residual[:, 0], residual[:, 1]).max() <= gate:
                return state, used.reshape(seen.shape)
        return None

    def _from_grid(self, frame: np.ndarray, moves: bool):
        """The frame (C, 1, M, 2) fitted as `mocap fit` fits a frame without a start."""
        fit = fit_joints(self.machine, self.cameras, frame, options=replace(self.options, base_motion=moves))
        base = None if fit.base is None else np.nan_to_num(fit.base)
        return self.fitters[moves].fit(frame, np.nan_to_num(fit.joints), base)


@dataclass(frozen=True)
class Pose:
    """A row's pose: joints (J,) and their SDs, named points (N, 3) and SDs (N,), bucket
    angle and SD (rad); `filled` when the smoother predicted it (no fit of its own); `base`
    the motion CSV's base columns with base motion (`base_columns`, without their SDs), else
    empty."""

    joints: np.ndarray
    joints_sd: np.ndarray
    points: np.ndarray
    points_sd: np.ndarray
    bucket_angle: float
    bucket_angle_sd: float
    filled: bool
    base: dict


def warm_up(machine: Machine, lag: int, base_motion: bool) -> None:
    """A throwaway smoother given a few still frames: its compiled kernel is loaded from numba's
    cache and the modules its rows import on first use are imported (0.5-0.6 s the first time
    in a process) before the cameras' clock starts, not while the first rows wait (5 of a
    20 s run's 583 rows 160-280 ms late: its p99)."""
    smoother = FixedLagSmoother(machine, lag, base_motion=base_motion)
    n_params = machine.n_joints + 6 * base_motion
    values = np.r_[machine.clip_to_limits(np.zeros(machine.n_joints)), np.zeros(6 * base_motion)]
    still = FrameFit(values, np.eye(n_params), True, 0.0, 0, base_moves=base_motion)
    for k in range(lag + 2):
        smoother.push(k / 30.0, still)


class FixedLagSmoother:
    """The Rauch-Tung-Striebel smoother of `mocap fit` (`mocap.reconstruct.smooth`) over a
    sliding window of the last `window` frames; a frame's pose is given `lag` frames after it
    came (lag 0: the filter's estimate, from the frames before only). The process noise is
    estimated as `mocap fit` does from the last `_PROCESS_NOISE_FRAMES` frames, every
    `_PROCESS_NOISE_EVERY` frames once they span `window` frames (before: little smoothing).

    That estimate is the motion's pace over half a minute: where the machine accelerates
    beyond it (a swing starting) the prediction would outweigh the frames' own fits and the
    rows trail the truth. So each row's smoothing is judged by its newest `_PACE_FRAMES` fits:
    their chi-square about the smoothed values (weighed by the fits' information), over the
    usual one (its median over the last rows: the fits' information may be overconfident), is
    held against the quantile `_PACE_PROBABILITY`; beyond it the process noise is raised
    `_PACE_FACTOR` times and the window smoothed again, up to `pace_steps` times: the smallest
    process noise the newest fits do not contradict. Fits that no raise tried explains leave
    it as it is where they are a failed fit or two; where the newest `_PACE_RUN` fits all
    contradict it, the motion is faster than any pace the window has shown (a joint that stood still
    for the whole estimate, then swings: its estimate is near 0, and no multiple of it
    follows), and the parameters they observe are smoothed as little as before the first
    estimate. `pace` is the factor of the last row given.

    The usual chi-square over its degrees of freedom (at least 1: `variance_factor`) is how
    much larger the fits' scatter is than their information says (pixel errors that are not
    independent: a rolling shutter, a marker's blur); the rows' covariances are multiplied by
    it, as `mocap fit` scales its SDs by the residuals, and by 1 + 2 rho for the fits'
    deviations' correlation rho from one frame to the next (`scale`). Both are measured only
    once the process noise has been estimated (before, the window is smoothed so little that
    the fits barely deviate from it); until they are, and while few rows have measured them,
    the scale leans on `prior_scale` (the rows' first seconds were otherwise the fits' own
    covariance: 43 of seed 1's 44 rows beyond 3 SDs were in its first 170 frames).

    With `base_motion` the values carry the base's six parameters after the joints; a fit
    whose base was held (`FrameFit.base_moves` False) has them unobserved. A row whose own fit
    held the base is smoothed over the joints alone (each fit's information on them with its
    base unknown: the moving base's fits count as they are, no more) and its base is the
    calibration's; one whose fit moved it, over all the parameters (the base unobserved in
    the fits that held it). The base's process noise is estimated from the fits that moved it."""

    def __init__(self, machine: Machine, lag: int, window: int = 60, options: SmoothOptions | None = None,
                 base_motion: bool = False, pace_steps: int = _PACE_STEPS, prior_scale: float = PRIOR_SCALE):
        if lag < 0 or window <= lag:
            raise ValueError(f"need 0 <= lag < window, got lag {lag}, window {window}")
        self.machine, self.lag, self.window = machine, lag, window
        self.options = options or SmoothOptions()
        self.time: deque[float] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.values: deque[np.ndarray] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.information: deque[np.ndarray] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.joint_information: deque[np.ndarray] = deque(maxlen=_PROCESS_NOISE_FRAMES)  # the base unknown
        self.valid: deque[bool] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.moving: deque[bool] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.base_motion = base_motion
        self.wrap = np.r_[machine.wraps, np.zeros(6 * base_motion, bool)]
        self.process_noise = np.full(len(self.wrap), _FIRST_PROCESS_NOISE)
        self.count = 0
        self.pending = 0  # frames pushed whose pose is not given yet
        self.pace = np.ones(len(self.wrap))
        self.pace_steps = pace_steps
        self.prior_scale = prior_scale
        self.disagreement: deque[float] = deque(maxlen=_PROCESS_NOISE_FRAMES)  # the newest fits' chi-square / dof
        self.scatter: deque[float] = deque(maxlen=_PROCESS_NOISE_FRAMES)  # the same over its expectation
        self.variance_factor = 1.0
        self.correlations: deque[float] = deque(maxlen=_PROCESS_NOISE_FRAMES)
        self.correlation = 0.0
        self.estimated = False  # the process noise estimated once

    @property
    def scale(self) -> float:
        """The rows' covariance scale: the fits' scatter over their information times
        1 + 2 rho for their correlation, as measured, and `prior_scale` until it is (the
        two's geometric mean, the prior counting for `_PRIOR_ROWS` rows of measurement)."""
        measured = self.variance_factor * (1 + 2 * max(self.correlation, 0.0))
        rows = min(len(self.scatter), len(self.correlations))
        share = rows / (rows + _PRIOR_ROWS) if _PRIOR_ROWS else 1.0
        return float(np.exp(share * np.log(measured) + (1 - share) * np.log(self.prior_scale)))

    def push(self, time: float, fit: FrameFit) -> Pose | None:
        """Add a frame; the pose of the frame `lag` back once there is one."""
        self.time.append(time)
        self.values.append(fit.values)
        self.information.append(fit.information)
        self.joint_information.append(self._joint_information(fit.information))
        self.valid.append(fit.valid)
        self.moving.append(bool(fit.base_moves) and self.base_motion)
        self.count += 1
        self.pending += 1
        if self.count % _PROCESS_NOISE_EVERY == 0 and self.count >= self.window:
            self._estimate_process_noise()
        if self.pending <= self.lag:
            return None
        self.pending -= 1
        return self._pose(len(self.time) - 1 - self.lag)

    def revise(self, fit: FrameFit) -> None:
        """Replace the newest frame's fit (a provisional one, by the frame's own once all its
        cameras are in); its pose, not given yet, follows from this one."""
        self.values[-1], self.information[-1], self.valid[-1] = fit.values, fit.information, fit.valid
        self.joint_information[-1] = self._joint_information(fit.information)
        self.moving[-1] = bool(fit.base_moves) and self.base_motion

    def flush(self) -> list[Pose]:
        """The poses not yet given (the last `lag` frames), from the frames there are."""
        out = [self._pose(len(self.time) - k) for k in range(self.pending, 0, -1)]
        self.pending = 0
        return out

    def _joint_information(self, information: np.ndarray) -> np.ndarray:
        """(J, J) the joints' information with the base's parameters unknown (its Schur complement)."""
        n_joints = self.machine.n_joints
        if not self.base_motion:
            return information
        joints, cross = information[:n_joints, :n_joints], information[:n_joints, n_joints:]
        return joints - cross @ np.linalg.pinv(information[n_joints:, n_joints:]) @ cross.T

    def _arrays(self, frames: int):
        """The last `frames` frames' time (W,), values (W, P), information (W, P, P), valid (W,),
        moving (W,), joints' information (W, J, J)."""
        first = max(len(self.time) - frames, 0)
        return tuple(np.array([x[k] for k in range(first, len(x))])
                     for x in (self.time, self.values, self.information, self.valid, self.moving,
                               self.joint_information))

    def _estimate_process_noise(self) -> None:
        time, values, information, valid, moving, joints_information = self._arrays(_PROCESS_NOISE_FRAMES)
        if valid.sum() < 3:
            return
        estimate = replace(self.options, process_noise=None)
        self.estimated = True
        if not self.base_motion or moving[valid].all():
            result = smooth(time, values, information, valid, self.wrap, estimate)
            self.process_noise = np.maximum(result.process_noise, 1e-6)
            return
        n_joints = self.machine.n_joints
        joints = smooth(time, values[:, :n_joints], joints_information, valid, self.wrap[:n_joints], estimate)
        self.process_noise[:n_joints] = np.maximum(joints.process_noise, 1e-6)
        moved = valid & moving
        if moved.sum() >= self.window:
            result = smooth(time[moved], values[moved], information[moved], valid[moved], self.wrap, estimate)
            self.process_noise[n_joints:] = np.maximum(result.process_noise[n_joints:], 1e-6)

    def _pose(self, at: int) -> Pose:
        time, values, information, valid, moving, joints_information = self._arrays(self.window)
        at -= len(self.time) - len(time)
        machine, n_joints, n_params = self.machine, self.machine.n_joints, len(self.wrap)
        if not valid[: at + 1 + self.lag].any():
            nan = np.full(n_params, np.nan)
            return _pose(machine, nan, np.full((n_params, n_params), np.nan), True, self.base_motion)
        columns = n_params if moving[at] or not self.base_motion else n_joints
        if columns < n_params:  # the base held: the joints alone
            values, information = values[:, :n_joints], joints_information
        result, pace = self._smooth_at_pace(time, values, information, valid, self.wrap[:columns],
                                            self.process_noise[:columns])
        self.pace = np.r_[pace, np.ones(n_params - columns)]
        values = np.zeros(n_params)
        values[:columns] = result.values[at]
        covariance = np.zeros((n_params, n_params))
        scale = self.scale  # the fits' scatter, their correlation
        covariance[:columns, :columns] = result.covariance[at] * scale
        limits = machine.joint_limits
        span = limits[:, 1] - limits[:, 0]
        joints = values[:n_joints]
        wrapped = limits[:, 0] + np.mod(joints - limits[:, 0], np.where(machine.wraps, span, 1.0))
        values[:n_joints] = np.where(machine.wraps, wrapped, joints)
        return _pose(machine, values, covariance, bool(result.filled[at]), self.base_motion)

    def _smooth_at_pace(self, time, values, information, valid, wrap, process_noise):
        """The window smoothed with the smallest multiple of the process noise that its newest
        fits do not contradict, raised for the parameters those fits observe (none explains
        them: the estimate itself). The result and the multiples (P,). Updates
        `variance_factor`."""
        newest = slice(max(len(time) - _PACE_FRAMES, 0), None)
        base = np.ones(len(wrap))
        first = smooth(time, values, information, valid, wrap, replace(self.options, process_noise=process_noise))
        kept = valid[newest] & ~first.rejected[newest]
        typical = _typical_sd(information, valid & np.isfinite(values).all(1))
        statistic, dof, observed = _disagreement(values[newest], information[newest], kept, first.values[newest],
                                                 wrap, typical, self.options.unobserved_factor)
        if not dof:
            return first, base
        self.disagreement.append(statistic / dof)
        usual = max(float(np.median(self.disagreement)) * dof / chi2_quantile(0.5, dof), 1.0)
        if self.estimated:  # before, the window is smoothed little: the fits' scatter about it shows nothing
            self._scale_variance(statistic, values[newest], information[newest], kept, first.covariance[newest], dof)
            self._correlation(values, information, valid & ~first.rejected, first.values, wrap)
        limit = usual * chi2_quantile(_PACE_PROBABILITY, dof)
        if statistic <= limit or not observed.any() or not self.pace_steps:
            return first, base
        for step in range(1, self.pace_steps + 1):
            factor = np.where(observed, _PACE_FACTOR**step, 1.0)
            result = smooth(time, values, information, valid, wrap,
                            replace(self.options, process_noise=factor * process_noise))
            statistic, _, _ = _disagreement(values[newest], information[newest], kept, result.values[newest],
                                            wrap, typical, self.options.unobserved_factor)
            if statistic <= limit:
                return result, factor
        # no raise tried explains them: a failed fit or two (a mirror solution in a frame
        # whose markers hardly tell) leave the smoothing as it is, but the newest fits all
        # contradicting it, frame after frame, are a motion faster than any pace the window has
        # shown (a joint still for the whole estimate, then swinging: its estimated noise is
        # near 0 and no multiple of it follows): those parameters are smoothed as little as
        # before the first estimate
        each = _frame_disagreement(values[newest], information[newest], kept, first.values[newest], wrap)
        contradicting = (each > usual * chi2_quantile(_PACE_PROBABILITY, values.shape[1]))[kept]
        if len(contradicting) < _PACE_RUN or not contradicting[-_PACE_RUN:].all():
            return first, base
        raised = np.where(observed, np.maximum(process_noise * _PACE_FACTOR**self.pace_steps, _FIRST_PROCESS_NOISE),
                          process_noise)
        result = smooth(time, values, information, valid, wrap, replace(self.options, process_noise=raised))
        return result, raised / process_noise


    def _scale_variance(self, statistic: float, measured: np.ndarray, information: np.ndarray, kept: np.ndarray,
                        covariance: np.ndarray, dof: int) -> None:
        """`variance_factor`: the newest fits' chi-square about the smoothed values over what the
        model expects of it (a fit's deviation from the smoothed value has the fit's covariance
        less the smoothed one: its expectation is P - tr(information x smoothed covariance)),
        its median over the last rows, at least 1."""
        kept = kept & np.isfinite(measured).all(1) & np.isfinite(covariance).all((1, 2))
        expected = float(np.sum(kept) * measured.shape[1] - np.einsum("kij,kji->", information[kept], covariance[kept]))
        if expected <= 0.1 * dof:
            return
        self.scatter.append(statistic / expected)
        self.variance_factor = max(float(np.median(self.scatter)) * dof / chi2_quantile(0.5, dof), 1.0)


    def _correlation(self, measured, information, valid, smoothed, wrap) -> None:
        """`correlation`: the window's fits' deviations from the smoothed values, frame to next
        frame, weighed by the fits' information (`frame_correlation`, as `mocap fit` scales its
        SDs): its median over the last rows."""
        rho = frame_correlation(measured, information, valid, smoothed, wrap)
        if rho is None:
            return
        self.correlations.append(rho)
        self.correlation = float(np.median(self.correlations))


def _wrapped(difference: np.ndarray, wrap: np.ndarray) -> np.ndarray:
    """`difference` (K, P), its angles (the columns `wrap` (P,)) taken into [-pi, pi), in place."""
    difference[:, wrap] = np.mod(difference[:, wrap] + np.pi, 2 * np.pi) - np.pi
    return difference


def _disagreement(measured: np.ndarray, information: np.ndarray, valid: np.ndarray, smoothed: np.ndarray,
                  wrap: np.ndarray, typical_sd: np.ndarray, unobserved_factor: float) -> tuple[float, int, np.ndarray]:
    """The chi-square of the fits measured (K, P) with information (K, P, P) about the
    smoothed values (K, P) (angles in `wrap` compared modulo 2 pi), frames not `valid` left
    out; its degrees of freedom; and the parameters (P,) observed in every frame kept (their
    fit's SD within `unobserved_factor` times `typical_sd` (P,), as `smooth` tells)."""
    valid = valid & np.isfinite(measured).all(1) & np.isfinite(smoothed).all(1)
    difference = _wrapped(measured[valid] - smoothed[valid], wrap)
    if not valid.any():
        return 0.0, 0, np.zeros(measured.shape[1], bool)
    observed = np.all(fit_sds(information[valid]) <= unobserved_factor * typical_sd, axis=0)
    return float(np.einsum("ki,kij,kj->", difference, information[valid], difference)), difference.size, observed


def _frame_disagreement(measured: np.ndarray, information: np.ndarray, valid: np.ndarray, smoothed: np.ndarray,
                        wrap: np.ndarray) -> np.ndarray:
    """(K,) each fit's chi-square (`_disagreement`'s terms per frame; 0 where not `valid`)."""
    difference = np.nan_to_num(_wrapped(np.where(valid[:, None], measured - smoothed, 0.0), wrap))
    return np.einsum("ki,kij,kj->k", difference, np.nan_to_num(information), difference)


def _typical_sd(information: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(P,) the median over the `valid` frames of each parameter's fit SD (information (W, P, P))."""
    if not valid.any():
        return np.full(information.shape[1], np.inf)
    return np.median(fit_sds(information[valid]), axis=0)


def _pose(machine: Machine, values: np.ndarray, covariance: np.ndarray, filled: bool, base_motion: bool) -> Pose:
    """The row's quantities of parameters (P,) with covariance (P, P)."""
    n_joints = machine.n_joints
    quantities = point_quantities(machine, values[None], covariance[None], base_motion)
    sd = np.sqrt(np.abs(np.diagonal(covariance)))[:n_joints]
    base = {}
    if base_motion:
        columns = base_columns(base_matrices(np.nan_to_num(values[None, n_joints:])))  # SDs: 4 ms a row more
        base = {name: float(value[0]) if np.isfinite(values[n_joints:]).all() else np.nan
                for name, value in columns.items()}
    return Pose(values[:n_joints], sd, quantities.points[0], quantities.points_sd[0],
                float(quantities.bucket_angle[0]),
                float(quantities.bucket_angle_sd[0]) if quantities.bucket_angle_sd is not None else np.nan, filled,
                base)
